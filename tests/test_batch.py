"""``torchql.fit_many``: each sample's result is the single fit's, failures stay per sample."""

import math

import pytest
import torch

import torchql
from torchql.models import CoastingCar, LinearOscillator
from torchql.result import Status

DT = torch.float64
AREA, MASS = 17.3, 80.43
CAR_T = torch.arange(9, dtype=DT) * 5.0
OSC_T = torch.arange(14, dtype=DT) * 0.5


def car_data(B: int, seed: int = 3) -> tuple[list, torch.Tensor]:
    """``B`` noisy coast-down logs (cars with their own coefficients) and each log's first speed ``(B, 1)``."""
    g = torch.Generator().manual_seed(seed)
    data = []
    for _ in range(B):
        C_D = 0.45 + 0.05 * torch.randn((), generator=g, dtype=DT)
        mu = 0.015 + 0.003 * torch.randn((), generator=g, dtype=DT)
        v0 = 117.3 + 2.0 * torch.randn((1,), generator=g, dtype=DT)
        v = torchql.simulate(CoastingCar(AREA, MASS, float(C_D), float(mu)), v0, CAR_T, rtol=1e-12, atol=1e-12)
        data.append(torchql.Observations(CAR_T, v + 0.3 * torch.randn(9, 1, generator=g, dtype=DT), observe=["v"]))
    return data, torch.stack([d.y[0] for d in data])


def assert_same_as_single(batch, singles, rel=1e-8):
    for b, single in enumerate(singles):
        assert batch.status[b] is single.status, (b, batch.message[b], single.message)
        assert batch.message[b] == single.message
        assert bool(batch.success[b]) == single.success
        assert int(batch.iterations[b]) == single.iterations, b
        scale = single.estimates.abs().clamp(min=1e-12)
        assert ((batch.estimates[b] - single.estimates).abs() / scale).max() <= rel, b
        assert torch.allclose(batch.x0[b], single.x0, rtol=rel, atol=0)
        if math.isfinite(single.sse):
            assert abs(float(batch.sse[b]) - single.sse) <= rel * single.sse, b
            both = torch.isfinite(single.covariance)
            assert torch.equal(both, torch.isfinite(batch.covariance[b]))
            assert torch.allclose(batch.covariance[b][both], single.covariance[both], rtol=1e-6, atol=0)
        else:
            assert math.isnan(float(batch.sse[b]))


@pytest.mark.slow
def test_car_fleet_equals_single_fits_with_per_sample_failures():
    """Six cars: four converge, one has no frontal area (``C_D`` undetermined), one starts from a
    drag coefficient that makes the model blow up. Each status, message, estimate, SSE and
    covariance is the one ``torchql.fit`` reports for that car alone."""
    data, x0 = car_data(6)
    C_D = torch.tensor([0.4, 0.4, 0.4, -40.0, 0.4, 3.0], dtype=DT)
    area = torch.tensor([AREA, AREA, 0.0, AREA, AREA, AREA], dtype=DT)
    # integrated from the guesses, where C_D = -40 blows up (from the data every car converges)
    batch = torchql.fit_many(CoastingCar(AREA, MASS), data, x0, guesses={"C_D": C_D, "frontal_area": area}, grid=50,
                             initial_trajectory="integrate")
    singles = [torchql.fit(CoastingCar(float(area[b]), MASS, C_D=float(C_D[b])), data[b], x0[b], grid=50,
                           initial_trajectory="integrate") for b in range(6)]
    assert [s.name for s in batch.status] == ["CONVERGED", "CONVERGED", "NOT_IDENTIFIABLE", "INTEGRATION_FAILED",
                                             "CONVERGED", "CONVERGED"]
    assert "{C_D}" in batch.message[2]
    assert_same_as_single(batch, singles)
    # the per-sample constant is reported per sample; the failed sample keeps its guesses
    assert torch.equal(batch.params["frontal_area"], area)
    assert float(batch.params["C_D"][3]) == -40.0 and int(batch.iterations[3]) == 0


