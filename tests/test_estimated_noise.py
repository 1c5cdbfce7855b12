"""sigma='estimate' as unknowns of the fit: the start from the data's scatter, the result without them
among the coefficients, their standard errors, names that avoid the model's, the exact-fit floor."""

import math

import pytest
import torch

import torchql
from torchql.estimated_noise import EstimatedNoise, scatter_sigma
from torchql.models import LinearOscillator

DT = torch.float64
T = torch.linspace(0, 10, 41, dtype=DT)
X0 = torch.tensor([1.0, 0.0], dtype=DT)
GUESS_X0 = torch.tensor([0.5, 0.5], dtype=DT)
STATES = torchql.simulate(LinearOscillator(0.3, 4.0), X0, T, rtol=1e-12, atol=1e-14)


def noisy(seed: int, noise=(0.01, 0.2)) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return STATES + torch.randn(STATES.shape, generator=g, dtype=DT) * torch.tensor(noise, dtype=DT)


def test_scatter_about_neighbours_estimates_white_noise_on_a_line():
    g = torch.Generator().manual_seed(0)
    t = torch.sort(torch.rand(2000, generator=g, dtype=DT) * 10).values  # uneven times
    y = 3.0 - 0.5 * t + 0.1 * torch.randn(2000, generator=g, dtype=DT)
    mask = torch.ones(2000, dtype=torch.bool)
    mask[::7] = False  # gaps: the neighbours are the nearest values present
    y = torch.where(mask, y, torch.full_like(y, 123.0))  # what the gaps hold is never read
    square, count = scatter_sigma(t.reshape(1, -1, 1), y.reshape(1, -1, 1), mask.reshape(1, -1, 1))
    assert int(count) == int(mask.sum()) - 2
    # the estimate of sigma^2 from ~1700 values: relative standard error about sqrt(2 * 3 / 1700) < 6 %
    assert math.sqrt(float(square / count)) == pytest.approx(0.1, rel=0.06)
    exact_line = 3.0 - 0.5 * t
    square, _ = scatter_sigma(t.reshape(1, -1, 1), exact_line.reshape(1, -1, 1), mask.reshape(1, -1, 1))
    assert float(square) < 1e-25


def test_start_pools_groups_and_falls_back_to_the_values_scale():
    noise = EstimatedNoise(["pos", "vel"], [0, 1, 0], ["k"])
    t = torch.linspace(0, 1, 5, dtype=DT)
    y = torch.stack([torch.zeros(5, dtype=DT), torch.full((5,), 2.0, dtype=DT), torch.zeros(5, dtype=DT)], dim=-1)
    y[2, 0] = 1.0  # one deviation in "pos": e = 1, a = b = 1/2, so e^2 / 1.5, pooled over 6 interior values
    mask = torch.ones(5, 3, dtype=torch.bool)
    mask[:, 1] = torch.tensor([True, False, False, False, True])  # "vel" has two values: their RMS, 2
    sigma = noise.start(t, y.unsqueeze(0), mask.unsqueeze(0))
    assert sigma.shape == (1, 2)
    # the deviation of y[2] (1), and of y[1] and y[3] from lines through it (1/2 each), over six values
    expected = math.sqrt((1 + 0.25 + 0.25) / 1.5 / 6)
    assert float(sigma[0, 0]) == pytest.approx(expected, rel=1e-12)
    assert float(sigma[0, 1]) == pytest.approx(2.0, rel=1e-12)


def test_the_sigmas_leave_the_coefficients_and_the_users_model_alone():
    model = LinearOscillator(0.5, 2.0)
    before = {name: value.clone() for name, value in model.named_buffers()}
    result = torchql.fit(model, torchql.Observations(T, noisy(0), observe=["y", "v"], sigma="estimate"), x0=GUESS_X0)
    assert result.success, result.message
    assert result.unknown_names == ["y(t0)", "v(t0)", "A", "B"] and set(result.params) == {"A", "B"}
    assert result.covariance.shape == (4, 4) and result.jacobian.shape == (82, 4)
    assert result.singular_values.shape == (4,) and result.lower is None and result.log_scaled == []
    assert result.dof == 82 - 4
    assert all(set(record.params) == {"A", "B"} for record in result.history)
    assert {name for name, _ in result.model.named_buffers()} == set(before)
    assert {name for name, _ in model.named_buffers()} == set(before)
    for name, value in model.named_buffers():
        assert torch.equal(value, before[name])
    # the expected information about log sigma_g is 2 n_g: stderr(sigma_g) = sigma_g / sqrt(2 n_g)
    for name in ("y", "v"):
        assert result.sigma_stderr[name] == pytest.approx(result.sigma[name] / math.sqrt(2 * 41), rel=1e-6)
    assert f"y: {result.sigma['y']:.7g} ± " in result.report()


