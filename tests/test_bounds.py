"""Bounds on the unknowns: the change of variables, fits that respect them, and bad bounds.

Exact data of the linear oscillator (truth A = 0.1, B = 3): with bounds that contain the truth
the fit recovers it to the same 1e-8 as without; with a lower bound above the truth the
optimum lies on the bound, which the estimate reaches to rounding and the message names.

Guesses on a bound (or beyond it) are moved inside (``Bounds.move_inside``) and the fit goes
on: first-order kinetics with every rate guessed 0 on its bound 0, and the oscillator with a
two-sided bound guessed on either side, reach the truth of their exact data as from guesses
inside; the moved guesses are recorded, and the user's model and ``x0`` are left as they were.
"""

import math

import pytest
import torch

import torchql
from testmodels import SIR, Decay
from torchql.bounds import START_OFFSET, Bounds
from torchql.models import BranchedReactions, LinearOscillator

DT = torch.float64
TRUTH = torch.tensor([0.0, 1.0, 0.1, 3.0], dtype=DT)
GUESS = dict(A=0.5, B=1.0)
X0 = torch.tensor([0.5, 0.5], dtype=DT)


@pytest.fixture(scope="module")
def data():
    t = torch.arange(14, dtype=DT) * 0.5
    x = torchql.simulate(LinearOscillator(), torch.tensor([0.0, 1.0], dtype=DT), t, rtol=1e-13, atol=1e-15)
    return torchql.Observations(t, x[:, :1], observe=["y"])


def make(lower, upper):
    names = ["a", "b", "c", "d"]
    return Bounds({n: (lo, hi) for n, lo, hi in zip(names, lower, upper)}, names, {}, names, DT, torch.device("cpu"))


def test_transform_round_trip_and_derivative():
    b = make([0.0, None, -1.0, None], [None, 2.0, 3.0, None])
    u = torch.tensor([0.3, -5.0, 2.5, 7.0], dtype=DT)
    q = b.internal(u)
    assert torch.allclose(b.external(q, u), u, rtol=1e-14, atol=0)
    h = 1e-6
    numeric = (b.external(q + h, u) - b.external(q - h, u)) / (2 * h)
    assert torch.allclose(b.derivative(u), numeric, rtol=1e-8)
    assert q[3] == u[3]  # unbounded: the identity


def test_a_bound_far_from_the_iterate_is_open_to_the_change_of_variables():
    """``u = lo + exp(q)`` resolves ``u`` only to ``eps |u - lo|``: a bound more than ``FAR_BOUND``
    times ``max(|s|, 1)`` away is not used at that iterate (the identity there), and a step that
    would cross it goes nine tenths of the way, blocked; near it the bound is used again."""
    from torchql.bounds import FAR_BOUND

    b = make([-1e15, -1.0, -1e7, None], [1e15, None, None, None])
    u = torch.tensor([0.05, 0.05, 0.0, 2.0], dtype=DT)
    assert b.transformed_at(u).tolist() == [False, True, False, False]
    q = b.internal(u)
    assert q[0] == u[0] and q[2] == u[2] and b.derivative(u)[0] == 1.0
    torch.testing.assert_close(b.external(q, u), u, rtol=1e-15, atol=0.0)
    change, blocked = b.step(u, torch.tensor([1e-12, 0.0, -3e7, 0.0], dtype=DT))
    assert float(change[0]) == pytest.approx(1e-12, rel=1e-3)  # resolved in its own units (lo + exp(q): to 0.2)
    assert change[2] == pytest.approx(-0.9e7, rel=1e-15) and blocked.tolist() == [False, False, True, False]
    near = torch.tensor([0.0, 0.0, -1e7 + 0.5 * FAR_BOUND, 0.0], dtype=DT)
    assert b.transformed_at(near)[2]


@pytest.mark.parametrize("method", torchql.METHODS)
def test_bounds_far_from_the_estimate_give_the_unbounded_fit(method):
    """Bounds of +-1e15 around the oscillator's damping 0.1 "converged" at A = 0 (SSE 2.6 times the
    optimum's, interval (0, 0)); of -1e15 alone at the guess, after 0 iterations; of +-1e308 ended
    DIVERGED at once. Each is now the unbounded fit: estimates, SSE and intervals."""
    free = torchql.fit(LinearOscillator(**GUESS), _noisy(), x0=X0, method=method)
    assert free.success
    for pair in ((-1e15, 1e15), (-1e15, None), (-1e308, 1e308), (None, 1e12)):
        r = torchql.fit(LinearOscillator(**GUESS), _noisy(), x0=X0, method=method, bounds={"A": pair})
        assert r.success, (pair, r.message)
        torch.testing.assert_close(r.estimates, free.estimates, rtol=1e-9, atol=1e-12)
        assert r.sse == pytest.approx(free.sse, rel=1e-10)
        assert r.confidence_intervals()["A"] == pytest.approx(free.confidence_intervals()["A"], rel=1e-6)


def _noisy():
    t = torch.arange(14, dtype=DT) * 0.5
    x = torchql.simulate(LinearOscillator(), torch.tensor([0.0, 1.0], dtype=DT), t, rtol=1e-13, atol=1e-15)
    noise = 0.01 * torch.randn(14, 1, generator=torch.Generator().manual_seed(5), dtype=DT)
    return torchql.Observations(t, x[:, :1] + noise, observe=["y"], sigma=0.01)


def test_step_stays_strictly_inside_and_reports_blocked():
    b = make([0.2, None, None, None], [None, None, None, None])
    u = torch.tensor([0.2 + 1e-12, 1.0, 1.0, 1.0], dtype=DT)
    change, blocked = b.step(u, torch.tensor([-100.0, 0.5, 0.0, 0.0], dtype=DT))
    new = u + change
    assert new[0] > 0.2 and blocked.tolist() == [True, False, False, False]
    assert change[1] == 0.5


