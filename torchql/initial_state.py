"""Initial states given as expressions of the other values: ``S(t0) = N - I(t0)``.

``fit(..., x0_expr={"S": lambda v: v["N"] - v["I"]})`` makes ``S(t0)`` neither an unknown nor a
fixed value: it follows the coefficients and the other initial states at every iterate. Each
expression receives a dict of the current values, the coefficients by name (tensors of their
shapes, estimated or not) and the initial states by name (scalars), and returns a scalar tensor.
It must be differentiable (torch operations): the homogeneous solution of each unknown starts
from the derivative of the augmented initial state with respect to it,
``(dx0/du_j, e_j)``, not from the unit vector alone, so the superposition and the sensitivities
stay exact (a steady state computed from the rates, as PEtab models start from, is one such
expression). The expressions are evaluated in the order given: one may use a state set by an
earlier one.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import torch
from torch.func import jacrev, vmap

__all__ = ["InitialStateExpressions", "ReadValues", "check_expressions"]

Expression = Callable[[dict], torch.Tensor]


def check_expressions(x0_expr, state_names: Sequence[str], fixed_x0: Sequence[str] | None) -> dict[str, Expression]:
    """``x0_expr`` validated: ``{state name: callable}``, no state also in ``fixed_x0``."""
    if x0_expr is None:
        return {}
    if not isinstance(x0_expr, Mapping):
        raise TypeError(f"`x0_expr` must be a dict {{state name: callable(values) -> scalar}}; received "
                        f"{type(x0_expr).__name__}")
    out = {}
    for name, fn in x0_expr.items():
        state = name.removesuffix("(t0)") if isinstance(name, str) else name
        if state not in state_names:
            raise ValueError(f"`x0_expr` names unknown state {name!r}; the model's states are {tuple(state_names)}")
        if not callable(fn):
            raise TypeError(f"`x0_expr[{name!r}]` must be callable (it receives the values by name and returns the "
                            f"initial value); received {type(fn).__name__}")
        if fixed_x0 is not None and state in fixed_x0:
            raise ValueError(f"`x0_expr` gives state {state!r} by an expression and `fixed_x0` fixes it too: give it "
                             "in one place")
        out[state] = fn
    return out


class InitialStateExpressions:
    """The augmented initial state ``z0 (M,)`` completed by the expressions, and its Jacobian.

    Parameters
    ----------
    expressions : dict of str to callable
        ``{state name: f(values) -> scalar}``, validated by :func:`check_expressions`.
    system : AugmentedSystem
        Gives the state names, the estimated coefficients' slots in ``z`` and the other
        coefficients' values.
    """

    def __init__(self, expressions: Mapping[str, Expression], system) -> None:
        self.system = system
        self.items = [(system.state_names.index(name), name, fn) for name, fn in expressions.items()]
        self.index = [i for i, _, _ in self.items]

    def __bool__(self) -> bool:
        return bool(self.items)

    def _values(self, z: torch.Tensor) -> dict[str, torch.Tensor]:
        values = self.system.coefficient_values(z)
        values.update({name: z[i] for i, name in enumerate(self.system.state_names)})
        return values

    def _complete_one(self, z: torch.Tensor) -> torch.Tensor:
        entries = list(z.unbind(0))
        for i, name, fn in self.items:
            values = self._values(torch.stack(entries))
            entries[i] = _scalar(fn(values), name, z)
        return torch.stack(entries)

    def complete(self, z0: torch.Tensor) -> torch.Tensor:
        """``z0 (S, M)`` with the expressions' states set from the other values (a new tensor)."""
        if not self.items:
            return z0
        return vmap(self._complete_one)(z0)

    def columns(self, z0: torch.Tensor, unknown_index: torch.Tensor) -> torch.Tensor:
        """``W(t0) = [z0, dz0/du]``: shape ``(S, M, 1 + m)`` for ``z0 (S, M)`` (complete)."""
        J = vmap(jacrev(self._complete_one))(z0)  # (S, M, M): identity but for the expressions' rows
        return torch.cat([z0.unsqueeze(-1), J[:, :, unknown_index]], dim=-1)

    def check(self, z0: torch.Tensor) -> None:
        """Evaluate every expression on the first sample's ``z0 (S, M)``: a clear error for one that
        fails, does not return a scalar tensor, or is not finite, and for one that reads a state set
        by itself or by a later expression (whose value there would be its guess at every iterate:
        ``{"a": tot - b, "b": tot - a}`` held ``b(t0)`` at its guess)."""
        z = z0[0]
        for k, (i, name, fn) in enumerate(self.items):
            values = ReadValues(self._values(z))
            try:
                value = fn(values)
            except Exception as exc:  # noqa: BLE001 - report any failure of user code clearly
                raise ValueError(f"`x0_expr[{name!r}]` failed on the guesses: {type(exc).__name__}: {exc}") from exc
            later = [other for _, other, _ in self.items[k:] if other in values.read]
            if later:
                raise ValueError(f"`x0_expr[{name!r}]` reads {later[0]!r}, which `x0_expr` sets "
                                 f"{'by this same expression' if later[0] == name else 'after it'}: the expressions "
                                 "are evaluated in the order given, each may read the states set by earlier ones "
                                 "only; order them so, and give a cycle of them by one expression")
            value = _scalar(value, name, z)
            if not bool(torch.isfinite(value)):
                raise ValueError(f"`x0_expr[{name!r}]` is {float(value)} at the guesses; it must be finite")
            z = z.clone()
            z[i] = value


class ReadValues(dict):
    """The values an expression receives, recording the names it reads (``read``)."""

    def __init__(self, values: dict) -> None:
        super().__init__(values)
        self.read: set = set()

    def __getitem__(self, key):
        self.read.add(key)
        return super().__getitem__(key)

    def get(self, key, default=None):
        self.read.add(key)
        return super().get(key, default)


def _scalar(value, name: str, like: torch.Tensor) -> torch.Tensor:
    """An expression's value as a scalar of ``like``'s dtype (a clear error otherwise)."""
    if not isinstance(value, torch.Tensor):
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return torch.full((), float(value), dtype=like.dtype, device=like.device)
        raise TypeError(f"`x0_expr[{name!r}]` must return a scalar tensor; received {type(value).__name__}")
    if value.numel() != 1:
        raise ValueError(f"`x0_expr[{name!r}]` must return a scalar; received shape {tuple(value.shape)}")
    return value.reshape(()).to(like.dtype)
