"""Fits of a model with a measured input: fit, several experiments, fit_many, predict and simulate."""

import functools

import numpy as np
import pytest
import torch
from scipy.interpolate import CubicSpline

import torchql
from torchql.models import DrivenOscillator

DT = torch.float64
TRUTH = {"c": 0.3, "k": 4.0}
X0 = torch.tensor([0.5, 0.0], dtype=DT)


@functools.lru_cache(maxsize=None)
def force(seed: int, kind: str = "zoh", span: float = 12.0, samples: int = 49) -> torchql.Inputs:
    """A random force sampled every ``span / (samples - 1)``."""
    g = torch.Generator().manual_seed(seed)
    t = torch.linspace(0, span, samples, dtype=DT)
    return torchql.Inputs(t, torch.randn(samples, generator=g, dtype=DT), names="u", kind=kind)


@functools.lru_cache(maxsize=None)
def _positions(inputs, x0: tuple, times: tuple) -> torch.Tensor:
    """The true oscillator's positions ``(T, 1)`` from ``x0`` at ``times[0]``, exact: between the input's samples the force is a
    polynomial in the time since the last sample, and the oscillator with that polynomial's powers
    as extra states is linear with constant coefficients, so each stretch is one matrix exponential.
    (The zero-order hold's smoothed steps keep the held signal's integral: they change the solution
    by O(ramp^2), far below the tolerances asserted.)"""
    knots = inputs.t.numpy()
    u = inputs.u[:, 0].numpy()
    if inputs.kind == "cubic":
        coefficients = np.ascontiguousarray(CubicSpline(knots, u, bc_type="not-a-knot").c[::-1].T)  # powers 0..3
    else:
        slope = np.diff(u) / np.diff(knots) if inputs.kind == "linear" else np.zeros(len(knots) - 1)
        coefficients = np.stack([u[:-1], slope, np.zeros_like(slope), np.zeros_like(slope)], axis=1)
    A = torch.zeros(6, 6, dtype=DT)  # (y, v, 1, s, s^2, s^3), s the time since the last sample
    A[0, 1], A[1, 0], A[1, 1] = 1.0, -TRUTH["k"], -TRUTH["c"]
    A[3, 2], A[4, 3], A[5, 4] = 1.0, 2.0, 3.0
    state = torch.tensor([*x0, 1.0, 0.0, 0.0, 0.0], dtype=DT)
    now, out = times[0], []
    for target in times:
        while now < target:
            j = min(int(np.searchsorted(knots, now, side="right")) - 1, len(knots) - 2)
            step = min(target, float(knots[j + 1])) - now
            A[1, 2:] = torch.tensor(coefficients[j], dtype=DT)
            state[2:] = torch.tensor([(now - knots[j]) ** p for p in range(4)], dtype=DT)
            state = torch.linalg.matrix_exp(A * step) @ state
            now += step
        out.append(float(state[0]))
    return torch.tensor(out, dtype=DT).unsqueeze(-1)


def measured(inputs, *, noise: float = 0.0, seed: int = 0, x0=X0, times=None) -> torchql.Observations:
    """Positions of the true oscillator driven by ``inputs`` (exact), with Gaussian noise."""
    t = torch.linspace(0, 12, 41, dtype=DT) if times is None else times
    y = _positions(inputs, tuple(x0.tolist()), tuple(t.tolist()))
    if noise:
        y = y + noise * torch.randn(y.shape, generator=torch.Generator().manual_seed(seed), dtype=DT)
    return torchql.Observations(t, y, observe=["y"], sigma=noise or None, inputs=inputs)


GUESS_X0 = torch.tensor([0.0, 0.0], dtype=DT)


@pytest.mark.parametrize("method, kind", [("kantorovich", "zoh"), ("kantorovich", "linear"), ("kantorovich", "cubic"),
                                          ("shooting", "zoh"), ("shooting", "linear")])