def test_step_near_a_bound_is_capped_not_overflowed():
    """Next to its bound ``du/dq`` is tiny, and a linearized step to a far ``u`` is huge in ``q``."""
    b = make([0.0, 1.0, 0.0, None], [None, None, 1.0, None])
    u = torch.tensor([3e-9, 1.0 + 1e-12, 0.5, 2.0], dtype=DT)
    change, blocked = b.step(u, torch.tensor([3e7, 5.0, -1e300, 1e3], dtype=DT))
    new = u + change
    assert torch.isfinite(new).all()
    assert new[0] == pytest.approx(3e-9 * 1000, rel=1e-12)  # a factor 1000 farther from the bound
    assert new[1] - 1.0 == pytest.approx(1e-12 * math.exp(5.0), rel=1e-3)  # within the cap: as asked
    assert new[2] == pytest.approx(1 / 11, rel=1e-12)  # toward a bound: q from 0 to -log(10)
    assert change[3] == 1e3  # unbounded: never capped
    assert blocked.tolist() == [True, False, True, False]


def test_rate_pulled_far_from_its_bound_gives_a_status_not_nan():
    """2-digit oscillator data (y only), guesses A = 0.015, B = 0.45, both bounded below by 0.

    The first step drove A to 3e-9; the next asked for A ~ 0.1, a step of 3e7 in log A, whose
    ``exp`` overflowed to a non-finite update (DIVERGED). Capped at a factor 1000 either way, the
    fit then ended at an optimum on the bounds, 1.7 times the data's sum of squares. With steps
    toward a bound capped at a factor 10 (:data:`torchql.bounds.MAX_TOWARD_STEP`) the rate is not
    driven against its bound, and both methods reach the data's optimum, the unbounded fit's.
    (The first reference integrated from these guesses; built from the data, it reaches it too.)
    """
    t = torch.arange(14, dtype=DT) * 0.5
    y = torchql.simulate(LinearOscillator(), torch.tensor([0.0, 1.0], dtype=DT), t, rtol=1e-13, atol=1e-15)[:, 0]
    data = torchql.Observations(t, torch.tensor([[float(f"{v:.1e}")] for v in y.tolist()], dtype=DT), observe=["y"])
    x0 = torch.tensor([0.0, 0.86], dtype=DT)
    free = torchql.fit(LinearOscillator(A=0.1, B=3.0), data, x0=torch.tensor([0.0, 1.0], dtype=DT))
    assert free.success and float(free.params["A"]) > 0.1
    for method in torchql.METHODS:
        r = torchql.fit(LinearOscillator(A=0.01526, B=0.4475), data, x0=x0, method=method,
                        bounds={"A": (0.0, None), "B": (0.0, None)}, initial_trajectory="integrate")
        assert r.status is not torchql.Status.DIVERGED, (method, r.message)
        assert torch.isfinite(r.estimates).all() and r.success, (method, r.message)
        assert "lie at their bounds" not in r.message
        assert r.sse == pytest.approx(free.sse, rel=1e-9)
        torch.testing.assert_close(r.estimates, free.estimates, rtol=1e-7, atol=1e-9)


def test_capped_step_is_judged_by_the_model_not_by_its_linear_solution():
    """2-digit oscillator data, guesses A = 0.016, B = 1.94 (a start of the basin study).

    The fifth step asks to raise both rates a thousandfold (capped). The linear solution of that
    step fits the data well, so its own misfit would accept it; the model at A = 16297,
    B = 2972 does not, and once there the iteration drifted for 30 iterations to estimates the
    data cannot fix (NOT_IDENTIFIABLE). A capped step is now accepted only when the model's own
    sum of squares falls: the fit converges to the optimum.
    """
    t = torch.arange(14, dtype=DT) * 0.5
    y = torchql.simulate(LinearOscillator(), torch.tensor([0.0, 1.0], dtype=DT), t, rtol=1e-13, atol=1e-15)[:, 0]
    y = torch.tensor([[float(f"{v:.1e}")] for v in y.tolist()], dtype=DT)
    data = torchql.Observations(t, y, observe=["y"])
    x0 = torch.tensor([y[0, 0].item(), ((y[1, 0] - y[0, 0]) / 0.5).item()], dtype=DT)
    r = torchql.fit(LinearOscillator(A=0.1 * 0.159746, B=3.0 * 0.647142), data, x0=x0, max_iter=30, max_steps=5000,
                    bounds={"A": (0.0, None), "B": (0.0, None)})
    assert r.status is torchql.Status.CONVERGED, r.message
    # the optimum of these data (the basin study's, to its printed digits)
    assert r.params["A"].item() == pytest.approx(0.102054, rel=1e-5)
    assert r.params["B"].item() == pytest.approx(3.00089, rel=1e-5)


@pytest.mark.parametrize("method", torchql.METHODS)
def test_bounds_containing_the_truth_recover_it(data, method):
    r = torchql.fit(LinearOscillator(**GUESS), data, x0=X0, method=method,
                    bounds={"A": (0.0, None), "B": (0.5, 10.0), "y": (-1.0, 1.0)})
    assert r.success, r.message
    scale = torch.where(TRUTH == 0, torch.ones_like(TRUTH), TRUTH.abs())
    assert ((r.estimates - TRUTH).abs() / scale).max() < 1e-8
    for rec in r.history:  # every iterate inside
        assert rec.params["A"] > 0 and 0.5 < rec.params["B"] < 10 and -1 < rec.x0[0] < 1