@pytest.mark.slow
def test_oscillators_stop_on_their_own_and_max_iter_is_per_sample():
    """Oscillators from guesses at different distances need 5 to 7 updates; one from the thesis' poor
    guess does not converge within ``max_iter=9`` and says so, without holding the others back."""
    g = torch.Generator().manual_seed(1)
    truths = [(0.1, 3.0), (0.2, 2.5), (0.05, 3.5), (0.15, 2.0), (0.1, 3.0)]
    data = []
    for A, B in truths:
        y = torchql.simulate(LinearOscillator(A, B), torch.tensor([0.0, 1.0], dtype=DT), OSC_T, rtol=1e-13,
                             atol=1e-15)[:, :1]
        data.append(torchql.Observations(OSC_T, y + 0.01 * torch.randn(14, 1, generator=g, dtype=DT), observe=["y"]))
    guesses = {"A": torch.tensor([0.12, 0.25, 0.06, 0.5, 0.5], dtype=DT),
               "B": torch.tensor([2.8, 2.6, 3.3, 1.0, 1.0], dtype=DT)}
    x0 = torch.tensor([[0.0, 1.0]] * 4 + [[0.5, 0.5]], dtype=DT)
    finished = []
    # integrated from the guesses (the thesis' poor guess converges within 9 from the data)
    batch = torchql.fit_many(LinearOscillator(), data, x0, guesses=guesses, grid=50, max_iter=9,
                             progress=lambda done, total: finished.append(done), initial_trajectory="integrate")
    singles = [torchql.fit(LinearOscillator(float(guesses["A"][b]), float(guesses["B"][b])), data[b], x0[b],
                           grid=50, max_iter=9, initial_trajectory="integrate") for b in range(5)]
    assert_same_as_single(batch, singles)
    assert [s.name for s in batch.status] == ["CONVERGED"] * 4 + ["MAX_ITER"]
    # no error bars about the unconverged sample's estimates, as fit gives none
    assert torch.isnan(batch.covariance[4]).all() and torch.isfinite(batch.covariance[:4]).all()
    assert all(math.isnan(lo) and math.isnan(hi) for lo, hi in batch[4].confidence_intervals().values())
    assert len(set(batch.iterations[:4].tolist())) > 1  # converged samples stopped at their own iteration
    assert finished[-1] == 5 and sorted(finished) == finished and len(finished) > 2  # samples finished apart


def exact_oscillators() -> tuple[torch.Tensor, list, dict, torch.Tensor]:
    """Three oscillators' exact y data (integrated at rtol 1e-13): their truths ``(3, 4)`` (y0, v0,
    A, B), the datasets, and guesses of A, B and the initial state off by 5-30 %."""
    truths = torch.tensor([[0.0, 1.0, 0.1, 3.0], [0.2, -0.5, 0.3, 1.5], [-0.1, 0.8, 0.05, 4.0]], dtype=DT)
    data = []
    for row in truths:
        y = torchql.simulate(LinearOscillator(float(row[2]), float(row[3])), row[:2], OSC_T, rtol=1e-13, atol=1e-15)
        data.append(torchql.Observations(OSC_T, y[:, :1], observe=["y"]))
    return truths, data, {"A": truths[:, 2] * 1.3, "B": truths[:, 3] * 0.9}, truths[:, :2] + 0.05


def test_exact_data_recovers_truth():
    """Exact oscillator data (integrated at rtol 1e-13): the Kantorovich fixed point then has zero
    residual whatever the storage grid, so the estimates are the truth to about the data's own
    integration error (1e-13 observed); 1e-10 leaves room for the fit's rtol."""
    truths, data, guesses, x0 = exact_oscillators()
    batch = torchql.fit_many(LinearOscillator(), data, x0, guesses=guesses, grid=100)
    assert batch.success.all(), batch.summary()
    error = (batch.estimates - truths).abs() / truths.abs().clamp(min=1.0)
    assert error.max() <= 1e-10
    assert (batch.sse <= 1e-16).all()