def test_exact_data_recover_the_truth(kind, method):
    # the data are exact; the fit's default tolerances are 1e-10 (rtol) and 1e-12 (atol)
    data = measured(force(0, kind))
    result = torchql.fit(DrivenOscillator(), data, x0=GUESS_X0, method=method)
    assert result.success, result.message
    for name, value in TRUTH.items():
        assert abs(float(result.params[name]) - value) < 1e-8, (name, result.params)
    torch.testing.assert_close(result.x0, X0, rtol=0, atol=1e-8)


def test_noisy_data_give_intervals_that_hold_the_truth():
    data = measured(force(1), noise=0.02, seed=3)
    result = torchql.fit(DrivenOscillator(), data, x0=GUESS_X0)
    assert result.success, result.message
    intervals = result.confidence_intervals(0.99)
    for name, value in TRUTH.items():
        low, high = intervals[name]
        assert low < value < high, (name, intervals[name])
        assert high - low < 0.2 * value  # informative: the input excites the oscillator
    # the reduced chi-square of a correct model with the right sigma is near 1
    assert 0.5 < result.sse / result.dof < 1.6


def test_the_quintic_storage_fits_a_held_input_as_the_default_does():
    """A zero-order hold's grid nodes lie just outside its smooth steps, where the input is held: one
    computed at a step's very end fell inside it by a roundoff, the step's second derivative there
    (9e8 for a unit step) entered the quintic storage's A'', and its fit stuck at MAX_ITER 0.1-0.3
    standard errors from the optimum."""
    inputs = force(1)
    nodes = inputs.nodes
    for order in (1, 2):  # the input is held at every node: its derivatives vanish there exactly
        derivative = lambda t: inputs(t.reshape(1))[0, 0]  # noqa: E731
        for _ in range(order):
            derivative = torch.func.grad(derivative)
        assert bool((torch.vmap(derivative)(nodes) == 0).all())
    data = measured(inputs, noise=0.02, seed=3)
    default = torchql.fit(DrivenOscillator(), data, x0=GUESS_X0)
    quintic = torchql.fit(DrivenOscillator(), data, x0=GUESS_X0, linear_solver="taylor_quintic")
    assert default.success and quintic.status is torchql.Status.CONVERGED, quintic.message
    se = torch.tensor(list(default.stderr.values()), dtype=DT)
    assert float(((quintic.estimates - default.estimates) / se).abs().max()) < 1e-4
    assert quintic.sse == pytest.approx(default.sse, rel=1e-9)


def test_predict_and_simulate_use_the_fit_inputs_or_new_ones():
    data = measured(force(0))
    result = torchql.fit(DrivenOscillator(), data, x0=GUESS_X0)
    t = torch.linspace(0, 6, 7, dtype=DT)
    other = force(5)
    assert result.model.inputs is not None  # the fitted model holds its data's inputs
    torch.testing.assert_close(result.predict(t, inputs=other),
                               torchql.simulate(DrivenOscillator(**TRUTH), X0, t, inputs=other), rtol=0, atol=1e-7)
    torch.testing.assert_close(torchql.simulate(result.model, result.x0, t, **result.solver_options),
                               result.predict(t), rtol=0, atol=0)
    assert DrivenOscillator().inputs is None  # the user's model is left as it was


def test_two_experiments_with_their_own_inputs_share_the_coefficients():
    first = measured(force(0))
    x0_second = torch.tensor([-0.2, 0.4], dtype=DT)
    second = measured(force(7), x0=x0_second, times=torch.linspace(1, 9, 30, dtype=DT))
    result = torchql.fit(DrivenOscillator(), [first, second], x0=torch.zeros(2, 2, dtype=DT), t0=[0.0, 1.0])
    assert result.success, result.message
    for name, value in TRUTH.items():
        assert abs(float(result.params[name]) - value) < 1e-8
    t = torch.linspace(1, 9, 5, dtype=DT)
    expected = torchql.simulate(DrivenOscillator(**TRUTH), x0_second, t, t0=1.0, inputs=second.inputs)
    torch.testing.assert_close(result.predict(t, experiment=1), expected, rtol=0, atol=1e-7)