def test_optimum_on_a_bound_is_reached_and_named(data):
    r = torchql.fit(LinearOscillator(**GUESS), data, x0=X0, bounds={"A": (0.2, None)})
    assert r.success, r.message
    assert 0.2 < r.params["A"].item() <= 0.2 * (1 + 1e-12)
    assert "['A'] lie at their bounds" in r.message
    # the other unknowns are the constrained optimum: the best B, y0, v0 for A = 0.2
    held = torchql.fit(LinearOscillator(A=0.2, B=1.0), data, x0=X0, params=["B"])
    assert held.success
    assert abs(r.params["B"].item() - held.params["B"].item()) < 1e-7 * 3
    assert r.sse == pytest.approx(held.sse, rel=1e-6)


def test_vector_buffer_bound_applies_to_every_element():
    class Linear(torchql.ODEModel):
        state_names = ("x1", "x2")

        def __init__(self, K):
            super().__init__()
            self.register_buffer("K", torch.as_tensor(K, dtype=DT))

        def forward(self, t, x):
            return -(x * self.K)

    t = torch.linspace(0, 2, 11, dtype=DT)
    x = torchql.simulate(Linear([1.0, 2.0]), torch.tensor([1.0, 1.0], dtype=DT), t, rtol=1e-13, atol=1e-15)
    data = torchql.Observations(t, x, observe=["x1", "x2"])
    r = torchql.fit(Linear([0.5, 0.5]), data, fixed_x0=["x1", "x2"], x0=torch.tensor([1.0, 1.0], dtype=DT),
                    bounds={"K": (0.0, 5.0)})
    assert r.success and torch.allclose(r.params["K"], torch.tensor([1.0, 2.0], dtype=DT), rtol=1e-8)
    # a guess beyond the upper bound: moved 1e-3 of the width inside it, and the fit goes on
    r = torchql.fit(Linear([0.5, 6.0]), data, fixed_x0=["x1", "x2"], x0=torch.tensor([1.0, 1.0], dtype=DT),
                    bounds={"K": (0.0, 5.0)})
    assert list(r.moved_guesses) == ["K[1]"] and r.moved_guesses["K[1]"] == pytest.approx((6.0, 4.995), rel=1e-14)
    assert r.success and torch.allclose(r.params["K"], torch.tensor([1.0, 2.0], dtype=DT), rtol=1e-8)


@pytest.mark.parametrize("bounds, error, match", [
    ({"A": (1.0, 0.5)}, ValueError, r"bounds\['A'\].*lower < upper"),
    ({"A": (0.5, 0.5)}, ValueError, r"lower < upper"),
    ({"A": (0.5, 0.5)}, ValueError, r"a fixed value.*`params=`.*`fixed_x0=`"),
    ({"y": (0.5, 0.5)}, ValueError, r"bounds\['y'\].*a fixed value"),
    ({"A": (0.0, math.nan)}, ValueError, r"bounds\['A'\]` upper bound is NaN"),
    ({"Q": (0.0, 1.0)}, ValueError, r"`bounds` names unknown 'Q'"),
    ({"A": 0.5}, TypeError, r"bounds\['A'\].*pair"),
    ({"A": (math.nan, 1.0)}, ValueError, r"bounds\['A'\]` lower bound is NaN"),
    ({"A": ("0", 1.0)}, TypeError, r"number or None"),
    ({"A": (math.inf, None)}, ValueError, r"bounds\['A'\]` lower bound is inf: no value lies above it"),
    ({"A": (None, -math.inf)}, ValueError, r"bounds\['A'\]` upper bound is -inf: no value lies below it"),
    ([("A", (0, 1))], TypeError, r"`bounds` must be a dict"),
])
def test_bad_bounds_are_named(data, bounds, error, match):
    with pytest.raises(error, match=match):
        torchql.fit(LinearOscillator(**GUESS), data, x0=X0, bounds=bounds)


def test_numpy_scalars_are_bounds(data):
    """NumPy's float32 and integer scalars were refused as "a number or None" (its float64 passed)."""
    import numpy as np

    plain = torchql.fit(LinearOscillator(**GUESS), data, x0=X0, bounds={"A": (0.0, 1.0)})
    for lo, hi in ((np.float32(0.0), np.float32(1.0)), (np.int64(0), np.int32(1))):
        r = torchql.fit(LinearOscillator(**GUESS), data, x0=X0, bounds={"A": (lo, hi)})
        torch.testing.assert_close(r.estimates, plain.estimates, rtol=0.0, atol=0.0)
    assert torchql.Parameter(min=np.float32(0.0), max=np.int64(2)).min == 0.0


def test_bound_on_a_fixed_unknown_is_an_error(data):
    with pytest.raises(ValueError, match="not estimated"):
        torchql.fit(LinearOscillator(**GUESS), data, x0=X0, params=["B"], bounds={"A": (0.0, None)})
    with pytest.raises(ValueError, match="not estimated"):
        torchql.fit(LinearOscillator(**GUESS), data, x0=X0, fixed_x0=["y"], bounds={"y": (-1.0, 1.0)})


