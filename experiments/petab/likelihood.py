"""The PEtab v1 negative log-likelihood of a problem, from simulations of its conditions.

Per measurement ``m`` with simulated observable ``y`` and noise ``sigma`` (PEtab v1):

* normal, lin:    ``0.5 log(2 pi sigma^2) + 0.5 ((m - y) / sigma)^2``
* normal, log10:  ``0.5 log(2 pi sigma^2 m^2 ln(10)^2) + 0.5 ((log10 m - log10 y) / sigma)^2``
* laplace, lin:   ``log(2 sigma) + |m - y| / sigma``

and the negative log-likelihood is their sum over every row of the measurement table.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping

import torch

import torchql

from .problem import PetabProblem, resolve_entry, setup_condition

__all__ = ["Simulator", "torchql_simulator", "row_terms", "likelihood_terms", "negative_log_likelihood"]

#: ``(model, x0 (n,), times (T,), t0) -> states (T, n)``.
Simulator = Callable[[torchql.ODEModel, torch.Tensor, torch.Tensor, float], torch.Tensor]
_LOG_2PI = math.log(2 * math.pi)
_LN10 = math.log(10.0)


def torchql_simulator(solver: str, rtol: float, atol: float) -> Simulator:
    """A :data:`Simulator` by :func:`torchql.simulate` with these settings."""
    def simulate(model, x0, times, t0):
        return torchql.simulate(model, x0, times, t0=t0, solver=solver, rtol=rtol, atol=atol)
    return simulate


def row_terms(m: torch.Tensor, y: torch.Tensor, sigma: torch.Tensor, transformation: str,
              distribution: str) -> torch.Tensor:
    """Negative log-likelihood of each measurement ``m`` given ``y`` and ``sigma``, all ``(R,)`` -> ``(R,)``."""
    if (transformation, distribution) == ("lin", "normal"):
        return 0.5 * (_LOG_2PI + torch.log(sigma**2)) + 0.5 * ((m - y) / sigma) ** 2
    if (transformation, distribution) == ("log10", "normal"):
        return (0.5 * (_LOG_2PI + torch.log((sigma * m * _LN10) ** 2))
                + 0.5 * ((torch.log10(m) - torch.log10(y)) / sigma) ** 2)
    if (transformation, distribution) == ("lin", "laplace"):
        return torch.log(2 * sigma) + (m - y).abs() / sigma
    raise ValueError(f"(transformation, distribution) must be one of ('lin', 'normal'), ('log10', 'normal'), "
                     f"('lin', 'laplace'); received {(transformation, distribution)}")


def _placeholders(entries, values):
    """Column ``i`` of a list of rows of placeholder entries, as ``Tensor (R,)`` each."""
    width = len(entries[0])
    if any(len(e) != width for e in entries):
        raise ValueError("the rows of one observable in one condition give different numbers of placeholders")
    return tuple(torch.tensor([resolve_entry(e[i], values) for e in entries], dtype=torch.float64)
                 for i in range(width))


def likelihood_terms(problem: PetabProblem, values: Mapping[str, float],
                     simulate: Simulator | None = None) -> torch.Tensor:
    """Each measurement's negative log-likelihood, ``(N,)`` in the measurement table's order.

    Parameters
    ----------
    problem : PetabProblem
    values : dict of str to float
        Every parameter's value, linear scale (:func:`~.problem.nominal_values`,
        :func:`~.problem.values_from_scaled`).
    simulate : Simulator, optional
        Integrates one condition; default :func:`torchql.simulate` with the spec's solver and tolerances.
    """
    spec = problem.spec
    simulate = simulate or torchql_simulator(spec.solver, spec.rtol, spec.atol)
    out = torch.full((len(problem.measurements),), float("nan"), dtype=torch.float64)
    for condition in dict.fromkeys(m.condition for m in problem.measurements):
        setup = setup_condition(problem, condition, values)
        states = simulate(setup.model, setup.x0, setup.times, setup.t0)[setup.time_index]  # (R, n)
        rows = torch.tensor(setup.rows)
        for obs_id, observable in problem.observables.items():
            mask = torch.tensor([problem.measurements[i].observable == obs_id for i in setup.rows])
            if not bool(mask.any()):
                continue
            chosen = [problem.measurements[i] for i in rows[mask].tolist()]
            x = dict(zip(spec.model.state_names, states[mask].unbind(-1)))
            obs_params = _placeholders([m.observable_parameters for m in chosen], values)
            noise_params = _placeholders([m.noise_parameters for m in chosen], values)
            y = spec.observables[obs_id](x, setup.symbols, obs_params)
            sigma = spec.noise[obs_id](x, setup.symbols, noise_params)
            m = torch.tensor([r.value for r in chosen], dtype=torch.float64)
            out[rows[mask]] = row_terms(m, y, sigma.expand_as(m), observable.transformation, observable.distribution)
    return out


def negative_log_likelihood(problem: PetabProblem, values: Mapping[str, float],
                            simulate: Simulator | None = None) -> float:
    """The PEtab v1 negative log-likelihood at the parameter ``values`` (linear scale), summed over every
    measurement; ``simulate`` as in :func:`likelihood_terms`."""
    return float(likelihood_terms(problem, values, simulate).sum())