def test_fit_many_with_shared_inputs_equals_fit():
    inputs = force(0)
    datasets = [measured(inputs, noise=0.01, seed=s) for s in range(3)]
    batch = torchql.fit_many(DrivenOscillator(), datasets, x0=GUESS_X0)
    for b, data in enumerate(datasets):
        alone = torchql.fit(DrivenOscillator(), data, x0=GUESS_X0)
        assert batch[b].status == alone.status
        torch.testing.assert_close(batch.estimates[b], alone.estimates, rtol=1e-9, atol=1e-12)


def test_fit_many_with_per_sample_inputs_equals_per_sample_fits():
    a, b = force(0), force(2)
    datasets = [measured(a, noise=0.01, seed=0), measured(b, noise=0.01, seed=1), measured(a, noise=0.01, seed=2)]
    seen = set()
    batch = torchql.fit_many(DrivenOscillator(), datasets, x0=GUESS_X0,
                             callback=lambda sample, record: seen.add(sample))
    assert seen == {0, 1, 2}
    for i, data in enumerate(datasets):
        alone = torchql.fit(DrivenOscillator(), data, x0=GUESS_X0)
        assert batch[i].status == alone.status and batch[i].iterations == alone.iterations
        torch.testing.assert_close(batch.estimates[i], alone.estimates, rtol=1e-9, atol=1e-12)
        assert batch[i].model.inputs.same_as(data.inputs)  # each sample predicts with its own input
    # one batched Observations with an Inputs per sample is the same problem
    y = torch.stack([d.y for d in datasets])
    stacked = torchql.Observations(datasets[0].t, y, observe=["y"], sigma=0.01, inputs=[a, b, a])
    again = torchql.fit_many(DrivenOscillator(), stacked, x0=GUESS_X0)
    torch.testing.assert_close(again.estimates, batch.estimates, rtol=0, atol=0)


@pytest.mark.parametrize("kind", ["zoh", "linear"])
def test_the_adaptive_solver_lands_on_the_input_s_breakpoints(monkeypatch, kind):
    """The batched Dormand–Prince's steps end at every node where a held or linear input is not
    smooth (and restart there, as torchdiffeq's ``jump_t``), in ``fit`` as in ``fit_many``; stepping
    across those kinks took 5 times the evaluations (a shooting ``fit_many`` of three zero-order
    hold datasets: 64,191 against 12,135)."""
    import torchql.engine_evaluate as engine

    seen = []

    def spy(system, z0, grid, **kwargs):
        seen.append((grid, kwargs["land"]))
        return real(system, z0, grid, **kwargs)

    real = engine.dopri_batch
    monkeypatch.setattr(engine, "dopri_batch", spy)
    inputs = force(0, kind)
    data = measured(inputs, noise=0.01)
    torchql.fit(DrivenOscillator(), data, x0=GUESS_X0, method="shooting", max_iter=1)
    torchql.fit_many(DrivenOscillator(), [data, measured(inputs, noise=0.01, seed=1)], x0=GUESS_X0,
                     method="shooting", max_iter=1)
    assert len(seen) >= 2
    inner = inputs.jumps[(inputs.jumps > 0) & (inputs.jumps < 12)]  # where the input is not smooth
    for grid, land in seen:
        for row_grid, row_land in zip(grid.expand(land.shape).reshape(-1, grid.shape[-1]),
                                      land.reshape(-1, land.shape[-1])):
            at = torch.searchsorted(row_grid, inner)
            assert bool((row_grid[at] == inner).all()) and bool(row_land[at].all())