def test_move_inside_rule():
    """On or beyond a bound: ``1e-3 max(1, |bound|)`` inside one bound, ``1e-3`` of the width inside two."""
    names = ["a", "b", "c", "d", "e", "f"]
    b = Bounds({n: (lo, hi) for n, lo, hi in zip(names, [0.0, 5.0, None, -1.0, -1.0, 0.0],
                                                [None, None, -3.0, 3.0, 3.0, None])},
               names, {}, names, DT, torch.device("cpu"))
    u = torch.tensor([0.0, 4.0, -3.0, -1.0, 10.0, 1e-10], dtype=DT)
    given = u.clone()
    used, moved = b.move_inside(u)
    assert torch.equal(u, given)  # not modified
    assert START_OFFSET == 1e-3 and START_OFFSET == pytest.approx(math.exp(-torchql.bounds.MAX_INTERNAL_STEP))
    expected = torch.tensor([1e-3, 5.005, -3.003, -1.0 + 4e-3, 3.0 - 4e-3, 1e-10], dtype=DT)
    assert torch.allclose(used, expected, rtol=1e-14, atol=0)
    assert moved.tolist() == [True, True, True, True, True, False]  # 1e-10 is inside: kept as given
    # one capped step from the moved point reaches the unknown's scale
    q = b.internal(used)
    back = b.external(q + torchql.bounds.MAX_INTERNAL_STEP * torch.tensor([1, 1, 1, 1, 0, 0], dtype=DT), used)
    assert back[0].item() == pytest.approx(1.0, rel=1e-12)  # distance max(1, |0|)
    assert back[1].item() == pytest.approx(5.0 + 5.0, rel=1e-12)  # distance max(1, |5|)
    assert back[3].item() == pytest.approx(1.0, abs=5e-3)  # near the middle of (-1, 3)
    # rounding: an offset too small for the bound's magnitude still lands strictly inside
    tiny = Bounds({"a": (1e20, 1e20 * (1 + 1e-15))}, ["a"], {}, ["a"], DT, torch.device("cpu"))
    used, _ = tiny.move_inside(torch.tensor([1e20], dtype=DT))
    assert tiny.lower[0] < used[0] < tiny.upper[0]




K_TRUTH = {"k1": 0.9, "k2": 0.4, "k3": 0.25}
K_X0 = torch.tensor([1.0, 0.0, 0.0], dtype=DT)
K_BOUNDS = {"k1": (0.0, None), "k2": (0.0, None), "k3": (0.0, None)}


@pytest.fixture(scope="module")
def kinetics_data():
    t = torch.arange(21, dtype=DT) * 0.5
    x = torchql.simulate(BranchedReactions(**K_TRUTH), K_X0, t, rtol=1e-13, atol=1e-15)
    return torchql.Observations(t, x, observe=["A", "B", "C"])


@pytest.fixture(scope="module")
def kinetics_inside(kinetics_data):
    return torchql.fit(BranchedReactions(0.5, 0.5, 0.5), kinetics_data, K_X0, bounds=K_BOUNDS,
                       initial_trajectory="integrate")


def _relative_error(result, truth):
    return max(abs(result.params[k].item() - v) / abs(v) for k, v in truth.items())


@pytest.mark.parametrize("method", torchql.METHODS)
def test_rates_guessed_on_their_bound_reach_the_optimum(kinetics_data, kinetics_inside, method):
    """Every rate guessed 0, bounded at 0 (as the COPS kinetics start): refused before, now moved to 1e-3.

    Exact data: the optimum is the truth (SSE ~ rounding of the 1e-13 simulation). The start on the
    bound reaches it as the start inside does (measured: 9/10 iterations against 6/5, kantorovich/shooting;
    experiments/bound_start.py), to the same 1e-8 as every exact-data test here.
    """
    model = BranchedReactions(0.0, 0.0, 0.0)
    x0 = K_X0.clone()
    # integrated from the guesses, whose first iterate is the guesses themselves (a start built from
    # the data replaces the coefficients by those fitted to the data's slopes)
    r = torchql.fit(model, kinetics_data, x0, method=method, bounds=K_BOUNDS, initial_trajectory="integrate")
    assert r.status.success, r.message
    assert r.moved_guesses == {"k1": (0.0, 1e-3), "k2": (0.0, 1e-3), "k3": (0.0, 1e-3)}
    assert "['k1', 'k2', 'k3'] lay on or outside their bounds and were moved inside" in r.message
    assert "k1 = 0 -> 0.001" in r.message
    assert "moved guesses      = k1: 0 -> 0.001, k2: 0 -> 0.001, k3: 0 -> 0.001" in r.report()
    assert [r.history[0].params[k].item() for k in K_TRUTH] == [1e-3] * 3  # the first iterate: the guesses used
    assert r.iterations <= kinetics_inside.iterations + 6  # a few more than inside (measured: 3 to 5)
    assert _relative_error(r, K_TRUTH) < 1e-8
    assert r.sse < 1e-20
    assert kinetics_inside.success and _relative_error(kinetics_inside, K_TRUTH) < 1e-8
    for k in K_TRUTH:
        assert r.params[k].item() == pytest.approx(kinetics_inside.params[k].item(), rel=1e-8)
    # nothing the user passed changed
    assert [getattr(model, k).item() for k in K_TRUTH] == [0.0, 0.0, 0.0]
    assert torch.equal(x0, K_X0)
    assert kinetics_inside.moved_guesses == {}
    assert "moved" not in kinetics_inside.message and "moved guesses" not in kinetics_inside.report()


@pytest.mark.parametrize("guess, used", [(0.0, 1e-3), (1.0, 1.0 - 1e-3)], ids=["lower", "upper"])
def test_guess_on_a_two_sided_bound_reaches_the_optimum(data, guess, used):
    """A in (0, 1) guessed on either bound: moved 1e-3 of the width inside, the truth recovered."""
    model = LinearOscillator(A=guess, B=1.0)
    r = torchql.fit(model, data, x0=X0, bounds={"A": (0.0, 1.0), "B": (0.5, 10.0)})
    assert r.success, r.message
    assert list(r.moved_guesses) == ["A"] and r.moved_guesses["A"] == pytest.approx((guess, used), rel=1e-14)
    scale = torch.where(TRUTH == 0, torch.ones_like(TRUTH), TRUTH.abs())
    assert ((r.estimates - TRUTH).abs() / scale).max() < 1e-8
    assert model.A.item() == guess and torch.equal(X0, torch.tensor([0.5, 0.5], dtype=DT))


