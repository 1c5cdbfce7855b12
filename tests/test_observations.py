"""Validation and conversion of ``torchql.Observations``."""

import math
import re

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
    with pytest.raises(ValueError, match=r"Sort the times, and the values with them"):
        torchql.Observations([0.0, 2.0, 1.0], [1.0, 2.0, 3.0], ["y"])


def test_t_duplicate_names_index_and_values():
    with pytest.raises(ValueError, match=r"`t` must be strictly increasing \(no duplicates\).*t\[2\] = 3 followed by t\[3\] = 3"):
        torchql.Observations([0.0, 1.0, 3.0, 3.0], [1.0, 2.0, 3.0, 4.0], ["y"])
    with pytest.raises(ValueError, match=r"Replicate measurements at one time are columns"):
        torchql.Observations([0.0, 1.0, 3.0, 3.0], [1.0, 2.0, 3.0, 4.0], ["y"])


def test_replicates_as_columns_are_the_advised_remedy():
    """What the duplicate-time error advises works: two replicates at 3.0 as two columns of one state, one
    missing elsewhere: the four values are exact samples of y' = -k y with k = ln 2, which the fit recovers."""
    t = torch.tensor([0.0, 1.0, 3.0], dtype=torch.float64)
    y = torch.tensor([[1.0, float("nan")], [0.5, float("nan")], [0.125, 0.125]], dtype=torch.float64)
    result = torchql.fit(Decay(k=0.5), torchql.Observations(t, y, observe=["y", "y"]),
                         torch.tensor([0.9], dtype=torch.float64))
    assert result.success and result.n_observations == 4
    assert result.params["k"].item() == pytest.approx(math.log(2.0), rel=1e-7)


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


# ------------------------------------------------------------------ a batch of datasets, values (B, T, K)
YB = torch.stack([Y3, 2.0 * Y3, -Y3, Y3 + 1.0])  # (B, T, K) = (4, 3, 2)


def test_batch_shapes_and_defaults():
    obs = torchql.Observations(T3, YB, ["x", "u"])
    assert obs.batch_size == 4 and len(obs) == 4
    assert obs.n_times == 3 and obs.n_outputs == 2
    assert obs.y.shape == obs.sigma.shape == obs.exact.shape == obs.mask.shape == (4, 3, 2)
    assert torch.equal(obs.sigma, torch.ones(4, 3, 2, dtype=torch.float64)) and not obs.sigma_given
    assert not obs.exact.any() and obs.t.shape == (3,)
    assert repr(obs) == "Observations(B=4, T=3, K=2, t=[0, 1])"
    assert torchql.Observations(T3, Y3, ["x", "u"]).batch_size is None


@pytest.mark.parametrize("sigma", [
    0.5, torch.tensor([0.5, 2.0]), torch.full((3, 2), 0.5), torch.full((4, 1, 2), 0.5), torch.full((4, 3, 2), 0.5),
    torch.full((4, 1, 1), 0.5), torch.full((1, 3, 2), 0.5),
])
def test_batch_sigma_broadcasts_to_b_t_k(sigma):
    obs = torchql.Observations(T3, YB, ["x", "u"], sigma=sigma)
    expected = torch.broadcast_to(torch.as_tensor(sigma, dtype=torch.float64), (4, 3, 2))
    assert obs.sigma_given and obs.sigma.is_contiguous()
    torch.testing.assert_close(obs.sigma, expected, rtol=0, atol=0)


def test_batch_sigma_per_sample_and_per_time_for_one_output():
    y = YB[..., :1]  # K = 1
    per_time = torchql.Observations(T3, y, ["x"], sigma=torch.tensor([0.1, 0.2, 0.3]))
    assert per_time.sigma.shape == (4, 3, 1) and per_time.sigma[2, :, 0].tolist() == pytest.approx([0.1, 0.2, 0.3])
    per_sample = torchql.Observations(T3, y, ["x"], sigma=torch.arange(1.0, 5.0).reshape(4, 1, 1))
    assert per_sample.sigma[:, 1, 0].tolist() == [1.0, 2.0, 3.0, 4.0]