def test_chunks_and_order_do_not_change_results():
    data, x0 = car_data(5, seed=4)
    whole = torchql.fit_many(CoastingCar(AREA, MASS), data, x0, grid=20)
    chunked = torchql.fit_many(CoastingCar(AREA, MASS), data, x0, grid=20, chunk_size=2)
    reversed_ = torchql.fit_many(CoastingCar(AREA, MASS), data[::-1], x0.flip(0), grid=20)
    assert torch.allclose(chunked.estimates, whole.estimates, rtol=1e-12, atol=0)
    assert torch.allclose(reversed_.estimates.flip(0), whole.estimates, rtol=1e-12, atol=0)
    assert torch.equal(chunked.iterations, whole.iterations)


def test_result_access_and_summary():
    data, x0 = car_data(3, seed=5)
    result = torchql.fit_many(CoastingCar(AREA, MASS), data, x0[0], grid=20)  # one x0 for all
    assert len(result) == 3 and result.estimates.shape == (3, 3) and result.covariance.shape == (3, 3, 3)
    assert result.unknown_names == ["v(t0)", "C_D", "mu"]
    last = result[-1]
    assert last.index == 2 and last.status is result.status[2]
    assert torch.equal(last.estimates, result.estimates[2]) and last.params["C_D"].shape == ()
    assert set(last.stderr) == set(result.unknown_names) and result.stderr.shape == (3, 3)
    assert [s.index for s in result] == [0, 1, 2]
    with pytest.raises(IndexError, match="out of range for a batch of 3"):
        result[3]
    fitted = result.model_of(1)
    assert float(fitted.C_D) == float(result.params["C_D"][1]) and float(fitted.mass) == MASS
    text = result.summary()
    assert "3 samples, 3 converged" in text and "C_D" in text
    assert result.dof.tolist() == [6, 6, 6] and not result.sigma_known


def test_missing_values_per_sample():
    """NaNs differ per sample: each sample uses its own values, as the single fit does."""
    data, x0 = car_data(3, seed=6)
    y = data[1].y.clone()
    y[3:5] = float("nan")
    data[1] = torchql.Observations(CAR_T, y, observe=["v"])
    batch = torchql.fit_many(CoastingCar(AREA, MASS), data, x0, grid=20)
    single = torchql.fit(CoastingCar(AREA, MASS), data[1], x0[1], grid=20)
    assert batch.n_observations.tolist() == [9, 7, 9]
    assert torch.allclose(batch.estimates[1], single.estimates, rtol=1e-8, atol=0)
    assert abs(float(batch.residual_variance[1]) - single.residual_variance) <= 1e-8 * single.residual_variance
    assert_same_intervals(batch[1], single)  # residual variance estimated: Student's t with 7 - 3 dof
    with pytest.raises(ValueError, match="`level` must be a float strictly between 0 and 1"):
        batch[1].confidence_intervals(95)


def as_batch(data: list) -> torchql.Observations:
    """The datasets of a list as one batched Observations, values ``(B, T, K)``."""
    return torchql.Observations(data[0].t, torch.stack([d.y for d in data]), observe=data[0].observe)


def assert_identical(a, b):
    """Two fit_many results of the same data: equal to 1e-12 (the same computation)."""
    assert [s.name for s in a.status] == [s.name for s in b.status] and a.message == b.message
    assert torch.equal(a.iterations, b.iterations) and torch.equal(a.n_observations, b.n_observations)
    for name in ("estimates", "x0", "sse", "covariance", "residual_variance"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=1e-12, atol=0, equal_nan=True)


def test_batched_observations_fit_as_the_list():
    """One Observations holding the batch gives the list's fits, and neither is modified."""
    data, x0 = car_data(4, seed=11)
    batch = as_batch(data)
    stored = batch.y.clone()
    listed = torchql.fit_many(CoastingCar(AREA, MASS), data, x0, grid=20)
    batched = torchql.fit_many(CoastingCar(AREA, MASS), batch, x0, grid=20)
    assert batched.success.all()
    assert_identical(batched, listed)
    assert torch.equal(batch.y, stored)


