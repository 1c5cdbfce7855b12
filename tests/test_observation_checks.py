"""Argument checks of Observations (torchql/observation_checks.py): the values marked exact."""

import math

import pytest
import torch

import torchql
from torchql.observation_checks import exact_mask

DT = torch.float64
T = torch.arange(4, dtype=DT)


def values(batch=None):
    y = torch.ones(4, 2, dtype=DT) if batch is None else torch.ones(batch, 4, 2, dtype=DT)
    return y


def test_a_time_marked_as_a_whole_marks_its_present_values():
    y = values()
    y[1, 0] = math.nan
    obs = torchql.Observations(T, y, observe=torch.eye(2, dtype=DT), exact=torch.tensor([False, True, False, False]))
    expected = torch.zeros(4, 2, dtype=torch.bool)
    expected[1, 1] = True
    assert torch.equal(obs.exact, expected)


def test_a_time_marked_as_a_whole_must_hold_a_value():
    y = values()
    y[1] = math.nan
    with pytest.raises(ValueError, match=r"`exact` marks times that hold no value .* at index \(1,\)"):
        torchql.Observations(T, y, observe=torch.eye(2, dtype=DT), exact=torch.tensor([False, True, False, False]))


def test_a_value_marked_one_by_one_must_be_present_in_every_sample():
    y = values(batch=3)
    y[2, 1, 0] = math.nan
    exact = torch.zeros(4, 2, dtype=torch.bool)
    exact[1, 0] = True
    torchql.Observations(T, y[:2], observe=torch.eye(2, dtype=DT), exact=exact)  # present in samples 0 and 1
    with pytest.raises(ValueError, match=r"`exact` marks values that are missing \(NaN\), at index \(2, 1, 0\)"):
        torchql.Observations(T, y, observe=torch.eye(2, dtype=DT), exact=exact)


def test_no_mask_marks_nothing_and_the_mask_given_is_not_modified():
    assert not exact_mask(None, (4, 2), values()).any()
    given = torch.tensor([True, False, False, False])
    mask = exact_mask(given, (4, 2), values())
    assert mask.shape == (4, 2) and bool(mask[0].all()) and not bool(mask[1:].any())
    assert torch.equal(given, torch.tensor([True, False, False, False]))
