"""Property-based tests (hypothesis) of the estimator and of the entry points' validation.

1. Random stable linear systems ``x' = K x`` (2-5 states) with a random subset of ``K``'s entries
   unknown, every initial state unknown and random observation operators: from exact data,
   ``torchql.fit`` recovers the truth, or reports ``Status.NOT_IDENTIFIABLE`` exactly when the
   data cannot determine the unknowns. Identifiability is decided independently of torchql: the
   observations have the closed form ``y(t) = Q expm(K t) x0``, whose Jacobian with respect to the
   unknowns (by ``torch.func.jacrev`` through ``torch.linalg.matrix_exp``) is rank-tested by SVD.
   Draws in the grey zone between clearly full rank and clearly rank deficient are rejected.
   The default run fits a few systems per property; ``TORCHQL_THOROUGH=1`` fits the full count.
2. Garbage inputs to ``Observations(...)`` and ``fit(...)`` (wrong shapes, NaN, inf, negative
   values, strings, wrong dtypes, unsorted times, wrong types) either work or raise
   ``TypeError``/``ValueError``/``NotImplementedError`` naming the argument, in backticks.
"""

import math
import os
import warnings

import numpy as np
import pytest
import torch

import torchql

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, Phase, assume, event, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

DT = torch.float64
T_END, N_TIMES = 6.0, 25
#: Random linear systems fitted per property: a handful in the default run (each fit takes seconds,
#: a non-identifiable one tens of seconds), the full count with ``TORCHQL_THOROUGH=1``.
THOROUGH = os.environ.get("TORCHQL_THOROUGH") == "1"
IDENTIFIABLE_EXAMPLES, DEFICIENT_EXAMPLES = (15, 10) if THOROUGH else (6, 4)
#: Singular-value ratios (unit-norm columns) that count as clearly full rank / clearly deficient.
IDENTIFIABLE_RATIO, DEFICIENT_RATIO = 1e-4, 1e-11


class PartlyKnownLinear(torchql.ODEModel):
    """``x' = K x`` with ``K = K_known + sum_j k_j E_j``: the unknown entries are the vector buffer ``k``."""

    constants = ("K_known", "E")

    def __init__(self, K_known: torch.Tensor, positions: list[tuple[int, int]], k: torch.Tensor) -> None:
        super().__init__()
        n = K_known.shape[0]
        self.state_names = tuple(f"x{i}" for i in range(n))
        E = torch.zeros(len(positions), n, n, dtype=DT)
        for j, (r, c) in enumerate(positions):
            E[j, r, c] = 1.0
        self.register_buffer("K_known", K_known.clone())
        self.register_buffer("E", E)
        self.register_buffer("k", k.clone())

    def forward(self, t, x):
        K = self.K_known + torch.einsum("j,jrc->rc", self.k, self.E)
        return x @ K.T


class Linear(torchql.ODEModel):
    """``x' = K x`` with the whole matrix ``K`` a buffer (estimated element-wise as ``K[i,j]``)."""

    def __init__(self, K: torch.Tensor) -> None:
        super().__init__()
        self.state_names = tuple(f"x{i}" for i in range(K.shape[0]))
        self.register_buffer("K", K.clone())

    def forward(self, t, x):
        return x @ self.K.mT  # (K batched under vmap: .T of a 3-d tensor is deprecated)


def stable_matrix(rng: np.random.Generator, n: int) -> torch.Tensor:
    """``-(S S^T + 0.2 I) + (W - W^T) / 2``, scaled to spectral radius 1 (time constants 1-10)."""
    S = rng.normal(size=(n, n)) / math.sqrt(n)
    W = rng.normal(size=(n, n))
    K = -(S @ S.T + 0.2 * np.eye(n)) + 0.5 * (W - W.T)
    K /= np.abs(np.linalg.eigvals(K)).max()
    return torch.tensor(K, dtype=DT)


def observations_closed_form(K, x0, Q, t):
    """``y(t_i) = Q expm(K t_i) x0``, shape ``(T, m)``."""
    return torch.einsum("mn,tnk,k->tm", Q, torch.linalg.matrix_exp(t[:, None, None] * K), x0)