def test_batched_observations_with_missing_values_and_sigma_per_sample():
    """A sample with NaNs and per-sample ``sigma``: the batch fits it as the list does, and as
    ``torchql.fit`` fits that sample alone (``batch[1]``)."""
    data, x0 = car_data(3, seed=6)
    y = torch.stack([d.y for d in data])
    y[1, 3:5] = float("nan")
    sigma = torch.tensor([0.3, 0.5, 0.2], dtype=DT).reshape(3, 1, 1)
    batch = torchql.Observations(CAR_T, y, observe=["v"], sigma=sigma)
    listed = [torchql.Observations(CAR_T, y[b], observe=["v"], sigma=sigma[b, 0]) for b in range(3)]
    batched = torchql.fit_many(CoastingCar(AREA, MASS), batch, x0, grid=20)
    assert batched.n_observations.tolist() == [9, 7, 9] and batched.sigma_known
    assert_identical(batched, torchql.fit_many(CoastingCar(AREA, MASS), listed, x0, grid=20))
    single = torchql.fit(CoastingCar(AREA, MASS), batch[1], x0[1], grid=20)
    assert single.success and torch.allclose(batched.estimates[1], single.estimates, rtol=1e-8, atol=0)
    assert_same_intervals(batched[1], single)  # sigma known: normal quantile


def assert_same_intervals(sample, single, level=0.9):
    """A sample's Wald intervals are the single fit's (same quantile, estimates and standard errors)."""
    ours, theirs = sample.confidence_intervals(level), single.confidence_intervals(level)
    assert list(ours) == single.unknown_names
    for name, (lo, hi) in theirs.items():
        assert ours[name] == pytest.approx((lo, hi), rel=1e-6)


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(x0=torch.zeros(3, 2)), ValueError, r"`x0` must have shape \(B, n_states\) = \(2, 1\)"),
    (dict(x0=torch.tensor([[float("nan")], [1.0]])), ValueError, r"`x0` must be finite; rows \[0\]"),
    (dict(guesses={"C_D": torch.ones(3)}), ValueError, r"`guesses\['C_D'\]` must have shape .* \(2,\)"),
    (dict(guesses={"drag": torch.ones(2)}), ValueError, "`guesses` names unknown buffer 'drag'"),
    (dict(guesses=[1.0]), TypeError, "`guesses` must be a dict"),
    (dict(params=["C_D", "C_D"]), ValueError, "`params` lists a buffer twice"),
    (dict(params="C_D"), TypeError, "not a string"),
    (dict(fixed_x0=["w"]), ValueError, "`fixed_x0` names unknown state 'w'"),
    (dict(damping="strong"), ValueError, "`damping` must be one of"),
    (dict(chunk_size=0), ValueError, "chunk_size"),
    (dict(progress="yes"), TypeError, "`progress` must be a bool or a callable"),
    (dict(t0=10.0), ValueError, "`t0` must not be later than the first observation"),
])
def test_bad_arguments_name_themselves(kwargs, error, match):
    data, x0 = car_data(2, seed=7)
    args = dict(x0=x0)
    args.update(kwargs)
    with pytest.raises(error, match=match):
        torchql.fit_many(CoastingCar(AREA, MASS), data, grid=10, **args)


