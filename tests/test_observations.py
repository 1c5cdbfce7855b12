"""Validation and conversion of ``torchql.Observations``."""

import math

import numpy as np
import pytest
import torch

import torchql
from testmodels import Decay


T3 = torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64)
Y3 = torch.tensor([[1.0, 2.0], [0.5, 1.5], [0.25, 1.0]], dtype=torch.float64)


# ------------------------------------------------------------------ t
@pytest.mark.parametrize("t", [torch.zeros(3, 1), torch.tensor(1.0), torch.zeros(2, 2)])
def test_t_not_1d(t):
    with pytest.raises(ValueError, match="`t` must be one-dimensional"):
        torchql.Observations(t, torch.zeros(3), ["y"])


def test_t_empty():
    with pytest.raises(ValueError, match="`t` must contain at least one"):
        torchql.Observations(torch.zeros(0), torch.zeros(0), ["y"])


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_t_non_finite(bad):
    with pytest.raises(ValueError, match="`t` must be finite"):
        torchql.Observations([0.0, bad, 2.0], [1.0, 2.0, 3.0], ["y"])


def test_t_non_increasing_names_index_and_values():
    with pytest.raises(ValueError, match=r"`t` must be strictly increasing.*t\[1\] = 2 followed by t\[2\] = 1"):
        torchql.Observations([0.0, 2.0, 1.0], [1.0, 2.0, 3.0], ["y"])


def test_t_duplicate_names_index_and_values():
    with pytest.raises(ValueError, match=r"`t` must be strictly increasing \(no duplicates\).*t\[2\] = 3 followed by t\[3\] = 3"):
        torchql.Observations([0.0, 1.0, 3.0, 3.0], [1.0, 2.0, 3.0, 4.0], ["y"])


def test_t_rejects_non_numeric():
    with pytest.raises(TypeError, match="`t`"):
        torchql.Observations(["a", "b"], [1.0, 2.0], ["y"])


def test_t_rejects_bool_and_complex():
    with pytest.raises(TypeError, match="`t` must be real-valued"):
        torchql.Observations(torch.tensor([False, True]), [1.0, 2.0], ["y"])
    with pytest.raises(TypeError, match="`t` must be real-valued"):
        torchql.Observations(torch.tensor([0.0, 1.0], dtype=torch.complex128), [1.0, 2.0], ["y"])


def test_single_time_accepted():
    obs = torchql.Observations([0.0], [1.0], ["y"])
    assert obs.n_times == 1 and obs.n_outputs == 1


# ------------------------------------------------------------------ y
@pytest.mark.parametrize("y", [torch.zeros(4), torch.zeros(2, 2), torch.zeros(3, 2, 1), torch.tensor(1.0)])
def test_y_wrong_shape(y):
    with pytest.raises(ValueError, match=r"`y` must have shape \(T, K\) = \(3, K\)"):
        torchql.Observations(T3, y, ["y"])


def test_y_with_inf():
    y = Y3.clone()
    y[1, 0] = math.inf
    with pytest.raises(ValueError, match="`y` must not contain inf"):
        torchql.Observations(T3, y, ["x", "u"])


def test_y_all_nan():
    with pytest.raises(ValueError, match="`y` holds no value"):
        torchql.Observations(T3, torch.full((3, 2), math.nan), ["x", "u"])


def test_y_partially_nan_accepted_and_masked():
    y = Y3.clone()
    y[0, 1] = math.nan
    obs = torchql.Observations(T3, y, ["x", "u"])
    expected = torch.ones(3, 2, dtype=torch.bool)
    expected[0, 1] = False
    assert torch.equal(obs.mask, expected)


def test_y_1d_is_one_output():
    obs = torchql.Observations(T3, torch.tensor([1.0, 0.5, 0.25], dtype=torch.float64), ["y"])
    assert obs.y.shape == (3, 1)
    assert obs.n_outputs == 1
    assert obs.sigma.shape == (3, 1) and obs.exact.shape == (3, 1)