def test_inputs_that_do_not_fit_the_model_or_the_data_are_named():
    data = measured(force(0))
    bare = torchql.Observations(data.t, data.y, observe=["y"])
    with pytest.raises(ValueError, match="`model` takes inputs \\('u',\\).*`data` carries none"):
        torchql.fit(DrivenOscillator(), bare, x0=GUESS_X0)
    with pytest.raises(ValueError, match="`data` carries inputs \\['u'\\] but `model` declares none"):
        torchql.fit(torchql.models.LinearOscillator(), data, x0=GUESS_X0)
    wrong = torchql.Observations(data.t, data.y, observe=["y"], inputs=torchql.Inputs(data.t, data.t, "force"))
    with pytest.raises(ValueError, match="`data.inputs` names unknown input 'force'; the model's inputs are"):
        torchql.fit(DrivenOscillator(), wrong, x0=GUESS_X0)
    short = torchql.Observations(data.t, data.y, observe=["y"], inputs=force(0, span=6.0))
    with pytest.raises(ValueError, match="`data.inputs` must cover the data's times \\[0, 12\\]"):
        torchql.fit(DrivenOscillator(), short, x0=GUESS_X0)
    with pytest.raises(ValueError, match="`data\\[1\\]` carries no inputs but `data\\[0\\]` does"):
        torchql.fit_many(DrivenOscillator(), [data, bare], x0=GUESS_X0)
    with pytest.raises(ValueError, match="`data\\[1\\].inputs` must cover the experiment's times"):
        torchql.fit(DrivenOscillator(), [data, short], x0=torch.zeros(2, 2, dtype=DT))
    # fit_many fits samples with other inputs as other problems: the error names the sample in `data`
    with pytest.raises(ValueError, match="`data\\[2\\].inputs` must cover sample 2's times \\[0, 12\\]"):
        torchql.fit_many(DrivenOscillator(), [data, measured(force(1)), short], x0=GUESS_X0)
    stacked = torchql.Observations(data.t, torch.stack([data.y, data.y]), observe=["y"], inputs=[force(0), short.inputs])
    with pytest.raises(ValueError, match="`data.inputs\\[1\\]` must cover sample 1's times"):
        torchql.fit_many(DrivenOscillator(), stacked, x0=GUESS_X0)
    # ... and so does one whose signal has another name than the model's input
    with pytest.raises(ValueError, match="`data\\[2\\].inputs` names unknown input 'force'; the model's inputs are"):
        torchql.fit_many(DrivenOscillator(), [data, measured(force(1)), wrong], x0=GUESS_X0)
    renamed = torchql.Observations(data.t, torch.stack([data.y, data.y]), observe=["y"],
                                   inputs=[force(0), wrong.inputs])
    with pytest.raises(ValueError, match="`data.inputs\\[1\\]` names unknown input 'force'"):
        torchql.fit_many(DrivenOscillator(), renamed, x0=GUESS_X0)
    with pytest.raises(ValueError, match="`model` takes inputs \\('u',\\).*pass `inputs="):
        torchql.simulate(DrivenOscillator(), X0, data.t)
    with pytest.raises(ValueError, match="`inputs` must cover the simulated times \\[0, 12\\]"):
        torchql.simulate(DrivenOscillator(), X0, data.t, inputs=force(0, span=6.0))
    with pytest.raises(ValueError, match="`inputs` must cover the simulated times \\[1, 8\\]"):  # t0 after t
        torchql.simulate(DrivenOscillator(), X0, torch.tensor([1.0, 2.0], dtype=DT), t0=8.0, inputs=force(0, span=6.0))


class _GainDriven(torchql.ODEModel):
    """``y'' + c y' + k y = g u(t)``: the driven oscillator with an unknown gain."""

    state_names, input_names = ("y", "v"), ("u",)

    def __init__(self, c: float = 0.5, k: float = 3.0, g: float = 1.0) -> None:
        super().__init__()
        for name, value in (("c", c), ("k", k), ("g", g)):
            self.register_buffer(name, torch.tensor(value, dtype=DT))

    def forward(self, t, x, u):
        y, v = x.unbind(-1)
        return torch.stack((v, self.g * u[..., 0] - self.c * v - self.k * y), dim=-1)