def test_bad_data_is_named():
    data, x0 = car_data(2, seed=8)
    model = CoastingCar(AREA, MASS)
    with pytest.raises(ValueError, match="empty list"):
        torchql.fit_many(model, [], x0)
    with pytest.raises(TypeError, match="list of torchql.Observations"):
        torchql.fit_many(model, data[0].y, x0)
    with pytest.raises(TypeError, match="single dataset: use torchql.fit"):
        torchql.fit_many(model, data[0], x0[0])
    with pytest.raises(TypeError, match=r"`data\[1\]` must be a torchql.Observations"):
        torchql.fit_many(model, [data[0], "log"], x0)
    with pytest.raises(ValueError, match=r"`data\[1\]` holds a batch of 2 datasets, values \(2, 9, 1\): pass a "
                                         "batched Observations alone"):
        torchql.fit_many(model, [data[0], as_batch(data)], x0)
    shorter = torchql.Observations(CAR_T[:7], data[1].y[:7], observe=["v"])
    with pytest.raises(ValueError, match=r"`data\[1\]` has T = 7 observation times but `data\[0\]` has 9: fit_many "
                                         "needs the same number of times in every dataset"):
        torchql.fit_many(model, [data[0], shorter], x0)
    other = torchql.Observations(CAR_T, data[1].y, observe=["v"], sigma=0.3)
    with pytest.raises(ValueError, match=r"`data\[1\]` gives `sigma` but `data\[0\]` does not"):
        torchql.fit_many(model, [data[0], other], x0)
    marked = torch.zeros(2, 9, 1, dtype=torch.bool)
    marked[1, :4] = True  # four values to meet exactly, three unknowns
    with pytest.raises(ValueError, match=r"`data\[1\]`: more values are marked `exact` \(4\) than there are "
                                         r"unknowns \(3\)"):
        torchql.fit_many(model, torchql.Observations(CAR_T, as_batch(data).y, observe=["v"], exact=marked), x0)
    sparse = data[1].y.clone()
    sparse[2:] = float("nan")  # two values left for three unknowns
    with pytest.raises(ValueError, match=r"`data\[1\]` has 2 usable values, fewer than the 3 unknowns"):
        torchql.fit_many(model, [data[0], torchql.Observations(CAR_T, sparse, observe=["v"])], x0)


def test_progress_bar_with_tqdm(capsys):
    pytest.importorskip("tqdm")
    data, x0 = car_data(2, seed=9)
    result = torchql.fit_many(CoastingCar(AREA, MASS), data, x0, grid=10, progress=True)
    assert result.success.all()
    assert "fit_many" in capsys.readouterr().err


def test_progress_bar_names_each_phase(capsys):
    """The bar moves in every phase, not only as samples stop: it names the phase begun (the first
    trajectories, the iterations, the final pass), for one grid group as for several, while a
    callable keeps receiving counts only."""
    pytest.importorskip("tqdm")
    data, x0 = car_data(3, seed=9)
    torchql.fit_many(CoastingCar(AREA, MASS), data, x0, progress=True)
    err = capsys.readouterr().err
    positions = [err.find(phase) for phase in ("first trajectories", "iterating", "final pass")]
    assert -1 not in positions and positions == sorted(positions), err[-500:]
    seen = []
    torchql.fit_many(CoastingCar(AREA, MASS), data, x0, progress=lambda done, total: seen.append((done, total)))
    assert seen and all(isinstance(done, int) and total == 3 for done, total in seen) and seen[-1][0] == 3


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_follows_the_model_and_matches_cpu():
    data, x0 = car_data(4, seed=10)
    cpu = torchql.fit_many(CoastingCar(AREA, MASS), data, x0, grid=20)
    gpu = torchql.fit_many(CoastingCar(AREA, MASS).to("cuda"), data, x0, grid=20)
    assert gpu.estimates.device.type == "cuda"
    assert torch.allclose(gpu.estimates.cpu(), cpu.estimates, rtol=1e-8, atol=0)
    assert [s.name for s in gpu.status] == [s.name for s in cpu.status]
    assert Status.CONVERGED in gpu.status


# ------------------------------------------------------------------ per-sample observation times (B, T)
def own_time_cars(B: int, seed: int = 12) -> tuple[list, torch.Tensor]:
    """``B`` coast-down logs each recorded at its own 9 times (sample 0 at ``CAR_T``, the others at random
    times with their own start), and each log's first speed ``(B, 1)``."""
    g = torch.Generator().manual_seed(seed)
    data = []
    for b in range(B):
        C_D = 0.45 + 0.05 * torch.randn((), generator=g, dtype=DT)
        t = CAR_T if b == 0 else torch.sort(torch.rand(9, generator=g, dtype=DT)).values * 40 + b
        v = torchql.simulate(CoastingCar(AREA, MASS, float(C_D), 0.015), torch.tensor([117.3], dtype=DT), t,
                             rtol=1e-12, atol=1e-12)
        data.append(torchql.Observations(t, v + 0.3 * torch.randn(9, 1, generator=g, dtype=DT), observe=["v"]))
    return data, torch.stack([d.y[0] for d in data])