# ------------------------------------------------------------------ sigma
@pytest.mark.parametrize(
    "sigma, expected",
    [
        (0.5, torch.full((3, 2), 0.5)),
        (torch.tensor([0.5, 2.0]), torch.tensor([[0.5, 2.0]] * 3)),
        ([0.5, 2.0], torch.tensor([[0.5, 2.0]] * 3)),
        (torch.arange(1.0, 7.0).reshape(3, 2), torch.arange(1.0, 7.0).reshape(3, 2)),
        (None, torch.ones(3, 2)),
    ],
)
def test_sigma_accepted_shapes(sigma, expected):
    obs = torchql.Observations(T3, Y3, ["x", "u"], sigma=sigma)
    assert obs.sigma.shape == (3, 2)
    assert obs.sigma.dtype == obs.y.dtype
    torch.testing.assert_close(obs.sigma, expected.to(torch.float64), rtol=0, atol=0)


@pytest.mark.parametrize("sigma", [torch.ones(3), torch.ones(2, 3), torch.ones(3, 2, 1), torch.ones(1)])
def test_sigma_wrong_shape(sigma):
    with pytest.raises(ValueError, match=r"`sigma` must be a scalar, shape \(K,\) = \(2,\) or shape \(T, K\) = \(3, 2\)"):
        torchql.Observations(T3, Y3, ["x", "u"], sigma=sigma)


@pytest.mark.parametrize("sigma", [0.0, -1.0, math.nan, math.inf, [1.0, 0.0], [1.0, math.nan]])
def test_sigma_non_positive_or_non_finite(sigma):
    with pytest.raises(ValueError, match="`sigma` must be finite and strictly positive"):
        torchql.Observations(T3, Y3, ["x", "u"], sigma=sigma)


def test_sigma_bool_rejected():
    with pytest.raises(TypeError, match="`sigma`"):
        torchql.Observations(T3, Y3, ["x", "u"], sigma=torch.tensor([True, True]))


# ------------------------------------------------------------------ exact
def test_exact_per_time_mask_broadcast():
    obs = torchql.Observations(T3, Y3, ["x", "u"], exact=torch.tensor([True, False, False]))
    expected = torch.zeros(3, 2, dtype=torch.bool)
    expected[0] = True
    assert torch.equal(obs.exact, expected)


def test_exact_full_mask_and_list_and_numpy():
    full = torch.tensor([[True, False], [False, False], [False, True]])
    assert torch.equal(torchql.Observations(T3, Y3, ["x", "u"], exact=full).exact, full)
    assert torch.equal(torchql.Observations(T3, Y3, ["x", "u"], exact=full.tolist()).exact, full)
    assert torch.equal(torchql.Observations(T3, Y3, ["x", "u"], exact=full.numpy()).exact, full)
    default = torchql.Observations(T3, Y3, ["x", "u"]).exact
    assert default.dtype == torch.bool and not default.any() and default.shape == (3, 2)


@pytest.mark.parametrize("exact", [torch.zeros(2, dtype=torch.bool), torch.zeros(2, 3, dtype=torch.bool),
                                   torch.zeros(3, 2, 1, dtype=torch.bool)])
def test_exact_wrong_shape(exact):
    with pytest.raises(ValueError, match=r"`exact` must have shape \(T,\) = \(3,\) or \(T, K\) = \(3, 2\)"):
        torchql.Observations(T3, Y3, ["x", "u"], exact=exact)


@pytest.mark.parametrize("exact", [torch.zeros(3, 2), torch.zeros(3, dtype=torch.long), [1, 0, 0]])
def test_exact_not_bool(exact):
    with pytest.raises(TypeError, match="`exact` must be a boolean mask"):
        torchql.Observations(T3, Y3, ["x", "u"], exact=exact)


# ------------------------------------------------------------------ observe
def test_observe_single_string_rejected():
    with pytest.raises(TypeError, match=r"`observe` must be a sequence of state names, not a single string; use \['y'\]"):
        torchql.Observations(T3, torch.ones(3), "y")


@pytest.mark.parametrize("names", [["x"], ["x", "u", "w"], []])
def test_observe_names_count_mismatch(names):
    with pytest.raises(ValueError, match=r"`observe` names \d+ states but `y` has K = 2 columns"):
        torchql.Observations(T3, Y3, names)


def test_observe_names_must_be_strings():
    with pytest.raises(TypeError, match="`observe`"):
        torchql.Observations(T3, Y3, ["x", 1])