@pytest.mark.parametrize("sigma", [torch.ones(3), torch.ones(4, 3), torch.ones(5, 3, 2), torch.ones(4, 2, 2),
                                   torch.ones(2, 4, 3, 2)])
def test_batch_sigma_wrong_shape_names_expected_and_received(sigma):
    expected = r"`sigma` must be .* or broadcast to \(B, T, K\) = \(4, 3, 2\); received shape "
    with pytest.raises(ValueError, match=expected + re.escape(str(tuple(sigma.shape)))):
        torchql.Observations(T3, YB, ["x", "u"], sigma=sigma)


def test_batch_sigma_checked_in_every_sample():
    sigma = torch.ones(4, 3, 2)
    sigma[3, 2, 1] = 0.0
    with pytest.raises(ValueError, match="`sigma` must be finite and strictly positive"):
        torchql.Observations(T3, YB, ["x", "u"], sigma=sigma)


def test_batch_exact_shapes():
    per_time = torchql.Observations(T3, YB, ["x", "u"], exact=torch.tensor([True, False, False]))
    assert per_time.exact.shape == (4, 3, 2) and per_time.exact[:, 0].all() and not per_time.exact[:, 1:].any()
    own = torch.zeros(4, 3, 2, dtype=torch.bool)
    own[2, 1, 0] = True
    assert torch.equal(torchql.Observations(T3, YB, ["x", "u"], exact=own).exact, own)
    with pytest.raises(ValueError, match=r"`exact` must have shape \(T,\) = \(3,\) or \(T, K\) = \(3, 2\), or "
                                         r"broadcast to \(B, T, K\) = \(4, 3, 2\); received shape \(5, 3, 2\)"):
        torchql.Observations(T3, YB, ["x", "u"], exact=torch.zeros(5, 3, 2, dtype=torch.bool))


TB = torch.stack([T3, T3 + 0.25, 2.0 * T3, T3 - 1.0])  # per-sample times (B, T) = (4, 3)


def test_batch_per_sample_times_shapes_indexing_and_repr():
    sigma = torch.arange(1.0, 5.0).reshape(4, 1, 1)
    obs = torchql.Observations(TB, YB, ["x", "u"], sigma=sigma)
    assert obs.per_sample_times and obs.t.shape == (4, 3) and obs.n_times == 3 and len(obs) == 4
    assert not torchql.Observations(T3, YB, ["x", "u"]).per_sample_times
    assert repr(obs) == "Observations(B=4, T=3, K=2, t per sample in [-1, 2])"
    for b in (2, -1):
        sample = obs[b]
        single = torchql.Observations(TB[b], YB[b], ["x", "u"], sigma=sigma[b, 0, 0])
        assert sample.batch_size is None and not sample.per_sample_times
        for name in ("t", "y", "sigma", "exact"):
            assert torch.equal(getattr(sample, name), getattr(single, name)), name
    assert repr(obs[1]) == "Observations(T=3, K=2, t=[0.25, 1.25])"
    assert [s.t[0].item() for s in obs] == [0.0, 0.25, 0.0, -1.0]  # iteration: each sample with its own times
    part = obs[::-2]  # a slice keeps its samples' times
    assert part.per_sample_times and torch.equal(part.t, TB[[3, 1]]) and torch.equal(part.y, YB[[3, 1]])
    assert part.sigma[:, 0, 0].tolist() == [4.0, 2.0]