def test_cars_at_their_own_times_equal_single_fits_with_a_failure():
    """Each car observed at its own times (its own t0, its own grid: different lengths, padded in the
    batch): each status, message, estimate, SSE and covariance is the single fit's, a car whose guess
    blows up fails alone, and the batched Observations ``(B, T)`` gives the list's fits."""
    data, x0 = own_time_cars(5)
    from torchql.batch import _make_grid
    sizes = {_make_grid(40, d.t[0], d.t).numel() for d in data}
    assert len(sizes) > 1  # the samples' grids differ in length: the batch pads them
    C_D = torch.tensor([0.4, 0.4, -40.0, 0.4, 0.35], dtype=DT)
    model = CoastingCar(AREA, MASS)
    # integrated from the guesses, where C_D = -40 blows up (from the data every car converges)
    batch = torchql.fit_many(model, data, x0, guesses={"C_D": C_D}, grid=40, initial_trajectory="integrate")
    singles = [torchql.fit(CoastingCar(AREA, MASS, C_D=float(C_D[b])), data[b], x0[b], grid=40,
                           initial_trajectory="integrate") for b in range(5)]
    assert [s.name for s in batch.status] == ["CONVERGED", "CONVERGED", "INTEGRATION_FAILED", "CONVERGED",
                                             "CONVERGED"]
    assert_same_as_single(batch, singles)
    # t0 not given: each sample's own first time, as each single fit's
    assert torch.equal(batch.t0, torch.stack([d.t[0] for d in data]))
    assert [s.t0 for s in singles] == batch.t0.tolist() and batch[3].t0 == singles[3].t0
    times = torch.stack([d.t for d in data])
    stored = times.clone()
    own = torchql.Observations(times, torch.stack([d.y for d in data]), observe=["v"])
    batched = torchql.fit_many(model, own, x0, guesses={"C_D": C_D}, grid=40, initial_trajectory="integrate")
    assert_identical(batched, batch)
    assert torch.equal(own.t, stored)  # not modified
    chunked = torchql.fit_many(model, own, x0, guesses={"C_D": C_D}, grid=40, chunk_size=2,
                               initial_trajectory="integrate")
    assert_identical(chunked, batch)


def test_oscillators_at_their_own_times_from_a_shared_t0():
    """Oscillators sampled at their own times, every one from x0 at the shared ``t0 = -0.5`` (before any
    observation): each sample is the single fit with that ``t0``; the default grid (1000 intervals)."""
    g = torch.Generator().manual_seed(2)
    truths = [(0.1, 3.0), (0.2, 2.5), (0.05, 3.5)]
    data = []
    x_start = torch.tensor([0.0, 1.0], dtype=DT)
    for b, (A, B) in enumerate(truths):
        t = torch.sort(torch.rand(14, generator=g, dtype=DT)).values * 6.5 + 0.1 * b
        y = torchql.simulate(LinearOscillator(A, B), x_start, torch.cat([torch.tensor([-0.5], dtype=DT), t]),
                             rtol=1e-13, atol=1e-15)[1:, :1]
        data.append(torchql.Observations(t, y + 0.01 * torch.randn(14, 1, generator=g, dtype=DT), observe=["y"]))
    guesses = {"A": torch.tensor([0.12, 0.25, 0.06], dtype=DT), "B": torch.tensor([2.8, 2.6, 3.3], dtype=DT)}
    batch = torchql.fit_many(LinearOscillator(), data, x_start, guesses=guesses, t0=-0.5)
    singles = [torchql.fit(LinearOscillator(float(guesses["A"][b]), float(guesses["B"][b])), data[b], x_start,
                           t0=-0.5) for b in range(3)]
    assert batch.success.all() and batch.t0 == -0.5
    assert_same_as_single(batch, singles)


