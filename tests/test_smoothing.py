"""The smoother behind the data-driven first trajectory."""

import pytest
import torch

from torchql.smoothing import MAX_SMOOTHED_POINTS, SUMMED_POINTS, SUMMED_SERIES, interpolate, interpolate_each, smooth, smooth_each

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


def test_short_series_are_returned_unchanged():
    t = torch.tensor([0.0, 1.0, 2.0], dtype=DT)
    y = torch.tensor([1.0, 5.0, -2.0], dtype=DT)
    assert torch.equal(smooth(t, y), y)


def test_a_very_long_series_is_smoothed_through_the_means_of_its_runs():
    """20,000 values of sin(3 t) with noise 0.1 (longer than MAX_SMOOTHED_POINTS): smoothed through the
    means of runs of 80 points (SMOOTHED_MEANS), two series at once alike, and each as smooth_each gives it. The error
    is far below the noise (it was returned as given: the data-built start of a fit then matched slopes
    of the raw noise)."""
    T = 20 * MAX_SMOOTHED_POINTS
    t = torch.linspace(0, 14, T, dtype=DT)
    clean = torch.sin(3 * t)
    noise = 0.1 * torch.randn(2, T, generator=torch.Generator().manual_seed(4), dtype=DT)
    y = (clean + noise).T  # (T, 2)
    got = smooth(t, y)
    assert got.shape == (T, 2)
    error = got - clean.unsqueeze(1)
    assert float(error.square().mean().sqrt()) < 0.01 and float(error.abs().max()) < 0.06  # noise: 0.1, to 0.4
    assert torch.equal(smooth(t, y[:, 0]), got[:, 0])
    each = smooth_each(t.expand(2, T), y.T.contiguous(), torch.ones(2, T, dtype=DT))
    assert torch.equal(each, got.T)


def test_interpolate_reproduces_cubics_parabolas_and_chords_exactly():
    """A not-a-knot spline is exact on cubics (any knots), and is the parabola/chord for 3/2 knots."""
    g = torch.Generator().manual_seed(2)
    tq = torch.linspace(-1.0, 11.0, 241, dtype=DT)
    inside = tq.clamp(0.0, 10.0)
    for T, poly in ((9, lambda x: 0.3 * x**3 - x**2 + 2 * x - 1), (5, lambda x: -x**3 + 4 * x),
                    (3, lambda x: 2 * x**2 - 3 * x + 1), (2, lambda x: 5 - 0.5 * x)):
        t = torch.sort(torch.rand(T, generator=g, dtype=DT) * 10).values
        t[0], t[-1] = 0.0, 10.0
        got = interpolate(t, poly(t), tq)
        # exact inside up to rounding of values of size ~300; constant at the end values outside
        assert (got - poly(inside)).abs().max() < 1e-10 * poly(inside).abs().max()
    assert torch.equal(interpolate(torch.tensor([2.0], dtype=DT), torch.tensor([7.0], dtype=DT), tq),
                       torch.full_like(tq, 7.0))


def test_interpolate_slopes_are_continuous_and_accurate():
    t = torch.arange(14, dtype=DT) * 0.5
    tq = torch.linspace(0, 6.5, 1301, dtype=DT)
    z = interpolate(t, torch.sin(1.7 * t), tq)
    slope = torch.gradient(z, spacing=(tq,))[0]
    error = (slope - 1.7 * torch.cos(1.7 * tq)).abs()
    # O(h^3) slopes with h = 0.5 (0.85 rad per sample): within 1% of the amplitude inside, within
    # 8% in the end intervals (where not-a-knot extrapolates the neighbouring cubic)
    interior = (tq >= 1.0) & (tq <= 5.5)
    assert error[interior].max() < 0.01 * 1.7 and error.max() < 0.08 * 1.7
    # no kinks at the knots: consecutive slopes differ by the curvature over one step (about
    # 1.7^3 * 0.005 = 0.025); straight lines between the samples jump by up to 0.7 there
    assert (slope[1:] - slope[:-1]).abs().max() < 0.03


def test_series_at_the_same_times_are_smoothed_and_interpolated_together_as_each_alone():
    """Columns ``(T, N)`` sharing times and weights: each column is smoothed with its own GCV choice
    (a noiseless, a noisy and a rough series pick different smoothing) and interpolated, equal to
    the series alone bit for bit (so fit_many's data start is fit's, whatever the batch)."""
    g = torch.Generator().manual_seed(3)
    t = torch.sort(torch.rand(25, generator=g, dtype=torch.float64)).values * 6
    Y = torch.stack([torch.sin(t), torch.sin(t) + 0.1 * torch.randn(25, generator=g, dtype=torch.float64),
                     torch.randn(25, generator=g, dtype=torch.float64)], dim=1)
    w = torch.full((25,), 4.0, dtype=torch.float64)
    together = smooth(t, Y, w)
    alone = torch.stack([smooth(t, Y[:, j], w) for j in range(3)], dim=1)
    assert together.shape == (25, 3)
    assert torch.equal(together, alone)
    assert (together - Y).abs().amax(dim=0).unique().numel() == 3  # three different amounts of smoothing
    tq = torch.linspace(-1, 7, 50, dtype=torch.float64)
    joined = interpolate(t, together, tq)
    assert joined.shape == (50, 3)
    assert torch.equal(joined, torch.stack([interpolate(t, together[:, j], tq) for j in range(3)], dim=1))


