"""One engine for ``fit`` and ``fit_many``: on seven kinds of problem, by both schemes, each sample of a
``fit_many`` batch of seven datasets (each with its own noise) equals its own ``fit``: estimates and
SSE to 1e-8, the same status and the same number of iterations.

The problems: the thesis' linear and nonlinear oscillators, a coasting car, FitzHugh–Nagumo, a
bounded rate problem (log scale), two experiments per sample, and a dataset with values met exactly.
Shooting from the data-built start is checked alike on the four with special options.
"""

from __future__ import annotations

import pytest
import torch

import torchql
from torchql.models import CoastingCar, FitzHughNagumo, LinearOscillator, NonlinearOscillator

DT = torch.float64
B = 7


def _noisy(model, x0, t, noise: float, seed: int, observe=None) -> torch.Tensor:
    x = torchql.simulate(model, x0, t, rtol=1e-12, atol=1e-14)
    if observe is not None:
        x = x[:, observe]
    g = torch.Generator().manual_seed(seed)
    return x + noise * x.abs().amax(dim=0) * torch.randn(x.shape, generator=g, dtype=DT)


def _problem(name: str, seed: int):
    """``(model, data, x0, options)`` of sample ``seed`` of problem ``name``."""
    noise = 1e-3 * (1 + seed)  # each sample its own noise level and draw
    if name == "linear_oscillator":
        t = torch.linspace(0, 6, 25, dtype=DT)
        y = _noisy(LinearOscillator(0.3, 4.0), torch.tensor([1.0, 0.0], dtype=DT), t, noise, seed)
        return LinearOscillator(0.4, 3.5), torchql.Observations(t, y, observe=["y", "v"]), \
            torch.tensor([0.9, 0.1], dtype=DT), {}
    if name == "nonlinear_oscillator":
        t = torch.linspace(0, 6, 25, dtype=DT)
        y = _noisy(NonlinearOscillator(0.1, 3.0, 0.2, 4.0), torch.tensor([1.0, 0.0], dtype=DT), t, noise, seed,
                   observe=[0])
        return NonlinearOscillator(0.12, 2.8, 0.25, 3.7), torchql.Observations(t, y, observe=["y"]), \
            torch.tensor([1.0, 0.0], dtype=DT), {"fixed_x0": ["y", "v"]}
    if name == "car":
        t = torch.linspace(0, 60, 31, dtype=DT)
        truth = CoastingCar(frontal_area=2.0, mass=1500.0, C_D=0.35, mu=0.015)
        y = _noisy(truth, torch.tensor([30.0], dtype=DT), t, noise, seed)
        return CoastingCar(frontal_area=2.0, mass=1500.0, C_D=0.5, mu=0.03), \
            torchql.Observations(t, y, observe=["v"]), torch.tensor([29.0], dtype=DT), \
            {"params": ["C_D", "mu"]}
    if name == "fitzhugh_nagumo":
        t = torch.linspace(0, 10, 41, dtype=DT)
        y = _noisy(FitzHughNagumo(0.2, 0.2, 3.0), torch.tensor([-1.0, 1.0], dtype=DT), t, noise, seed)
        return FitzHughNagumo(0.25, 0.25, 2.8), torchql.Observations(t, y, observe=["V", "R"]), \
            torch.tensor([-1.0, 1.0], dtype=DT), {"fixed_x0": ["V", "R"]}
    if name == "bounded_rate":
        t = torch.linspace(0, 6, 25, dtype=DT)
        y = _noisy(LinearOscillator(0.3, 4.0), torch.tensor([1.0, 0.0], dtype=DT), t, noise, seed)
        return LinearOscillator(0.4, 3.5), torchql.Observations(t, y, observe=["y", "v"]), \
            torch.tensor([0.9, 0.1], dtype=DT), {"bounds": {"A": (0.05, 2.0), "B": (1.0, 10.0)},
                                                 "scale": {"A": "log", "B": "log"}}
    if name == "two_experiments":
        t = torch.linspace(0, 6, 25, dtype=DT)
        starts = [torch.tensor([1.0, 0.0], dtype=DT), torch.tensor([0.0, 2.0], dtype=DT)]
        data = [torchql.Observations(t, _noisy(LinearOscillator(0.3, 4.0), x0, t, noise, 10 * seed + e),
                                     observe=["y", "v"]) for e, x0 in enumerate(starts)]
        return LinearOscillator(0.4, 3.5), data, torch.stack(starts), {"fixed_x0": ["y", "v"]}
    if name == "exact_values":
        t = torch.linspace(0, 6, 25, dtype=DT)
        y = _noisy(LinearOscillator(0.3, 4.0), torch.tensor([1.0, 0.0], dtype=DT), t, noise, seed)
        y[0] = torch.tensor([1.0, 0.0], dtype=DT)  # the start is known exactly
        exact = torch.zeros(25, 2, dtype=torch.bool)
        exact[0] = True
        return LinearOscillator(0.4, 3.5), torchql.Observations(t, y, observe=["y", "v"], exact=exact), \
            torch.tensor([0.9, 0.1], dtype=DT), {}
    raise ValueError(name)


PROBLEMS = ["linear_oscillator", "nonlinear_oscillator", "car", "fitzhugh_nagumo", "bounded_rate",
            "two_experiments", "exact_values"]


