"""The datasets of a batch: ``fit_many``'s ``data`` validated (:func:`check_data`), and the one input
signal its samples share (:func:`shared_inputs`)."""

from __future__ import annotations

import torch

from .observations import Observations

__all__ = ["check_data", "check_alike", "inputs_all_or_none", "shared_inputs"]


def check_data(data) -> Observations | list[Observations]:
    """``fit_many``'s ``data`` validated: one batched Observations as it is, or a list of datasets.

    A list must hold one-dataset Observations with the same number ``T`` of observation times
    (each its own times), the same ``observe`` specification and all or none giving ``sigma``
    (a batched Observations has them in common by construction). Errors name the argument and
    the dataset.
    """
    if isinstance(data, Observations):
        if data.batch_size is None:
            raise TypeError("`data` must be a list of torchql.Observations (one per dataset) or one Observations "
                            "holding a batch, values (B, T, K); received a single dataset, values "
                            f"{tuple(data.y.shape)} (a single dataset: use torchql.fit, or pass [data])")
        return data
    if not isinstance(data, (list, tuple)):
        raise TypeError("`data` must be a list of torchql.Observations (one per dataset) or one Observations "
                        f"holding a batch, values (B, T, K); received {type(data).__name__}")
    if len(data) == 0:
        raise ValueError("`data` is an empty list: give one torchql.Observations per dataset (B >= 1)")
    for i, d in enumerate(data):
        if not isinstance(d, Observations):
            raise TypeError(f"`data[{i}]` must be a torchql.Observations; received {type(d).__name__}")
        if d.batch_size is not None:
            raise ValueError(f"`data[{i}]` holds a batch of {d.batch_size} datasets, values {tuple(d.y.shape)}: "
                             "pass a batched Observations alone as `data`, not in a list")
    items = list(data)
    first = items[0]
    for i, d in enumerate(items[1:], start=1):
        if d.n_times != first.n_times:
            raise ValueError(f"`data[{i}]` has T = {d.n_times} observation times but `data[0]` has "
                             f"{first.n_times}: fit_many needs the same number of times in every dataset (each "
                             "may have its own times); fit datasets with other numbers of times in another batch")
        check_alike(d, first, f"data[{i}]", "data[0]")
    return items


def check_alike(d: Observations, first: Observations, name: str, first_name: str) -> None:
    """An error naming ``name`` unless the dataset ``d`` observes what ``first`` (named ``first_name``)
    does, with the same noise model, and gives ``sigma`` where ``first`` does: the samples of one
    batch share one observation operator and one noise model."""
    if not _same_observe(d.observe, first.observe) or d.n_outputs != first.n_outputs:
        raise ValueError(f"`{name}` observes something else than `{first_name}` (its `observe` differs); "
                         "fit_many needs one observation operator for all datasets (the same names, matrix "
                         "or callable object)")
    if ((d.noise, d.sigma_estimated, d.sigma_groups) != (first.noise, first.sigma_estimated, first.sigma_groups)
            or d.sigma_function is not first.sigma_function):
        raise ValueError(f"`{name}` has another noise model than `{first_name}` (`noise`, sigma='estimate', "
                         "`sigma_groups` or the sigma(p) function object differ): one batch has one noise model")
    if d.sigma_given != first.sigma_given:
        raise ValueError(f"`{name}` {'gives' if d.sigma_given else 'does not give'} `sigma` but "
                         f"`{first_name}` {'does' if first.sigma_given else 'does not'}: give it for all or none")


def inputs_all_or_none(inputs: list) -> None:
    """An error naming the first dataset that has inputs where ``data[0]`` has none, or the reverse."""
    given = [item is not None for item in inputs]
    if any(given) and not all(given):
        b = given.index(not given[0])
        raise ValueError(f"`data[{b}]` {'carries' if given[b] else 'carries no'} inputs but `data[0]` "
                         f"{'does' if given[0] else 'does not'}: give inputs for every dataset or for none")


def shared_inputs(inputs: list):
    """The samples' one input signal (``None`` without inputs); an error when they differ."""
    first = inputs[0]
    if all(first.same_as(item) if first is not None else item is None for item in inputs[1:]):
        return first
    inputs_all_or_none(inputs)
    b = next(i for i, item in enumerate(inputs) if not first.same_as(item))
    raise ValueError(f"`data[{b}]` has other inputs than `data[0]`: one problem takes one input signal for all its "
                     "samples (torchql.fit_many groups samples by their inputs)")


def _same_observe(a, b) -> bool:
    if a is b:
        return True
    if isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor):
        return a.shape == b.shape and torch.equal(a.to(torch.float64), b.to(torch.float64))
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return list(a) == list(b)
    try:
        import numpy as np

        if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
            return bool(np.array_equal(np.asarray(a), np.asarray(b)))
    except ImportError:  # pragma: no cover
        pass
    return False