def test_per_sample_times_all_alike_fit_as_shared_times():
    data, x0 = car_data(3, seed=13)
    shared = torchql.fit_many(CoastingCar(AREA, MASS), data, x0, grid=20)
    rows = torchql.Observations(CAR_T.expand(3, 9), torch.stack([d.y for d in data]), observe=["v"])
    assert rows.per_sample_times
    assert_identical(torchql.fit_many(CoastingCar(AREA, MASS), rows, x0, grid=20), shared)
    assert shared.t0 == 0.0


def test_per_sample_times_t0_and_x0_errors_name_the_sample():
    data, x0 = own_time_cars(3, seed=14)
    model = CoastingCar(AREA, MASS)
    assert float(data[0].t[0]) == 0.0 and all(float(d.t[0]) >= 1.0 for d in data[1:])
    with pytest.raises(ValueError, match=r"`t0` must not be later than the first observation time of any sample; "
                                         r"`data\[0\]` starts at 0, received t0 = 0.5"):
        torchql.fit_many(model, data, x0, t0=0.5, grid=10)
    with pytest.raises(ValueError, match=r"`x0` is required when `t0` precedes the first observation \(as in "
                                         r"`data\[0\]`\)"):
        torchql.fit_many(model, data, t0=-1.0, grid=10)
    # with t0 not given, x0 comes from each sample's own first value
    result = torchql.fit_many(model, data, grid=10, max_iter=0)
    assert torch.equal(result.x0, x0)


def test_fit_and_adjoint_fit_refuse_a_batch_with_per_sample_times():
    data, x0 = own_time_cars(2, seed=15)
    own = torchql.Observations(torch.stack([d.t for d in data]), torch.stack([d.y for d in data]), observe=["v"])
    from torchql.baselines import adjoint_fit

    for fit in (torchql.fit, adjoint_fit):
        with pytest.raises(ValueError, match=r"`data` holds a batch of 2 independent datasets \(values of shape "
                                             r"\(B, T, K\) = \(2, 9, 1\)\), but torchql.fit fits one dataset.*"
                                             r"torchql.fit_many\(model, data, x0, ...\)"):
            fit(CoastingCar(AREA, MASS), own, x0=x0[0])


def test_values_marked_exact_are_met_in_each_sample_as_fit_meets_them():
    """Three cars, each with its first speed marked exact (one marks none): each sample's status,
    iterations, estimates, SSE and covariance are its single fit's, and the exact values are met
    to 1e-10 of the speed."""
    data, x0 = car_data(3, seed=11)
    marked = [torchql.Observations(CAR_T, d.y, observe=["v"], exact=(torch.arange(9) == 0) & (b != 2))
              for b, d in enumerate(data)]
    batch = torchql.fit_many(CoastingCar(AREA, MASS), marked, x0, grid=50)
    singles = [torchql.fit(CoastingCar(AREA, MASS), d, x0[b], grid=50) for b, d in enumerate(marked)]
    assert_same_as_single(batch, singles)
    for b in range(3):
        sample = batch[b]
        assert torch.equal(sample.exact_mask, singles[b].exact_mask)
        assert sample.exact_residual == pytest.approx(singles[b].exact_residual, abs=1e-12)
    assert batch[0].exact_residual < 1e-10 * 117 and batch[0].exact_mask[0] and not batch[2].exact_mask.any()