@pytest.mark.parametrize("bounds, name, moved", [
    ({"A": (0.6, None)}, "A", 0.601),
    ({"A": (None, 0.5)}, "A", 0.499),
    ({"A": (-2.0, None), "y": (2.0, None)}, "y(t0)", 2.002),
])
def test_guess_beyond_or_on_a_one_sided_bound_is_moved_inside(data, bounds, name, moved):
    """``1e-3 max(1, |bound|)`` inside: A = 0.5 below 0.6 to 0.601, on the upper bound 0.5 to 0.499;
    A = 0.5 inside (-2, inf) kept, the initial state y = 0.5 below its bound 2 to 2.002."""
    r = torchql.fit(LinearOscillator(**GUESS), data, x0=X0, bounds=bounds, max_iter=0)
    assert list(r.moved_guesses) == [name] and r.moved_guesses[name] == pytest.approx((0.5, moved), rel=1e-14)
    first = dict(zip(r.unknown_names, torchql.report.unknown_values(r, r.history[0])))
    assert first[name] == pytest.approx(moved, rel=1e-14)
    assert first["A" if name != "A" else "B"] == (0.5 if name != "A" else 1.0)  # the other guesses as given


def test_initial_state_guess_on_its_bound_in_several_experiments():
    """``y' = -k y``, two experiments (y0 = 1.5, 0.8; k = 0.7), ``y`` bounded (0, 2), k (0, None).

    Every guess lies on a bound: ``y0`` on 2 and on 0 (moved to 1.998 and 0.002, per experiment),
    ``k`` on 0. Exact data: the truth is recovered to 1e-8.
    """
    t = torch.linspace(0, 2, 11, dtype=DT)
    datasets = [torchql.Observations(t, (y0 * torch.exp(-0.7 * t)).unsqueeze(-1), observe=["y"]) for y0 in (1.5, 0.8)]
    x0 = torch.tensor([[2.0], [0.0]], dtype=DT)
    model = Decay(0.0)
    r = torchql.fit(model, datasets, x0, bounds={"y": (0.0, 2.0), "k": (0.0, None)})
    assert r.success, r.message
    assert set(r.moved_guesses) == {"y[0](t0)", "y[1](t0)", "k"}
    assert r.moved_guesses["y[0](t0)"] == pytest.approx((2.0, 1.998), rel=1e-14)
    assert r.moved_guesses["y[1](t0)"] == pytest.approx((0.0, 0.002), rel=1e-14)
    assert r.moved_guesses["k"] == pytest.approx((0.0, 1e-3), rel=1e-14)
    assert r.params["k"].item() == pytest.approx(0.7, rel=1e-8)
    assert torch.allclose(r.x0, torch.tensor([[1.5], [0.8]], dtype=DT), rtol=1e-8, atol=0)
    assert model.k.item() == 0.0 and torch.equal(x0, torch.tensor([[2.0], [0.0]], dtype=DT))


def test_multistart_accepts_a_guess_on_its_bound():
    """The central guess k = 0 on its bound (0, None): the first start is it (moved by fit), the
    others' distance from the bound is drawn in [1 / spread, spread]; all reach the truth k = 0.7."""
    t = torch.linspace(0, 2, 11, dtype=DT)
    data = torchql.Observations(t, (1.5 * torch.exp(-0.7 * t)).unsqueeze(-1), observe=["y"])
    ms = torchql.multistart(Decay(0.0), data, torch.tensor([1.5], dtype=DT), starts=4, spread=3.0,
                            bounds={"k": (0.0, None)})
    assert ms.guesses[0, 0].item() == 0.0 and ms.results[0].moved_guesses == {"k": (0.0, 1e-3)}
    assert bool(((ms.guesses[1:] >= 1 / 3) & (ms.guesses[1:] <= 3)).all())
    assert all(r.moved_guesses == {} for r in ms.results[1:])
    assert ms.n_converged == 4 and len(ms.optima) == 1
    assert ms.best.params["k"].item() == pytest.approx(0.7, rel=1e-8)


def test_profile_of_a_fit_started_on_its_bound():
    """A profile re-fits from the fit's estimates (inside), its own limit may sit on the rate's bound.

    ``y' = -k y`` with data perturbed by +-1% (so the SSE is not zero); the fit from k = 0 on its
    bound and the fit from k = 0.5 reach the same optimum, so their profile intervals of k agree
    to the profile's own location tolerance (``xtol`` 1e-3 of the step, about 1e-3 standard errors).
    """
    t = torch.linspace(0, 2, 11, dtype=DT)
    wiggle = torch.tensor([(-1.0) ** i for i in range(11)], dtype=DT)
    data = torchql.Observations(t, (1.5 * torch.exp(-0.7 * t) * (1 + 0.01 * wiggle)).unsqueeze(-1), observe=["y"])
    x0 = torch.tensor([1.5], dtype=DT)
    on = torchql.fit(Decay(0.0), data, x0, bounds={"k": (0.0, None), "y": (0.0, None)})
    inside = torchql.fit(Decay(0.5), data, x0, bounds={"k": (0.0, None), "y": (0.0, None)})
    assert on.success and inside.success and on.moved_guesses == {"k": (0.0, 1e-3)}
    assert on.params["k"].item() == pytest.approx(inside.params["k"].item(), rel=1e-8)
    se = on.stderr["k"]
    p_on = torchql.profile(on, "k", bounds=(0.0, None))
    p_in = torchql.profile(inside, "k", bounds=(0.0, None))
    assert p_on.closed == (True, True) and p_in.closed == (True, True)
    (lo_on, hi_on), (lo_in, hi_in) = p_on.interval, p_in.interval
    assert lo_on < on.params["k"].item() < hi_on
    assert abs(lo_on - lo_in) < 1e-2 * se and abs(hi_on - hi_in) < 1e-2 * se


SIR_POSITIVE = {"beta": (0, None), "gamma": (0, None), "I": (0, None)}