def test_the_sigmas_names_avoid_the_models_coefficients():
    class Taken(LinearOscillator):
        def __init__(self, A, B):
            super().__init__(A, B)
            self.register_buffer("sigma_y", torch.tensor(7.0, dtype=DT))

    result = torchql.fit(Taken(0.5, 2.0), torchql.Observations(T, noisy(1), observe=["y", "v"], sigma="estimate"),
                         x0=GUESS_X0, params=["A", "B"])
    assert result.success, result.message
    assert float(result.params["sigma_y"]) == 7.0  # the model's own coefficient, fixed, untouched
    assert result.sigma["y"] == pytest.approx(0.01, rel=0.3)


def test_an_output_met_exactly_converges_with_its_sigma_at_the_integration_error():
    y = STATES.clone()
    y[:, 1] += 0.1 * torch.randn(41, generator=torch.Generator().manual_seed(2), dtype=DT)
    result = torchql.fit(LinearOscillator(0.5, 2.0), torchql.Observations(T, y, observe=["y", "v"], sigma="estimate"),
                         x0=GUESS_X0)
    assert result.success, result.message
    assert result.sigma["y"] < 1e-8  # the fit's own integration error, not a noise
    torch.testing.assert_close(result.estimates[2:], torch.tensor([0.3, 4.0], dtype=DT), rtol=1e-8, atol=0)


def test_estimated_sigma_with_exact_values_is_an_error():
    exact = torch.zeros(41, 2, dtype=torch.bool)
    exact[0, 0] = True
    data = torchql.Observations(T, noisy(3), observe=["y", "v"], sigma="estimate", exact=exact)
    with pytest.raises(ValueError, match="`exact` values cannot be combined with sigma='estimate'"):
        torchql.fit(LinearOscillator(0.5, 2.0), data, x0=GUESS_X0)


def test_fit_many_starts_each_sample_from_its_own_scatter():
    small, large = noisy(4, (0.001, 0.002)), noisy(5, (0.1, 0.2))
    batch = torchql.fit_many(LinearOscillator(0.5, 2.0), [torchql.Observations(T, y, observe=["y", "v"],
                                                                                sigma="estimate")
                                                          for y in (small, large)], x0=GUESS_X0)
    assert bool(batch.success.all()), batch.message
    assert batch.sigma.shape == (2, 2) and batch.sigma_stderr.shape == (2, 2)
    assert batch[0].sigma["v"] == pytest.approx(0.002, rel=0.3)
    assert batch[1].sigma["v"] == pytest.approx(0.2, rel=0.3)


def test_a_sigma_group_without_values_is_named_before_the_fit():
    """An output with no values leaves its estimated sigma undetermined: the fit ended NOT_IDENTIFIABLE
    with advice to fix the sigma by `params=`, which does not take it. Now an error names the output,
    for one dataset and for the sample of a batch that lacks it."""
    t = torch.arange(14, dtype=torch.float64) * 0.5
    x = torchql.simulate(LinearOscillator(0.1, 3.0), torch.tensor([0.0, 1.0], dtype=torch.float64), t)
    y = x.clone()
    y[:, 1] = float("nan")
    x0 = torch.tensor([0.5, 0.5], dtype=torch.float64)
    with pytest.raises(ValueError, match=r"the output\(s\) \['v'\] of sigma group 'v' have no values, so nothing"):
        torchql.fit(LinearOscillator(0.5, 1.0), torchql.Observations(t, y, observe=["y", "v"], sigma="estimate"), x0)
    batch = torchql.Observations(t, torch.stack([x, y]), observe=["y", "v"], sigma="estimate")
    with pytest.raises(ValueError, match=r"have no values of `data\[1\]`"):
        torchql.fit_many(LinearOscillator(0.5, 1.0), batch, x0)


def test_estimated_and_known_sigmas_in_one_fit_are_an_error_that_says_so():
    """One experiment with ``sigma="estimate"``, another with ``sigma=0.1``: the error said "`sigma`
    must be given for every experiment or for none", though both gave one."""
    from torchql.models import LinearOscillator

    t = torch.linspace(0, 10, 21, dtype=torch.float64)
    x0 = torch.tensor([1.0, 0.0], dtype=torch.float64)
    y = torchql.simulate(LinearOscillator(), x0, t)[:, :1]
    data = [torchql.Observations(t, y, observe=["y"], sigma="estimate"),
            torchql.Observations(t, y, observe=["y"], sigma=0.1)]
    with pytest.raises(ValueError, match=r"sigma='estimate' must be given for every experiment or for none: the "
                                         r"experiments \[0\] estimate theirs, \[1\] do not"):
        torchql.fit(LinearOscillator(), data, x0=torch.stack([x0, x0]))