def test_batch_per_sample_times_copied_and_missing_values_per_sample():
    t, y = TB.clone(), YB.clone()
    y[1, 0, 0] = math.nan
    obs = torchql.Observations(t, y, ["x", "u"])
    t[0, 0] = 5.0  # the caller's tensor edited afterwards: the Observations kept its own copy
    assert obs.t[0, 0].item() == 0.0 and torch.equal(TB[1:], t[1:])
    obs[0].t[1] = 9.0  # editing a sample leaves the batch as it was
    assert obs.t[0, 1].item() == 0.5
    assert obs.mask.flatten(1).sum(dim=1).tolist() == [6, 5, 6, 6]
    assert torch.equal(obs[1].mask, torchql.Observations(TB[1], y[1], ["x", "u"]).mask)
    assert torchql.Observations(TB.numpy(), YB.numpy(), ["x", "u"]).t.dtype == torch.float64  # arrays converted


@pytest.mark.parametrize("t, y, match", [
    (TB, Y3, r"`t` must be one-dimensional, shape \(T,\), for one dataset; per-sample times \(B, T\) need values "
             r"`y` of shape \(B, T, K\); received `t` of shape \(4, 3\) and `y` of shape \(3, 2\)"),
    (TB[:2], YB, r"`t` of shape \(B, T\) must give the times of each of the B = 4 samples of `y` \(4, 3, 2\): "
                 r"expected shape \(4, 3\) or \(3,\) \(shared\); received shape \(2, 3\)"),
    (torch.zeros(4, 3, 1), YB, r"`t` must be one-dimensional, shape \(T,\), or for a batch two-dimensional, "
                               r"shape \(B, T\) \(each sample's own times\); received shape \(4, 3, 1\)"),
    (torch.zeros(4, 2), YB, r"`y` must have shape \(T, K\) = \(2, K\) to match `t`, or \(B, T, K\) = "
                            r"\(B, 2, K\) for a batch of B datasets; received shape \(4, 3, 2\)"),
    (torch.zeros(4, 0), torch.zeros(4, 0, 2), "`t` must contain at least one observation time"),
])
def test_batch_per_sample_times_bad_shapes(t, y, match):
    with pytest.raises(ValueError, match=match):
        torchql.Observations(t, y, ["x", "u"])


def test_batch_per_sample_times_checked_row_by_row():
    t = TB.clone()
    t[2, 1] = math.nan
    with pytest.raises(ValueError, match=r"`t` must be finite in every row; received NaN or inf times in row t\[2\] "
                                         r"\(the times of sample 2\)"):
        torchql.Observations(t, YB, ["x", "u"])
    t = TB.clone()
    t[3, 2] = t[3, 1]
    with pytest.raises(ValueError, match=r"`t` must be strictly increasing \(no duplicates\) in every row; received "
                                         r"t\[3, 1\] = -0.5 followed by t\[3, 2\] = -0.5 \(the times of sample 3\)"):
        torchql.Observations(t, YB, ["x", "u"])
    t = TB.clone()
    t[1] = t[1].flip(0)
    with pytest.raises(ValueError, match=r"received t\[1, 0\] = 1.25 followed by t\[1, 1\] = 0.75 \(the times of "
                                         r"sample 1\)"):
        torchql.Observations(t, YB, ["x", "u"])


@pytest.mark.parametrize("y, match", [
    (torch.zeros(4, 2, 2), r"`y` must have shape \(T, K\) = \(3, K\) to match `t`, or \(B, T, K\) = \(B, 3, K\) "
                           r"for a batch of B datasets; received shape \(4, 2, 2\)"),
    (torch.zeros(2, 4, 3, 2), r"received shape \(2, 4, 3, 2\)"),
    (torch.zeros(0, 3, 2), r"`y` must hold at least one dataset: shape \(B, T, K\) with B >= 1; received shape "
                           r"\(0, 3, 2\)"),
])
def test_batch_y_wrong_shape(y, match):
    with pytest.raises(ValueError, match=match):
        torchql.Observations(T3, y, ["x", "u"])


def test_batch_y_inf_and_empty_sample_named():
    y = YB.clone()
    y[2, 1, 0] = math.inf
    with pytest.raises(ValueError, match=r"`y` must not contain inf \(y\[2\] does\)"):
        torchql.Observations(T3, y, ["x", "u"])
    y = YB.clone()
    y[1] = math.nan
    y[3] = math.nan
    with pytest.raises(ValueError, match=r"`y\[1\]` holds no value: every entry of that sample is NaN \(samples "
                                         r"\[1, 3\] alike\); remove it from the batch"):
        torchql.Observations(T3, y, ["x", "u"])