@pytest.fixture(scope="module")
def sir_data():
    """14 daily values of I (the boarding-school influenza shape: N = 763, beta = 1.66, gamma = 0.44, I0 = 1),
    exact and with 3 % multiplicative noise."""
    t = torch.arange(14, dtype=DT)
    x = torchql.simulate(SIR(), torch.tensor([762.0, 1.0, 0.0], dtype=DT), t, rtol=1e-12, atol=1e-12)
    noise = torch.randn(14, 1, generator=torch.Generator().manual_seed(0), dtype=DT)
    return {"exact": torchql.Observations(t, x[:, 1:2], observe=["I"]),
            "noisy": torchql.Observations(t, x[:, 1:2] * (1 + 0.03 * noise), observe=["I"])}


def _fit_sir(data, guess, bounds, method):
    beta, gamma, i0 = guess
    return torchql.fit(SIR(beta, gamma), data, torch.tensor([762.0, i0, 0.0], dtype=DT), fixed_x0=["S", "R"],
                       bounds=bounds, method=method, max_iter=100)


@pytest.mark.parametrize("method", ["kantorovich", "shooting"])
@pytest.mark.parametrize("kind", ["exact", "noisy"])
def test_sir_with_positive_rates_and_initial_state_reaches_the_unbounded_optimum(sir_data, method, kind):
    """SIR, S(t0) = N - 1 and R(t0) = 0 known, only I observed; beta, gamma and I(t0) bounded below by 0.

    From beta = 3, gamma = 1, I0 = 0.5 (each 2-3x the truth) the Kantorovich fit with all three bounds
    once ended far from the optimum (NOT_IDENTIFIABLE on exact data, STALLED on noisy data) where the
    unbounded fit converged: its capped steps in log beta were accepted on the linear solution's misfit.
    Now the bounded fit ends where the unbounded one does, in both methods, and on exact data at the truth.
    """
    data = sir_data[kind]
    free = _fit_sir(data, (3.0, 1.0, 0.5), None, method)
    bounded = _fit_sir(data, (3.0, 1.0, 0.5), SIR_POSITIVE, method)
    assert free.success and bounded.success, (free.message, bounded.message)
    assert bounded.unknown_names == ["I(t0)", "beta", "gamma"]
    assert torch.allclose(bounded.estimates, free.estimates, rtol=1e-6, atol=0)
    if kind == "exact":
        truth = torch.tensor([1.0, 1.66, 0.44], dtype=DT)
        assert torch.allclose(bounded.estimates, truth, rtol=1e-8, atol=0)
        assert bounded.sse < 1e-12 and free.sse < 1e-12
    else:
        assert bounded.sse == pytest.approx(free.sse, rel=1e-9)


def test_sir_shooting_trial_that_overflows_the_grid_solver_is_rejected_not_raised(sir_data):
    """A shooting trial step from beta = 0.6, gamma = 1.2, I0 = 3 (gamma bounded below by 0) gave the grid
    solver a huge finite error ratio whose step-doubling exponent overflowed int64 (OverflowError)."""
    fitted = _fit_sir(sir_data["exact"], (0.6, 1.2, 3.0), {"gamma": (0, None)}, "shooting")
    assert fitted.success, fitted.message
    assert torch.allclose(fitted.estimates, torch.tensor([1.0, 1.66, 0.44], dtype=DT), rtol=1e-8, atol=0)


# --- unknowns on a logarithmic scale (``scale=``): iterated in s = log u, bounds applying to s

def make_log(lower, upper):
    names = ["a", "b", "c", "d"]
    return Bounds({n: (lo, hi) for n, lo, hi in zip(names, lower, upper)}, names, {}, names, DT,
                  torch.device("cpu"), scale={n: "log" for n in names})


def test_log_scale_transform_round_trip_and_derivative():
    """No bound: u = exp(q); lower bound 0 is open on the log scale (the same); lower 1e-5: log u - log 1e-5 =
    exp(q); both: logistic between log 1e-5 and log 1e5."""
    b = make_log([None, 0.0, 1e-5, 1e-5], [None, None, None, 1e5])
    u = torch.tensor([2e-7, 3.0, 0.5, 40.0], dtype=DT)
    q = b.internal(u)
    assert torch.allclose(b.external(q, u), u, rtol=1e-13, atol=0)
    assert torch.allclose(q[:2], u[:2].log(), rtol=1e-15, atol=0)
    assert q[2] == pytest.approx(math.log(math.log(0.5 / 1e-5)), rel=1e-14)
    h = 1e-6
    numeric = (b.external(q + h, u) - b.external(q - h, u)) / (2 * h)
    assert torch.allclose(b.derivative(u), numeric, rtol=1e-8)


def test_log_scale_guesses_on_a_bound_move_inside_on_the_log_scale():
    """``[1e-5, 1e3]`` on the log scale: a guess below moves ``1e-3`` of the log-width inside,
    ``1e-5 * 1e8^0.001`` (not ``1e-3`` of the linear width, which would put it near 1); one-sided:
    ``1e-3 max(1, |log bound|)`` inside in ``log u``; a lower bound 0 keeps the linear rule."""
    b = make_log([1e-5, 1e-5, 1e-5, 0.0], [1e3, 1e3, None, None])
    used, moved = b.move_inside(torch.tensor([8e-6, 1200.0, 1e-5, 0.0], dtype=DT))
    assert moved.tolist() == [True, True, True, True]
    expected = [1e-5 * 1e8 ** 1e-3, 1e3 / 1e8 ** 1e-3, 1e-5 * math.exp(1e-3 * math.log(1e5)), 1e-3]
    assert torch.allclose(used, torch.tensor(expected, dtype=DT), rtol=1e-12, atol=0)