@pytest.mark.parametrize("linear_solver", ["rk4_doubling", "torchdiffeq"])
def test_a_propagator_fits_each_sample_as_fit_does(linear_solver):
    """``linear_solver="rk4_doubling"`` (batched: every interval of every sample at once) and
    ``"torchdiffeq"`` (no batched form: each sample propagated in turn): each sample equals its
    single fit."""
    import warnings

    data, x0 = car_data(2, seed=5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # torchdiffeq's, one sample at a time
        batch = torchql.fit_many(CoastingCar(AREA, MASS), data, x0, grid=20, linear_solver=linear_solver)
    singles = [torchql.fit(CoastingCar(AREA, MASS), d, x0[b], grid=20, linear_solver=linear_solver)
               for b, d in enumerate(data)]
    assert_same_as_single(batch, singles)
    assert batch.success.all()


def test_a_batch_integrated_one_sample_at_a_time_says_so():
    """A ``solver`` or ``linear_solver`` without a batched form makes ``fit_many`` go through the
    samples in turn: it warns, naming the option and the batched choices, at the caller's line;
    the defaults (and ``max_steps``, the batched Dormand–Prince's budget) warn nothing."""
    import warnings

    data, x0 = car_data(2, seed=5)
    with pytest.warns(UserWarning, match=r"solver='dopri8' has no batched form, so each of the 2 samples") as caught:
        torchql.fit_many(CoastingCar(AREA, MASS), data, x0, solver="dopri8")
    assert [w.filename for w in caught if "no batched form" in str(w.message)] == [__file__]
    with pytest.warns(UserWarning, match=r"linear_solver='torchdiffeq' has no batched form .* 'taylor', "
                      r"'rk4_doubling', .* take them all at once"):
        torchql.fit_many(CoastingCar(AREA, MASS), data, x0, linear_solver="torchdiffeq")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        torchql.fit_many(CoastingCar(AREA, MASS), data, x0, linear_solver="rk4_doubling")
        torchql.fit_many(CoastingCar(AREA, MASS), data, x0, max_steps=500)
        torchql.fit(CoastingCar(AREA, MASS), data[0], x0[0], solver="dopri8")


def test_throw_raises_once_every_sample_was_fitted_naming_the_failed_ones():
    """``throw=True``: a batch with a failed sample raises :class:`torchql.BatchFitError` (a
    ``FitError``) holding the whole result and the failed indices; one that converges returns."""
    data, x0 = car_data(3)
    area = torch.tensor([AREA, 0.0, AREA], dtype=DT)  # no frontal area: C_D undetermined
    with pytest.raises(torchql.FitError) as info:
        torchql.fit_many(CoastingCar(AREA, MASS), data, x0, guesses={"frontal_area": area}, grid=50, throw=True)
    error = info.value
    assert isinstance(error, torchql.BatchFitError)
    assert error.failed == [1]
    assert isinstance(error.result, torchql.BatchFitResult) and len(error.result) == 3
    assert [s.name for s in error.result.status] == ["CONVERGED", "NOT_IDENTIFIABLE", "CONVERGED"]
    assert str(error).startswith("1 of 3 samples did not converge (sample 1: ")
    assert error.result.message[1] in str(error)
    import pickle

    again = pickle.loads(pickle.dumps(error))
    assert again.failed == [1] and str(again) == str(error)
    # without the failed sample it returns the batch, as without throw
    kept = torchql.fit_many(CoastingCar(AREA, MASS), [data[0], data[2]], x0[[0, 2]], grid=50, throw=True)
    plain = torchql.fit_many(CoastingCar(AREA, MASS), [data[0], data[2]], x0[[0, 2]], grid=50)
    assert torch.equal(kept.estimates, plain.estimates)
    # several experiments per sample take it too
    with pytest.raises(torchql.BatchFitError):
        torchql.fit_many(CoastingCar(AREA, MASS), [[data[0], data[1]]], max_iter=1, grid=50, throw=True)


@pytest.mark.parametrize("value", [1, "yes", None])
def test_throw_must_be_a_bool(value):
    data, x0 = car_data(1)
    for fitting in (lambda: torchql.fit_many(CoastingCar(AREA, MASS), data, x0, throw=value),
                    lambda: torchql.fit(CoastingCar(AREA, MASS), data[0], x0[0], throw=value)):
        with pytest.raises(TypeError, match=r"`throw` must be True or False; received"):
            fitting()