def test_a_held_step_at_an_observation_time_keeps_the_data_start():
    """A held force switched on at t = 5, an observation time: the grid has nodes 1e-8 on either
    side of the switch as well as at it, three within 2e-8. The data start's slopes at the middle
    one were a difference across 2e-8 (of the velocity derived from the data, which differs by
    O(h y'') on the two sides), 3e6, and its gradient matching set c, k and g 5e4 to 2e5 times too
    large; the fit then crawled for minutes. Now each difference spans the neighbours beyond the
    cluster (:func:`torchql.data_start.slopes`): the first coefficients are within 10 % of the truth
    and the fit converges to it."""
    force = torchql.Inputs(torch.tensor([0.0, 5.0, 20.0], dtype=DT), torch.tensor([0.0, 1.0, 1.0], dtype=DT),
                           names="u", kind="zoh")
    t = torch.linspace(0.0, 20.0, 81, dtype=DT)
    x0 = torch.zeros(2, dtype=DT)
    y = torchql.simulate(_GainDriven(0.3, 4.0, 0.7), x0, t, inputs=force, rtol=1e-12, atol=1e-14)[:, :1]
    records = []
    result = torchql.fit(_GainDriven(), torchql.Observations(t, y, observe=["y"], inputs=force), x0,
                         fixed_x0=["y", "v"], max_time=30, callback=records.append)
    truth = {"c": 0.3, "k": 4.0, "g": 0.7}
    assert result.status is torchql.Status.CONVERGED, result.message
    for name, value in truth.items():
        assert float(records[0].params[name]) == pytest.approx(value, rel=0.1)
        assert float(result.params[name]) == pytest.approx(value, rel=1e-8)


class _Lag(torchql.ODEModel):
    """``y' = -k y + u``."""

    state_names, input_names = ("y",), ("u",)

    def __init__(self, k: float = 0.5) -> None:
        super().__init__()
        self.register_buffer("k", torch.tensor(k, dtype=DT))

    def forward(self, t, x, u):
        return -self.k * x + u[..., :1]


def test_a_one_sample_hold_is_a_constant_input_from_its_time_on():
    """``Inputs([0], [2], kind="zoh")``: u = 2 at every time from 0, in ``simulate`` and ``fit``
    (they asked its one sample to span the times). Closed form ``y = (2 / k)(1 - e^{-k t})``."""
    constant = torchql.Inputs(torch.tensor([0.0], dtype=DT), torch.tensor([2.0], dtype=DT), names="u", kind="zoh")
    t = torch.linspace(0.0, 3.0, 7, dtype=DT)
    exact = (2.0 / 1.3) * (1 - torch.exp(-1.3 * t)).unsqueeze(-1)
    torch.testing.assert_close(torchql.simulate(_Lag(1.3), torch.zeros(1, dtype=DT), t, inputs=constant,
                                                rtol=1e-12, atol=1e-14), exact, rtol=0, atol=1e-10)
    result = torchql.fit(_Lag(), torchql.Observations(t, exact, observe=["y"], inputs=constant),
                         x0=torch.zeros(1, dtype=DT), fixed_x0=["y"])
    assert result.success and result.params["k"].item() == pytest.approx(1.3, rel=1e-8), result.message
    late = torchql.Inputs(torch.tensor([1.0], dtype=DT), torch.tensor([2.0], dtype=DT), names="u", kind="zoh")
    with pytest.raises(ValueError, match=r"`inputs` must cover the simulated times \[0, 3\]"):
        torchql.simulate(_Lag(), torch.zeros(1, dtype=DT), t, inputs=late)  # from its time on only