@pytest.mark.parametrize("method", ["kantorovich", "shooting"])
@pytest.mark.parametrize("name", PROBLEMS)
def test_each_fit_many_sample_equals_its_own_fit(name, method):
    samples = [_problem(name, seed) for seed in range(B)]
    model, _, x0, options = samples[0]
    alone = [torchql.fit(model, data, x0=x0, method=method, **options) for _, data, _, _ in samples]
    batch = torchql.fit_many(model, [data for _, data, _, _ in samples], x0=x0, method=method, **options)
    assert sum(result.success for result in alone) >= B - 1, [result.message for result in alone]
    for b, result in enumerate(alone):
        got = batch[b]
        assert got.status is result.status, (b, got.message, result.message)
        assert got.iterations == result.iterations, b
        torch.testing.assert_close(got.estimates, result.estimates, rtol=1e-8, atol=1e-12)
        assert got.sse == pytest.approx(result.sse, rel=1e-8, abs=1e-20)


@pytest.mark.parametrize("name", ["nonlinear_oscillator", "bounded_rate", "two_experiments", "exact_values"])
def test_shooting_from_the_data_equals_its_own_fit_and_the_integrated_start_s_optimum(name):
    """``method="shooting", initial_trajectory="data"`` with known initial states, bounds on a log
    scale, two experiments per sample and values met exactly: each ``fit_many`` sample equals its
    own ``fit``, which reaches the optimum of shooting from the integrated guesses (SSE to 1e-9)
    in no more iterations."""
    samples = [_problem(name, seed) for seed in range(2)]
    model, _, x0, options = samples[0]
    alone = [torchql.fit(model, data, x0=x0, method="shooting", initial_trajectory="data", **options)
             for _, data, _, _ in samples]
    batch = torchql.fit_many(model, [data for _, data, _, _ in samples], x0=x0, method="shooting",
                             initial_trajectory="data", **options)
    for b, result in enumerate(alone):
        assert result.success, result.message
        got = batch[b]
        assert got.status is result.status and got.iterations == result.iterations, (b, got.message)
        torch.testing.assert_close(got.estimates, result.estimates, rtol=1e-8, atol=1e-12)
        integrated = torchql.fit(model, samples[b][1], x0=x0, method="shooting", **options)
        assert integrated.success and result.iterations <= integrated.iterations
        assert result.sse == pytest.approx(integrated.sse, rel=1e-9)


@pytest.mark.parametrize("method", ["kantorovich", "shooting"])
def test_a_fit_integrates_as_each_fit_many_sample_does(method):
    """Where the engine integrates the model by its adaptive solver (here every trial, with
    ``linear_solver="torchdiffeq"``), one sample is integrated as a batch's are, by the batched
    Dormand–Prince: a ``fit`` and its ``fit_many`` sample agree to rounding, not only within the
    integration's tolerance (two solvers differed by 1e-9 in the SSE, and at a fit's last steps
    that flipped a status from CONVERGED to STALLED)."""
    samples = [_problem("car", seed) for seed in range(2)]
    model, _, x0, options = samples[0]
    alone = [torchql.fit(model, data, x0=x0, method=method, linear_solver="torchdiffeq", **options)
             for _, data, _, _ in samples]
    batch = torchql.fit_many(model, [data for _, data, _, _ in samples], x0=x0, method=method,
                             linear_solver="torchdiffeq", **options)
    for b, result in enumerate(alone):
        assert result.success and batch[b].status is result.status and batch[b].iterations == result.iterations
        torch.testing.assert_close(batch[b].estimates, result.estimates, rtol=1e-12, atol=0.0)
        assert batch[b].sse == pytest.approx(result.sse, rel=1e-12)


@pytest.mark.parametrize("method", ["kantorovich", "shooting"])
def test_a_step_budget_keeps_every_sample_on_the_batched_solver(method, monkeypatch):
    """``max_steps`` is the batched Dormand–Prince's budget per grid interval (torchdiffeq's
    ``max_num_steps`` per output time), so a batch with one is integrated at once, not sample by
    sample (200 oscillators took 39 s so, against 0.8 s without it), and a ``fit`` equals its
    ``fit_many`` sample. A budget too small for the model fails each sample, in words."""
    import torchql.engine_evaluate as engine_evaluate

    def one_at_a_time(*args, **kwargs):
        raise AssertionError("a sample was integrated on its own")

    monkeypatch.setattr(engine_evaluate, "integrate_each", one_at_a_time)
    samples = [_problem("nonlinear_oscillator", seed) for seed in range(2)]
    model, _, x0, options = samples[0]
    alone = [torchql.fit(model, data, x0=x0, method=method, max_steps=1000, **options) for _, data, _, _ in samples]
    batch = torchql.fit_many(model, [data for _, data, _, _ in samples], x0=x0, method=method, max_steps=1000,
                             **options)
    for b, result in enumerate(alone):
        assert result.success and batch[b].status is result.status and batch[b].iterations == result.iterations
        torch.testing.assert_close(batch[b].estimates, result.estimates, rtol=1e-12, atol=0.0)
    starved = torchql.fit_many(model, [data for _, data, _, _ in samples], x0=x0, method=method, max_steps=1,
                               initial_trajectory="integrate", **options)
    for b in range(2):
        assert starved[b].status is torchql.Status.INTEGRATION_FAILED
        assert "max_steps = 1 steps between two grid nodes ran out" in starved[b].message, starved[b].message