def singular_value_ratio(jacobian: torch.Tensor) -> float:
    """``s_min / s_max`` of the Jacobian with unit-norm columns (scale-free rank measure)."""
    norms = jacobian.norm(dim=0)
    if (norms == 0).any():
        return 0.0
    s = torch.linalg.svdvals(jacobian / norms)
    return float(s[-1] / s[0])


@st.composite
def linear_problems(draw):
    n = draw(st.integers(2, 5), label="n")
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1), label="seed"))
    K = stable_matrix(rng, n)
    x0 = torch.tensor(rng.normal(size=n), dtype=DT)
    x0 = x0 / x0.norm() * 2.0
    whole = n <= 3 and draw(st.booleans(), label="whole K unknown")
    entries = [(r, c) for r in range(n) for c in range(n)]
    if whole:
        positions = entries
    else:
        m = draw(st.integers(1, min(n * n, 6)), label="unknown entries")
        positions = [entries[i] for i in sorted(rng.choice(n * n, size=m, replace=False))]
    kind = draw(st.sampled_from(["states", "matrix"]), label="observation operator")
    if kind == "states":
        observed = sorted(rng.choice(n, size=draw(st.integers(1, n), label="observed states"), replace=False))
        Q = torch.eye(n, dtype=DT)[list(observed)]
        observe = [f"x{i}" for i in observed]
    else:
        rows = draw(st.integers(1, n), label="matrix rows")
        Q = torch.tensor(rng.normal(size=(rows, n)), dtype=DT)
        assume(torch.linalg.matrix_rank(Q) == rows)
        observe = Q
    method = draw(st.sampled_from(torchql.METHODS), label="method")
    return dict(n=n, rng=rng, K=K, x0=x0, whole=whole, positions=positions, Q=Q, observe=observe, method=method)


def _fit_linear(problem):
    """The data's times and the unknowns' truth; the independent singular-value ratio."""
    n, K, x0, Q = problem["n"], problem["K"], problem["x0"], problem["Q"]
    positions = problem["positions"]
    t = torch.linspace(0.0, T_END, N_TIMES, dtype=DT)
    rows = torch.tensor([r for r, _ in positions])
    cols = torch.tensor([c for _, c in positions])
    k_true = K[rows, cols].clone()
    assume(N_TIMES * Q.shape[0] >= n + len(positions))  # fewer values than unknowns: a ValueError, tested elsewhere

    # independent identifiability check at the truth: unknowns (x0, k)
    def outputs(u):
        Ku = K.index_put((rows, cols), u[n:])
        return observations_closed_form(Ku, u[:n], Q, t).reshape(-1)

    ratio = singular_value_ratio(torch.func.jacrev(outputs)(torch.cat([x0, k_true])))
    assume(ratio > IDENTIFIABLE_RATIO or ratio < DEFICIENT_RATIO)  # no grey zone
    return ratio, torch.cat([x0, k_true]), t, rows, cols, k_true


def _run_fit(problem, t, rows, cols, k_true):
    n, rng, K, x0, Q, positions = (problem[key] for key in ("n", "rng", "K", "x0", "Q", "positions"))
    data = torchql.Observations(t, observations_closed_form(K, x0, Q, t), observe=problem["observe"])
    # guesses: every unknown entry 10% off (plus 0.05 absolute), every initial state 0.1 off
    k_guess = k_true * torch.tensor(1 + 0.1 * rng.choice([-1.0, 1.0], size=len(positions)), dtype=DT) + 0.05
    x0_guess = x0 + torch.tensor(0.1 * rng.choice([-1.0, 1.0], size=n), dtype=DT)
    if problem["whole"]:
        model = Linear(K.index_put((rows, cols), k_guess))
        names = [f"K[{r},{c}]" for r, c in positions]
    else:
        K_known = K.index_put((rows, cols), torch.zeros(len(positions), dtype=DT))
        model = PartlyKnownLinear(K_known, positions, k_guess)
        names = [f"k[{j}]" for j in range(len(positions))]
    # max_iter: one derandomized draw (4 states, 6 entries unknown, 2 observed, ratio 3e-4, shooting)
    # follows a curved valley where the undamped steps fail and the damped ones gain ~20% a step:
    # it converges to the truth in 57 iterations
    result = torchql.fit(model, data, x0=x0_guess, method=problem["method"], grid=60, max_iter=100, max_steps=2000)
    assert result.unknown_names == [f"x{i}(t0)" for i in range(n)] + names
    return result