def test_batch_observe_checked_once_against_k():
    with pytest.raises(ValueError, match=r"`observe` names 1 states but `y` has K = 2 columns"):
        torchql.Observations(T3, YB, ["x"])


def test_batch_missing_values_per_sample():
    """Each sample keeps its own NaNs: sample b's mask is the one of its own Observations."""
    y = YB.clone()
    y[0, 1, 0] = math.nan
    y[3, :2, 1] = math.nan
    obs = torchql.Observations(T3, y, ["x", "u"])
    assert obs.mask.flatten(1).sum(dim=1).tolist() == [5, 6, 6, 4]
    for b in range(4):
        single = torchql.Observations(T3, y[b], ["x", "u"])
        assert torch.equal(obs[b].mask, single.mask)


def test_batch_indexing_gives_the_single_dataset():
    sigma = torch.arange(1.0, 25.0).reshape(4, 3, 2)
    exact = torch.zeros(4, 3, 2, dtype=torch.bool)
    exact[1, 0] = True
    observe = ["x", "u"]
    obs = torchql.Observations(T3, YB, observe, sigma=sigma, exact=exact)
    for b in (1, -3):
        sample = obs[b]
        single = torchql.Observations(T3, YB[b], observe, sigma=sigma[b], exact=exact[b])
        assert sample.batch_size is None and sample.observe is observe and sample.sigma_given
        for name in ("t", "y", "sigma", "exact"):
            assert torch.equal(getattr(sample, name), getattr(single, name)), name
    assert [s.y[0, 0].item() for s in obs] == [1.0, 2.0, -1.0, 2.0]  # iteration: the samples in order


def test_batch_slices_are_batches():
    obs = torchql.Observations(T3, YB, ["x", "u"], sigma=torch.arange(1.0, 5.0).reshape(4, 1, 1))
    part = obs[1:3]
    assert part.batch_size == 2 and torch.equal(part.y, YB[1:3]) and part.sigma[:, 0, 0].tolist() == [2.0, 3.0]
    backwards = obs[::-2]
    assert torch.equal(backwards.y, YB[[3, 1]]) and backwards.sigma[:, 0, 0].tolist() == [4.0, 2.0]
    with pytest.raises(IndexError, match=r"selects no sample of a batch of 4"):
        obs[3:1]


@pytest.mark.parametrize("index, error, match", [
    (4, IndexError, "sample index 4 is out of range for a batch of 4"),
    (-5, IndexError, "sample index -5 is out of range for a batch of 4"),
    (1.0, TypeError, "a sample index must be an int or a slice; received float"),
    (True, TypeError, "received bool"),
    ([0, 1], TypeError, "received list"),
])
def test_batch_bad_index(index, error, match):
    with pytest.raises(error, match=match):
        torchql.Observations(T3, YB, ["x", "u"])[index]


def test_one_dataset_has_no_len_index_or_iteration():
    single = torchql.Observations(T3, Y3, ["x", "u"])
    for operation in (len, lambda o: o[0], iter):
        with pytest.raises(TypeError, match=r"applies to a batch of datasets \(values \(B, T, K\)\); this "
                                            r"Observations holds one dataset, values of shape \(3, 2\)"):
            operation(single)
    assert bool(single)