def test_log_scale_step_is_a_relative_change_capped_at_a_factor_1000():
    b = make_log([None, None, 1e-5, None], [None, None, 1e5, None])
    u = torch.tensor([2.0, 2.0, 1.0, 1e-300], dtype=DT)
    change, blocked = b.step(u, torch.tensor([math.log(1.5), 50.0, 40.0, -800.0], dtype=DT))
    new = u + change
    assert new[0] == pytest.approx(3.0, rel=1e-14)  # a step of log 1.5 multiplies by 1.5
    assert new[1] == pytest.approx(2000.0, rel=1e-12)  # capped: a factor 1000
    # bounded on the log scale: ds/dq = (log 1e5 - log 1e-5) / 4 at the middle; capped at the q-step that
    # moves s by log 1000 to first order (the logistic bends, so less: at most a factor 1000, at least 100)
    assert 100.0 < new[2] <= 1000.0 and blocked[2]
    assert new[3] > 0 and torch.isfinite(new).all()  # stays positive, however small


def test_log_scale_fit_recovers_the_truth_and_its_interval_is_of_the_logarithm(data):
    """The oscillator's A and B on a log scale: the truth of exact data (to 1e-8), as on the linear scale;
    the Wald interval is that of log u mapped back, u * exp(-/+ q se / u)."""
    free = torchql.fit(LinearOscillator(**GUESS), data, x0=X0)
    logged = torchql.fit(LinearOscillator(**GUESS), data, x0=X0, scale={"A": "log", "B": "log10"})
    assert logged.success, logged.message
    assert logged.log_scaled == ["A", "B"]
    scale = torch.where(TRUTH == 0, torch.ones_like(TRUTH), TRUTH.abs())
    assert ((logged.estimates - TRUTH).abs() / scale).max() < 1e-8
    assert free.success and torch.allclose(logged.estimates[2:], free.estimates[2:], rtol=1e-8, atol=0)
    noisy = torchql.Observations(data.t, data.y * (1 + 0.01 * torch.randn(data.y.shape, dtype=DT,
                                                                          generator=torch.Generator().manual_seed(3))),
                                 observe=["y"])
    r = torchql.fit(LinearOscillator(**GUESS), noisy, x0=X0, scale={"B": "log"})
    assert r.success, r.message
    b, se = r.params["B"].item(), r.stderr["B"]
    q = torchql.uncertainty.student_t_quantile(0.975, r.dof)
    lo, hi = r.confidence_intervals()["B"]
    assert lo == pytest.approx(b * math.exp(-q * se / b), rel=1e-10)
    assert hi == pytest.approx(b * math.exp(q * se / b), rel=1e-10)
    header = next(line for line in r.report().splitlines() if line.startswith("[[Unknowns]]"))
    assert "of B on the log scale (the interval of log u" in header
    y_lo, y_hi = r.confidence_intervals()["y(t0)"]  # the linear-scale unknowns keep their symmetric intervals
    assert (y_lo + y_hi) / 2 == pytest.approx(r.x0[0].item(), rel=1e-12)


def test_an_estimate_at_the_edge_of_its_log_scale_is_named():
    """Data of a growing oscillation (A = -0.05) fitted with A on a log scale: A runs to the edge 0
    of its scale and the message says it lies at its bound, as with ``bounds={"A": (0, None)}``. A
    log-scaled estimate that is small because the truth is (A = 1e-9, guessed 1e-9) is not named."""
    t = torch.arange(14, dtype=DT) * 0.5
    for truth, guess, named in ((-0.05, 0.5, True), (1e-9, 1e-9, False)):
        y = torchql.simulate(LinearOscillator(truth, 3.0), torch.tensor([0.0, 1.0], dtype=DT), t, rtol=1e-13,
                             atol=1e-15)[:, :1]
        r = torchql.fit(LinearOscillator(guess, 2.9), torchql.Observations(t, y, observe=["y"]), x0=X0,
                        scale={"A": "log"})
        assert r.success, r.message
        assert ("['A'] lie at their bounds" in r.message) is named, r.message
        if named:
            assert r.params["A"].item() < 1e-6 * guess


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(scale={"A": "ln"}), ValueError, r"`scale\['A'\]` must be one of \['lin', 'log', 'log10'\]; received 'ln'"),
    (dict(scale={"A": "log"}, bounds={"A": (-1.0, 1.0)}), ValueError, r"its bounds must lie in \[0, inf\)"),
    (dict(scale={"Q": "log"}), ValueError, r"`scale` names unknown 'Q'"),
    (dict(scale={"A": "log"}, params=["B"]), ValueError, r"`scale` names 'A', which is not estimated"),
    (dict(scale=["A"]), TypeError, r"`scale` must be a dict"),
])
def test_bad_scales_are_named(data, kwargs, error, match):
    with pytest.raises(error, match=match):
        torchql.fit(LinearOscillator(**GUESS), data, x0=X0, **kwargs)


def test_log_scale_needs_a_positive_guess(data):
    with pytest.raises(ValueError, match=r"the guess of 'A' is -0.5, but it is on a log scale"):
        torchql.fit(LinearOscillator(A=-0.5, B=1.0), data, x0=X0, scale={"A": "log"})
    # with a lower bound 0 a guess of 0 is moved inside, as on the linear scale
    r = torchql.fit(LinearOscillator(A=0.0, B=1.0), data, x0=X0, scale={"A": "log"}, bounds={"A": (0.0, None)})
    assert r.success and r.moved_guesses == {"A": (0.0, START_OFFSET)}