@pytest.mark.parametrize("matrix", [torch.eye(3), torch.ones(2), np.ones((1, 2)), torch.ones(2, 2, 1)])
def test_observe_matrix_wrong_shape(matrix):
    with pytest.raises(ValueError, match=r"`observe` matrix must have shape \(K, n_states\) with K = 2"):
        torchql.Observations(T3, Y3, matrix)


def test_observe_other_types_rejected():
    with pytest.raises(TypeError, match="`observe`"):
        torchql.Observations(T3, Y3, 3)


def test_observe_matrix_and_callable_accepted():
    assert torchql.Observations(T3, Y3, torch.eye(2)).n_outputs == 2
    assert torchql.Observations(T3, Y3, np.eye(2)).n_outputs == 2
    assert torchql.Observations(T3, Y3, lambda x: x).n_outputs == 2
    assert torchql.Observations(T3, Y3, ("x", "u")).n_outputs == 2


# ------------------------------------------------------------------ conversion
def test_lists_and_numpy_converted_to_float_tensors():
    obs = torchql.Observations([0, 1, 2], np.array([3, 2, 1]), ["y"], sigma=[2], exact=np.array([True, False, False]))
    for value in (obs.t, obs.y, obs.sigma):
        assert isinstance(value, torch.Tensor)
        assert value.dtype == torch.float64
    assert torch.equal(obs.t, torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64))
    assert torch.equal(obs.y, torch.tensor([[3.0], [2.0], [1.0]], dtype=torch.float64))
    assert torch.equal(obs.sigma, torch.full((3, 1), 2.0, dtype=torch.float64))
    assert obs.exact.dtype == torch.bool


def test_y_follows_dtype_of_t():
    obs = torchql.Observations(torch.tensor([0.0, 1.0]), np.array([1.0, 2.0]), ["y"], sigma=np.float64(0.5))
    assert obs.t.dtype == torch.float32
    assert obs.y.dtype == torch.float32
    assert obs.sigma.dtype == torch.float32


def test_integer_tensors_converted():
    obs = torchql.Observations(torch.arange(3), torch.arange(3) + 1, ["y"])
    assert obs.t.dtype == torch.float64 and obs.y.dtype == torch.float64


# ------------------------------------------------------------------ no mutation
def test_user_tensors_not_mutated_by_construction_or_fit():
    t = torch.tensor([0.0, 0.4, 0.8, 1.2, 1.6, 2.0], dtype=torch.float64)
    y = 2.0 * torch.exp(-0.7 * t)
    y[2] = math.nan
    sigma = torch.full((6,), 0.1, dtype=torch.float64).unsqueeze(-1)
    exact = torch.zeros(6, dtype=torch.bool)
    exact[0] = True
    originals = [v.clone() for v in (t, y, sigma, exact)]

    def unchanged():
        for now, before in zip((t, y, sigma, exact), originals):
            torch.testing.assert_close(now, before, rtol=0, atol=0, equal_nan=True)

    data = torchql.Observations(t, y, ["y"], sigma=sigma, exact=exact)
    unchanged()
    stored = [v.clone() for v in (data.t, data.y, data.sigma, data.exact)]
    result = torchql.fit(Decay(0.3), data, grid=10)
    assert result.success
    unchanged()
    for now, before in zip((data.t, data.y, data.sigma, data.exact), stored):
        torch.testing.assert_close(now, before, rtol=0, atol=0, equal_nan=True)


def test_observations_keep_copies_of_t_and_y():
    t = torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64)
    y = torch.tensor([1.0, 0.5, 0.25], dtype=torch.float64)
    data = torchql.Observations(t, y, observe=["y"])
    t[1] = 5.0  # editing the caller's tensor afterwards cannot bypass validation
    y[0] = float("inf")
    assert data.t[1].item() == 1.0 and data.y[0, 0].item() == 1.0


def test_sigma_per_time_for_a_single_output():
    t = torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64)
    data = torchql.Observations(t, torch.ones(3, dtype=torch.float64), observe=["y"],
                                sigma=torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64))
    assert data.sigma.shape == (3, 1) and data.sigma[2, 0].item() == pytest.approx(0.3)