@pytest.mark.slow
@settings(max_examples=IDENTIFIABLE_EXAMPLES, deadline=None, derandomize=True, phases=[Phase.explicit, Phase.generate],
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(problem=linear_problems())
def test_random_identifiable_linear_systems_are_recovered(problem):
    ratio, expected, t, rows, cols, k_true = _fit_linear(problem)
    assume(ratio > IDENTIFIABLE_RATIO)
    event(f"{problem['method']}, {'whole K' if problem['whole'] else 'some entries'}")
    result = _run_fit(problem, t, rows, cols, k_true)
    assert result.success, (ratio, result.message, result)
    # exact data (closed form, ~1e-15): the error is the integrator's (rtol 1e-10) times the
    # conditioning, bounded by 1 / ratio < 1e4
    assert ((result.estimates - expected).abs() / (1 + expected.abs())).max() < 1e-5, (ratio, result)


@pytest.mark.slow
@settings(max_examples=DEFICIENT_EXAMPLES, deadline=None, derandomize=True, phases=[Phase.explicit, Phase.generate],
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(problem=linear_problems())
def test_random_non_identifiable_linear_systems_are_reported(problem):
    ratio, expected, t, rows, cols, k_true = _fit_linear(problem)
    assume(ratio < DEFICIENT_RATIO)
    event(f"{problem['method']}, {'whole K' if problem['whole'] else 'some entries'}")
    result = _run_fit(problem, t, rows, cols, k_true)
    assert result.status == torchql.Status.NOT_IDENTIFIABLE, (ratio, result)


# ------------------------------------------------------------------------------------------------
class Decay(torchql.ODEModel):
    """``y' = -k y``, ``z' = -2 k z``."""

    state_names = ("y", "z")

    def __init__(self, k=1.0):
        super().__init__()
        self.register_buffer("k", torch.tensor(k, dtype=DT))

    def forward(self, t, x):
        return torch.stack((-self.k * x[..., 0], -2 * self.k * x[..., 1]), dim=-1)


_T = torch.linspace(0.0, 2.0, 5, dtype=DT)
_Y = torch.stack((torch.exp(-_T), torch.exp(-2 * _T)), dim=-1)
OBSERVATIONS_ARGS = dict(t=_T, y=_Y, observe=["y", "z"], sigma=torch.full((2,), 0.1, dtype=DT),
                         exact=torch.zeros(5, 2, dtype=torch.bool))
FIT_ARGS = dict(x0=torch.tensor([1.0, 1.0], dtype=DT), params=["k"], fixed_x0=None, t0=None, method="kantorovich",
                bounds=None, max_iter=1, solver="dopri5", rtol=None, atol=None, xtol=None, ftol=None, rcond=None,
                grid=20, initial_trajectory="integrate", max_steps=None, callback=None)

GARBAGE = [
    None, "", "nonsense", "1.0", b"bytes", 1 + 2j, True, False, -1, 0, 3, 2.5, -2.5, math.nan, math.inf, -math.inf,
    [], [[1.0, 2.0], [3.0]], ["a", "b"], {"k": 1.0}, (None,), object(), len,
    torch.tensor(math.nan), torch.tensor(-1.0), torch.zeros(0), torch.zeros(2, 3, 4), torch.ones(7),
    torch.tensor([1 + 1j, 2 + 0j]), torch.tensor([True, False]), torch.arange(3), np.array(["x", "y"]),
    np.zeros((5, 2), dtype=np.float32), {"k": (0.0, None)}, {"k": ("a", 1)}, ["k", "k"], ["nope"], ["y", 3],
]


def _corruptions(value):
    """Garbage derived from a valid tensor argument: the right shape with bad entries, or the wrong shape/dtype."""
    if not isinstance(value, torch.Tensor):
        return []
    out = [value.reshape(-1)[:-1] if value.numel() > 1 else value.reshape(1, 1, 1), value.unsqueeze(0),
           value.to(torch.complex128) if value.is_floating_point() else value.to(torch.float64),
           value.flip(0), value.to(torch.int64), value.to(torch.bool), value.numpy().astype(str).tolist()]
    if value.is_floating_point():
        for bad in (math.nan, math.inf, -math.inf, -1.0, 0.0):
            v = value.clone()
            v.reshape(-1)[0] = bad
            out.append(v)
            v = value.clone()
            v.fill_(bad)
            out.append(v)
    if value.dim() >= 1 and value.shape[0] > 1:
        out.append(value[torch.randperm(value.shape[0], generator=torch.Generator().manual_seed(0))])
    if value.dim() == 2:
        out.append(value.T)
    return out


def _garbage_for(name, baseline):
    return st.sampled_from(GARBAGE + _corruptions(baseline.get(name)))


@st.composite
def garbage_calls(draw):
    target = draw(st.sampled_from(["Observations", "fit"]))
    baseline = OBSERVATIONS_ARGS if target == "Observations" else {"model": Decay(0.5), "data": None, **FIT_ARGS}
    name = draw(st.sampled_from(sorted(baseline)))
    value = draw(_garbage_for(name, baseline))
    return target, name, value


def _message_names(exc, name):
    return (f"`{name}`" in str(exc) or f"`{name}[" in str(exc)  # an element of a list argument
            or (name == "model" and "`model." in str(exc)))


@settings(max_examples=250, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(call=garbage_calls())
def test_garbage_inputs_raise_only_type_or_value_errors_naming_the_argument(call):
    target, name, value = call
    obs_kwargs = dict(OBSERVATIONS_ARGS)
    if target == "Observations":
        obs_kwargs[name] = value
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            data = torchql.Observations(**obs_kwargs)
            if target == "fit":
                kwargs = dict(FIT_ARGS)
                model, data_arg = Decay(0.5), data
                if name == "model":
                    model = value
                elif name == "data":
                    data_arg = value
                else:
                    kwargs[name] = value
                torchql.fit(model, data_arg, **kwargs)
        except (TypeError, ValueError, NotImplementedError) as exc:
            assert _message_names(exc, name), f"{target}({name}={value!r}) raised {type(exc).__name__}: {exc}"


#: Garbage that once escaped validation with an unnamed error; each must now name its argument.
FORMER_GAPS = [
    ("Observations", "exact", "yes"),  # TypeError: new(): invalid data type 'str'
    ("Observations", "exact", {"a": 1}),  # RuntimeError: Could not infer dtype of dict
    ("Observations", "exact", [[1.0, 2.0], [3.0]]),  # ValueError: expected sequence of length 2 at dim 1
    ("fit", "params", 3),  # TypeError: 'int' object is not iterable
    ("fit", "fixed_x0", 1 + 2j),  # TypeError: 'complex' object is not iterable
    ("fit", "method", np.array(["a", "b"])),  # ValueError: The truth value of an array ... is ambiguous
    ("fit", "solver", np.array(["a", "b"])),
    ("fit", "initial_trajectory", np.array(["a", "b"])),
]


@pytest.mark.parametrize("target, name, value", FORMER_GAPS,
                         ids=[f"{t}-{n}-{type(v).__name__}" for t, n, v in FORMER_GAPS])
def test_former_validation_gaps(target, name, value):
    """Each case raises TypeError/ValueError naming the argument."""
    obs_kwargs = dict(OBSERVATIONS_ARGS)
    if target == "Observations":
        obs_kwargs[name] = value
    with pytest.raises((TypeError, ValueError)) as info:
        data = torchql.Observations(**obs_kwargs)
        torchql.fit(Decay(0.5), data, **{**FIT_ARGS, name: value})
    assert _message_names(info.value, name), str(info.value)