@pytest.mark.parametrize("T", [25, 80])  # summed point by point (at most SUMMED_POINTS), and series by series
def test_a_large_batch_of_series_is_smoothed_as_each_alone_and_as_the_dense_formula(T):
    assert (T <= SUMMED_POINTS) == (T == 25)
    g = torch.Generator().manual_seed(5)
    N = SUMMED_SERIES + 52  # two blocks
    t = torch.linspace(0, 6, T, dtype=torch.float64)
    Y = torch.sin(t).unsqueeze(1) + 10.0 ** torch.linspace(-6, 0, N, dtype=torch.float64) * torch.randn(
        T, N, generator=g, dtype=torch.float64)
    together = smooth(t, Y)
    for j in (0, 1, SUMMED_SERIES - 1, SUMMED_SERIES, N - 1):
        assert torch.equal(together[:, j], smooth(t, Y[:, j]))
    # the GCV choice of each series, recomputed with matrix products for every lam
    D = torch.zeros(T - 2, T, dtype=torch.float64)
    h = t[1] - t[0]
    for i in range(T - 2):
        D[i, i:i + 3] = torch.tensor([1.0, -2.0, 1.0], dtype=torch.float64) / h**2 * h.sqrt()
    lams = torch.logspace(-12, 2, 29, dtype=torch.float64) * 6.0**3 / T
    hats = torch.linalg.inv(torch.eye(T, dtype=torch.float64) + lams.reshape(-1, 1, 1) * (D.T @ D))  # (L, T, T)
    for j in (0, N // 2, N - 1):
        Z = hats @ Y[:, j]  # (L, T)
        score = T * ((Y[:, j] - Z) ** 2).sum(dim=1) / (T - hats.diagonal(dim1=1, dim2=2).sum(dim=1)) ** 2
        # the eigenvalues of D^T D near its null space (straight lines) are rounding: 1e-8 of values of order 1
        torch.testing.assert_close(together[:, j], Z[int(torch.argmin(score))], rtol=0, atol=1e-8)


@pytest.mark.parametrize("T", [31, 80])  # one pass over the points for the batch, and series by series
def test_series_each_on_its_own_times_are_smoothed_as_each_alone(T):
    """``smooth_each``: every series on its own uneven times, with its own weights, exactly what
    ``smooth`` gives it alone (so a batch whose datasets each have their own times starts as its
    single fits do), in more than one block for the short series."""
    g = torch.Generator().manual_seed(7)
    N = SUMMED_SERIES + 3 if T <= SUMMED_POINTS else 5
    t = torch.sort(torch.rand(N, T, generator=g, dtype=DT), dim=1).values * torch.linspace(2, 9, N, dtype=DT).unsqueeze(1)
    y = torch.cos(t) + 10.0 ** torch.linspace(-6, -1, N, dtype=DT).unsqueeze(1) * torch.randn(N, T, generator=g, dtype=DT)
    w = torch.rand(N, T, generator=g, dtype=DT) + 0.5
    each = smooth_each(t, y, w)
    assert each.shape == (N, T)
    for n in sorted({0, 1, N // 2, N - 2, N - 1}):
        assert torch.equal(each[n], smooth(t[n], y[n], w[n]))
    assert (each - y).abs().amax(dim=1).unique().numel() == N  # each its own smoothing


def test_series_each_on_its_own_knots_are_interpolated_as_each_alone():
    """``interpolate_each``: each row is ``interpolate`` of that series alone, bit for bit, queries
    outside its knots included (held at the end values)."""
    g = torch.Generator().manual_seed(8)
    N, T = 6, 12
    t = torch.sort(torch.rand(N, T, generator=g, dtype=DT), dim=1).values * torch.linspace(1, 5, N, dtype=DT).unsqueeze(1)
    y = torch.sin(3 * t) + torch.randn(N, T, generator=g, dtype=DT)
    tq = torch.linspace(-0.5, 5.5, 90, dtype=DT).expand(N, -1) * torch.linspace(0.9, 1.1, N, dtype=DT).unsqueeze(1)
    each = interpolate_each(t, y, tq)
    assert each.shape == (N, 90)
    for n in range(N):
        assert torch.equal(each[n], interpolate(t[n], y[n], tq[n]))


@pytest.mark.parametrize("scale", [1e-6, 1e7])
def test_the_smoothing_does_not_depend_on_the_units_of_the_values_and_their_sigmas(scale):
    """Values and sigmas in units ``scale`` times smaller (weights ``1 / scale^2`` times): the same
    smoothing in those units. The candidates' range was fixed: with sigmas of 1e6 only the flat
    smoothings remained, and a Lotka–Volterra fit started from them ran to max_iter at 1,700 times
    the optimum's sum of squares (its fit in the first units: 6 iterations)."""
    t = torch.linspace(0, 15, 61, dtype=torch.float64)
    y = torch.sin(t) + 0.2 * torch.randn(61, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    weights = torch.full_like(t, 1 / 0.2 ** 2) * (1 + 0.5 * torch.rand(61, generator=torch.Generator().manual_seed(2),
                                                                       dtype=torch.float64))
    base = smooth(t, y, weights)
    torch.testing.assert_close(smooth(t, y * scale, weights / scale ** 2), base * scale, rtol=1e-9, atol=1e-12 * scale)
    each = smooth_each(t.unsqueeze(0), (y * scale).unsqueeze(0), (weights / scale ** 2).unsqueeze(0))
    torch.testing.assert_close(each, base.unsqueeze(0) * scale, rtol=1e-9, atol=1e-12 * scale)
