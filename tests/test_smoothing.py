"""The smoother behind the data-driven first trajectory."""

import torch

from torchql.smoothing import MAX_SMOOTHED_POINTS, smooth

DT = torch.float64


def test_exact_smooth_data_are_kept_to_interpolation_accuracy():
    t = torch.arange(14, dtype=DT) * 0.5
    y = torch.exp(-0.05 * t) * torch.sin(1.7 * t)
    assert (smooth(t, y) - y).abs().max() < 1e-8


def test_noise_is_reduced_and_slopes_become_usable():
    g = torch.Generator().manual_seed(0)
    t = torch.linspace(0, 20, 401, dtype=DT)
    truth = 2 * torch.sin(t)
    noisy = truth + 0.05 * torch.randn(401, generator=g, dtype=DT)
    z = smooth(t, noisy)
    rms = lambda e: e.square().mean().sqrt().item()  # noqa: E731
    assert rms(z - truth) < 0.5 * rms(noisy - truth)
    slope = lambda v: torch.gradient(v, spacing=(t,))[0]  # noqa: E731
    assert rms(slope(z) - 2 * torch.cos(t)) < 0.25 * rms(slope(noisy) - 2 * torch.cos(t))


def test_uneven_times_and_weights():
    g = torch.Generator().manual_seed(1)
    t = torch.sort(torch.rand(60, generator=g, dtype=DT) * 10).values
    truth = torch.cos(t)
    noisy = truth + 0.02 * torch.randn(60, generator=g, dtype=DT)
    z = smooth(t, noisy, torch.full((60,), 1 / 0.02**2, dtype=DT))
    assert (z - truth).square().mean() < (noisy - truth).square().mean()
    # a value with a huge weight is kept
    w = torch.ones(60, dtype=DT)
    w[30] = 1e12
    assert abs(smooth(t, noisy, w)[30] - noisy[30]) < 1e-6


def test_short_and_very_long_series_are_returned_unchanged():
    t = torch.tensor([0.0, 1.0, 2.0], dtype=DT)
    y = torch.tensor([1.0, 5.0, -2.0], dtype=DT)
    assert torch.equal(smooth(t, y), y)
    n = MAX_SMOOTHED_POINTS + 1
    t = torch.linspace(0, 1, n, dtype=DT)
    assert torch.equal(smooth(t, torch.sin(t)), torch.sin(t))