def test_log_scale_in_fit_many_equals_fit(data):
    batch = torchql.Observations(data.t, torch.stack([data.y, data.y * 1.01]), observe=["y"])
    many = torchql.fit_many(LinearOscillator(**GUESS), batch, X0, scale={"A": "log"})
    for i in range(2):
        one = torchql.fit(LinearOscillator(**GUESS), batch[i], X0, scale={"A": "log"})
        assert many[i].log_scaled == ["A"] and many[i].iterations == one.iterations
        assert torch.allclose(many[i].estimates, one.estimates, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("argument, given", [
    ("bounds", {"v": (2.0, 3.0), "v(t0)": (0.0, 5.0)}),
    ("bounds", {"v(t0)": (0.0, 5.0), "v": (2.0, 3.0)}),
    ("scale", {"v": "log", "v(t0)": "log"}),
])
def test_an_unknown_named_twice_in_bounds_or_scale_is_an_error(argument, given):
    """A state under its two names (``"v"``, ``"v(t0)"``) in one dict: which entry would win depended on
    the dict's order; now it is an error naming both keys."""
    t = torch.arange(14, dtype=DT) * 0.5
    y = torchql.simulate(LinearOscillator(0.1, 3.0), torch.tensor([0.0, 1.0], dtype=DT), t)[:, :1]
    data = torchql.Observations(t, y, observe=["y"])
    with pytest.raises(ValueError, match=rf"`{argument}` gives v\(t0\) twice, under '.*' and '.*': give it once"):
        torchql.fit(LinearOscillator(0.5, 1.0), data, torch.tensor([0.2, 0.8], dtype=DT), **{argument: given})


def test_a_small_estimate_the_data_determine_is_not_at_its_bound_whatever_the_units():
    """A decay rate bounded below by 0, fitted with time in seconds and in microseconds (the rate
    0.5 and 5e-7, each about 100 standard errors inside the bound): neither is named at its bound,
    and both intervals are the bound's log-variable ones, ``k exp(+-q se / k)``. The test of
    :meth:`Bounds.at_bound` took distances below 1e-6 as at the bound for every estimate below 1."""
    g = torch.Generator().manual_seed(0)
    relative = []
    for unit in (1.0, 1e6):
        k_true = 0.5 / unit
        t = torch.linspace(0, 4 * unit, 21, dtype=DT)
        y = (torch.exp(-k_true * t) + 0.01 * torch.randn(21, generator=g, dtype=DT)).unsqueeze(-1)
        data = torchql.Observations(t, y, observe=["y"], sigma=0.01)
        result = torchql.fit(Decay(k=2 * k_true), data, x0=torch.tensor([1.0], dtype=DT), bounds={"k": (0.0, None)})
        assert result.success and "at their bounds" not in result.message, result.message
        k, se = float(result.params["k"]), result.stderr["k"]
        low, high = result.confidence_intervals()["k"]
        q = 1.959963984540054
        assert low == pytest.approx(k * math.exp(-q * se / k), rel=1e-6)
        assert high == pytest.approx(k * math.exp(q * se / k), rel=1e-6)
        relative.append(se / k)
    assert relative[1] == pytest.approx(relative[0], rel=0.2)  # (different noise draws, the same problem)
    b = Bounds({"k": (0.0, None)}, ["k"], {}, ["k"], DT, torch.device("cpu"))
    u = torch.tensor([5e-7], dtype=DT)
    assert b.at_bound(u) == ["k"] and b.at_bound(u, stderr=torch.tensor([5e-9], dtype=DT)) == []
    assert b.at_bound(torch.tensor([1e-15], dtype=DT), stderr=torch.tensor([5e-9], dtype=DT)) == ["k"]


def test_a_step_toward_a_bound_shrinks_the_distance_at_most_tenfold():
    """SIR counts from rates three times off, bounded below by 0 (:data:`testmodels.SIR_FAR`). A
    step that asked to cross the bound was capped at a factor 1000: the rates went from 0.65 to
    6.5e-4, into a flat stretch of the sum of squares where no epidemic spreads, and further
    capped steps flipped beta between 1.7e-5 and 1.7e-8 (Kantorovich 25 iterations, shooting 42).
    Capped at a factor 10 toward a bound (:data:`torchql.bounds.MAX_TOWARD_STEP`), the rates stay
    above 0.01 on the way, and the fit takes 17."""
    from testmodels import SIR, SIR_FAR, SIR_FAR_GUESSES, sir_counts

    result = torchql.fit(SIR(**SIR_FAR_GUESSES), sir_counts(), **SIR_FAR)
    assert result.status is torchql.Status.CONVERGED, result.message
    assert result.iterations <= 20
    lowest = min(min(float(r.params["beta"]), float(r.params["gamma"])) for r in result.history)
    assert lowest > 0.01
    # the truth within noise (test_engine_steps.py checks this optimum against scipy's)
    assert float(result.params["beta"]) == pytest.approx(0.6, rel=0.02)


def test_a_capped_step_toward_a_bound_and_one_away_from_it():
    """Away from its nearer bound an unknown's distance to it grows at most a thousandfold in a step,
    toward it shrinks at most tenfold: one-sided bounds below and above, and two bounds near
    either (the odds ``(u - lo) / (hi - u)`` then change by those factors)."""
    b = make([0.0, None, 0.0, 0.0], [None, 1.0, 1.0, 1.0])
    u = torch.tensor([0.5, 0.5, 0.01, 0.99], dtype=DT)

    def odds(ratio):  # u of a two-sided unknown on [0, 1] whose odds u / (1 - u) are ``ratio``
        return ratio / (1 + ratio)
    toward, blocked = b.step(u, torch.tensor([-50.0, -50.0, -50.0, 50.0], dtype=DT))
    assert (u + toward).tolist() == pytest.approx([0.05, 0.95, odds(0.01 / 0.99 / 10), odds(99 * 10)], rel=1e-12)
    assert blocked.all()
    away, blocked = b.step(u, torch.tensor([50.0, 50.0, 50.0, -50.0], dtype=DT))
    assert (u + away).tolist() == pytest.approx([500.0, -499.0, odds(0.01 / 0.99 * 1000), odds(99 / 1000)], rel=1e-12)
    assert blocked.all()