def test_batch_inputs_and_batch_not_mutated():
    y, sigma = YB.clone(), torch.full((4, 1, 2), 0.5, dtype=torch.float64)
    y[2, 0, 1] = math.nan
    inputs = (T3.clone(), y.clone(), sigma.clone())
    obs = torchql.Observations(T3, y, ["x", "u"], sigma=sigma)
    stored = [v.clone() for v in (obs.t, obs.y, obs.sigma, obs.exact)]
    sample, part = obs[2], obs[1:3]
    for view in (sample, part):  # editing what indexing returned leaves the batch as it was
        view.t[0] = 9.0
        view.y.fill_(7.0)
        view.sigma.fill_(3.0)
        view.exact.fill_(True)
    y[0, 0, 0] = math.inf  # editing the caller's tensors afterwards cannot bypass validation
    for now, before in zip((obs.t, obs.y, obs.sigma, obs.exact), stored):
        torch.testing.assert_close(now, before, rtol=0, atol=0, equal_nan=True)
    y[0, 0, 0] = inputs[1][0, 0, 0]
    for now, before in zip((T3, y, sigma), inputs):
        torch.testing.assert_close(now, before, rtol=0, atol=0, equal_nan=True)


def test_single_observations_check_points_to_fit_many():
    from torchql import _checks

    batch = torchql.Observations(T3, YB, ["x", "u"])
    single = torchql.Observations(T3, Y3, ["x", "u"])
    _checks.single_observations("data", single)
    _checks.single_observations("data", [single, single])
    with pytest.raises(ValueError, match=r"`data` holds a batch of 4 independent datasets \(values of shape "
                                         r"\(B, T, K\) = \(4, 3, 2\)\), but torchql.fit fits one dataset.*"
                                         r"torchql.fit_many\(model, data, x0, ...\), or one sample with `data\[b\]`"):
        _checks.single_observations("data", batch)
    with pytest.raises(ValueError, match=r"`data\[1\]` holds a batch of 4"):
        _checks.single_observations("data", [single, batch])


# --- observation functions with unknowns of their own: h(x, p) = scale * x + offset

class _ScaledDecay(torchql.ODEModel):
    """x' = -k x, observed as scale * x + offset; ``scale`` and ``offset`` are coefficients that only the
    observation reads (and ``unused`` one that nothing reads)."""

    state_names = ("x",)

    def __init__(self, k=0.5, scale=1.0, offset=0.0, unused=1.0, scale_2=1.0):
        super().__init__()
        for name, value in dict(k=k, scale=scale, offset=offset, unused=unused, scale_2=scale_2).items():
            self.register_buffer(name, torch.tensor(value, dtype=torch.float64))

    def forward(self, t, x):
        return -self.k * x


def _scaled(x, p):
    return p["scale"] * x + p["offset"]


T_DECAY = torch.linspace(0, 4, 20, dtype=torch.float64)
ONE = torch.tensor([1.0], dtype=torch.float64)
OBSERVED = ["k", "scale", "offset"]


def _decay_data(scale=2.5, offset=0.3):
    return torchql.Observations(T_DECAY, (scale * torch.exp(-0.8 * T_DECAY) + offset).unsqueeze(-1), observe=_scaled)


@pytest.mark.parametrize("method", torchql.METHODS)
def test_observation_parameters_are_estimated_with_the_rest(method):
    """Exact data of 2.5 exp(-0.8 t) + 0.3: k, scale and offset to 1e-8. The Jacobian's columns are
    dh/dscale = x(t) and dh/doffset = 1, exactly as h(x, p) says."""
    r = torchql.fit(_ScaledDecay(), _decay_data(), ONE, fixed_x0=["x"], params=OBSERVED, method=method)
    assert r.success, r.message
    assert torch.allclose(r.estimates, torch.tensor([0.8, 2.5, 0.3], dtype=torch.float64), rtol=1e-8, atol=0)
    torch.testing.assert_close(r.jacobian[:, 1], torch.exp(-0.8 * T_DECAY), rtol=1e-8, atol=1e-10)
    torch.testing.assert_close(r.jacobian[:, 2], torch.ones(20, dtype=torch.float64), rtol=0, atol=1e-12)
    assert torchql.compare(r, _decay_data()).fit_percent.item() == pytest.approx(100.0, abs=1e-6)


def test_observation_parameter_that_nothing_reads_is_named_not_identifiable():
    r = torchql.fit(_ScaledDecay(), _decay_data(), ONE, fixed_x0=["x"], params=OBSERVED + ["unused"])
    assert r.status is torchql.Status.NOT_IDENTIFIABLE
    assert "{unused}" in r.message