def test_predict_past_the_fitted_inputs_says_which_inputs_it_used():
    """``result.predict(t)`` beyond the fitted data's inputs, with no ``inputs=``: the error said
    "`inputs` must cover ..." to a user who passed none. It says the model's own (the fitted data's)
    were used, and how to pass others."""
    t = torch.linspace(0.0, 3.0, 7, dtype=DT)
    signal = torchql.Inputs(t, torch.sin(t), names="u")
    y = torchql.simulate(_Lag(1.3), torch.zeros(1, dtype=DT), t, inputs=signal)
    result = torchql.fit(_Lag(), torchql.Observations(t, y, observe=["y"], inputs=signal), x0=torch.zeros(1, dtype=DT))
    with pytest.raises(ValueError, match=r"simulated times \[0, 6\] \(no `inputs` was passed: these are the ones the "
                                         r"model holds, its fitted data's; pass `inputs="):
        result.predict(torch.linspace(0.0, 6.0, 4, dtype=DT))
    longer = torchql.Inputs(torch.linspace(0.0, 6.0, 13, dtype=DT), torch.sin(torch.linspace(0.0, 6.0, 13, dtype=DT)),
                            names="u")
    assert result.predict(torch.linspace(0.0, 6.0, 4, dtype=DT), inputs=longer).shape == (4, 1)


@pytest.mark.parametrize("kind", ["zoh", "linear"])
def test_inputs_at_clock_times_fit_and_simulate_as_near_zero(kind):
    """The driven oscillator measured at t ~ 1e8 (clock times in seconds): a held input's step spanned
    1e5 roundoffs of t, and ``simulate`` failed (step size underflow) and ``fit`` ended
    INTEGRATION_FAILED at c = -1.9, k = 156; a linear input's fit took 9 s at 1e8 and failed at 1e9.
    Fits and simulations run in local time from ``t0``: the results equal those at t ~ 0, and the
    result speaks the data's time (``t0``, the records' times, ``predict``)."""
    x0 = torch.tensor([0.2, 0.0], dtype=DT)
    tu, t = torch.linspace(0, 10, 21, dtype=DT), torch.linspace(0, 10, 41, dtype=DT)
    u = torch.sin(3 * tu)
    results = []
    for offset in (0.0, 1e8, 1e9):
        signal = torchql.Inputs(tu + offset, u, names="u", kind=kind)
        y = torchql.simulate(DrivenOscillator(0.3, 4.0), x0, t + offset, inputs=signal)
        result = torchql.fit(DrivenOscillator(0.5, 2.0), torchql.Observations(t + offset, y[:, :1], observe=["y"],
                                                                              inputs=signal),
                             x0=torch.zeros(2, dtype=DT))
        assert result.status is torchql.Status.CONVERGED, result.message
        assert result.t0 == offset and float(result.history[-1].trajectory_t[0]) == offset
        torch.testing.assert_close(result.predict(t + offset), y, rtol=0, atol=1e-8)
        results.append((y, result.estimates))
    for y, estimates in results[1:]:
        torch.testing.assert_close(y, results[0][0], rtol=0, atol=1e-12)
        torch.testing.assert_close(estimates, results[0][1], rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(results[0][1][2:], torch.tensor([0.3, 4.0], dtype=DT), rtol=1e-8, atol=0)


def test_experiments_with_inputs_at_clock_times_fit_as_near_zero():
    """Two experiments of the driven oscillator, each with its own held input, 50 s apart at t ~ 1e8:
    each experiment's input is read in its own local time, and the fit equals the one near zero."""
    x0 = torch.tensor([0.2, 0.0], dtype=DT)
    tu, t = torch.linspace(0, 10, 21, dtype=DT), torch.linspace(0, 10, 41, dtype=DT)
    estimates = []
    for offset in (0.0, 1e8):
        data = []
        for e, start in enumerate((offset, offset + 50.0)):
            u = torch.sin(3 * tu + e)
            y = torchql.simulate(DrivenOscillator(0.3, 4.0), x0, t, inputs=torchql.Inputs(tu, u, names="u", kind="zoh"))
            data.append(torchql.Observations(t + start, y[:, :1], observe=["y"],
                                             inputs=torchql.Inputs(tu + start, u, names="u", kind="zoh")))
        result = torchql.fit(DrivenOscillator(0.5, 2.0), data, x0=torch.zeros(2, 2, dtype=DT))
        assert result.status is torchql.Status.CONVERGED, result.message
        assert result.experiment_t0 == [offset, offset + 50.0]
        estimates.append(result.estimates)
    torch.testing.assert_close(estimates[1], estimates[0], rtol=1e-9, atol=1e-12)