def test_observation_parameters_per_experiment_and_batched():
    """Two gels scale the same decay differently: ``conditions`` gives the second its own scale; and a
    batch of two datasets fitted by ``fit_many`` equals the fits one by one."""
    r = torchql.fit(_ScaledDecay(), [_decay_data(2.5), _decay_data(1.5)], torch.stack([ONE, ONE]),
                    fixed_x0=["x"], params=OBSERVED + ["scale_2"], conditions=[{}, {"scale": "scale_2"}])
    assert r.success, r.message
    for name, truth in dict(k=0.8, scale=2.5, scale_2=1.5, offset=0.3).items():
        assert r.params[name].item() == pytest.approx(truth, rel=1e-8)
    batch = torchql.Observations(T_DECAY, torch.stack([_decay_data(2.5).y, _decay_data(1.2, 0.1).y]), observe=_scaled)
    many = torchql.fit_many(_ScaledDecay(), batch, ONE, fixed_x0=["x"], params=OBSERVED)
    for i in range(2):
        one = torchql.fit(_ScaledDecay(), batch[i], ONE, fixed_x0=["x"], params=OBSERVED)
        assert many[i].iterations == one.iterations
        assert torch.allclose(many[i].estimates, one.estimates, rtol=1e-9, atol=0)


def test_lognormal_values_of_a_scaled_observation():
    data = torchql.Observations(T_DECAY, _decay_data().y, observe=_scaled, noise="lognormal", sigma=0.1)
    r = torchql.fit(_ScaledDecay(), data, ONE, fixed_x0=["x"], params=OBSERVED)
    assert r.success, r.message
    assert torch.allclose(r.estimates, torch.tensor([0.8, 2.5, 0.3], dtype=torch.float64), rtol=1e-8, atol=0)


def test_observation_with_parameters_that_fails_is_named():
    data = torchql.Observations(T_DECAY, _decay_data().y, observe=lambda x, p: p["gain"] * x)
    with pytest.raises(ValueError, match=r"`observe` callable failed on a state of shape \(1,\): KeyError: 'gain'"):
        torchql.fit(_ScaledDecay(), data, ONE, fixed_x0=["x"], params=["k"])


@pytest.mark.parametrize("observe", [lambda x: torch.as_tensor(np.asarray(x.detach())[..., 0] * 1.0),
                                     lambda x, p: p["scale"] * torch.as_tensor(np.asarray(x.detach()))])
def test_an_observation_that_torch_func_cannot_differentiate_is_named(observe):
    """NumPy inside ``h`` works on a plain state but not under jacrev and vmap, as the fit takes
    ``dh/dx``: the fit said "Cannot access data pointer of Tensor that doesn't have storage" from
    inside torch.func; it now names ``observe`` and what to write instead."""
    data = torchql.Observations(T_DECAY, _decay_data().y, observe=observe)
    with pytest.raises(ValueError, match=r"`observe` callable cannot be differentiated by torch.func on a state of "
                                         r"shape \(1,\) .*Write it with torch operations on x"):
        torchql.fit(_ScaledDecay(), data, ONE, fixed_x0=["x"], params=["k"])


def test_an_observation_matrix_is_copied_as_the_values_are():
    """``t``, ``y``, ``sigma`` and ``exact`` were copied, ``observe`` kept by reference: scaling the
    user's matrix afterwards changed the data already built (a fit then found y(t0) = 0.75 for
    data of 1.5)."""
    import torchql

    t = torch.linspace(0, 2, 11, dtype=torch.float64)
    Q = torch.ones(1, 1, dtype=torch.float64)
    by_matrix = torchql.Observations(t, torch.exp(-t)[:, None], observe=Q)
    Q.mul_(2.0)
    assert torch.equal(by_matrix.observe, torch.ones(1, 1, dtype=torch.float64))
