"""Measured inputs ``u(t)``: an experiment's input signals, interpolated between their samples.

A model with inputs declares their names (``input_names = ("u",)``) and takes their values as a
third argument, ``forward(t, x, u)`` with ``u`` of shape ``(n_inputs,)`` at the time ``t``. The
values come from an experiment's :class:`Inputs`, given with its data
(``Observations(..., inputs=Inputs(t_u, u, names=["u"]))``); every right-hand-side evaluation of
a fit, a simulation or a prediction interpolates them at its own time. The interpolation is
written with comparisons and ``index_select`` only, so it is differentiable in ``t`` (the time
derivative of the right-hand side, which the Taylor transfers need, includes ``du/dt``) and safe
under :func:`torch.func.vmap`, ``jacrev`` and ``jvp``.

Interpolation kinds:

* ``"zoh"``: zero-order hold, ``u(t) = u_k`` between the samples ``t_k`` and ``t_{k+1}`` (a
  sampled, held input). Each switch is a smooth step (the quintic ``6s^5 - 15s^4 + 10s^3``) of
  width :attr:`Inputs.ramp`, a relative :data:`RAMP` of the samples' span, centred on ``t_k``: the
  integral of ``u`` is exactly the held signal's, the solution differs from it by
  ``O(ramp^2)``, and the right-hand side and its time derivative stay continuous, which the
  grid's one-step methods and Hermite transfers need (a true jump at a node would be read with
  the value after it by the interval that ends there). At ``t_k`` itself ``u`` is the mean of
  ``u_{k-1}`` and ``u_k``.
* ``"linear"``: straight lines between the samples;
* ``"cubic"``: the not-a-knot cubic spline through the samples (MATLAB's ``spline``), continuous
  with its first two derivatives.

Outside ``[t_0, t_{N-1}]`` the signal holds its end values; a fit requires the samples to cover
the data's times (from the initial time to the last observation), and says so otherwise.

A fit's storage grid holds the times where the interpolant is not smooth (:attr:`Inputs.nodes`):
the ends of each zero-order-hold step (just outside it, :data:`NODE_MARGIN`); each linear sample, with a node a relative
:data:`BRACKET` of the span before it (the interval ending at a kink reads the slope after it in
its end data, so that interval is made negligibly short); each cubic sample.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from ._arrays import float_tensor
from .splines import hermite_basis, knot_slopes

__all__ = ["Inputs", "INTERPOLATIONS", "RAMP", "NODE_MARGIN", "BRACKET"]

#: The interpolation kinds of :class:`Inputs`.
INTERPOLATIONS = ("zoh", "linear", "cubic")

#: Length of the interval a grid places before each kink of a linear input, relative to the
#: samples' span. The Hermite transfers' error on that interval, which reads the slope after the
#: kink at its end, is of the order of its squared length times the change of slope.
BRACKET = 1e-9
#: Width of a zero-order hold's smooth step, relative to the samples' span (at most a hundredth of
#: the shortest sample interval, and at least 1e5 roundoffs of the times).
RAMP = 1e-9
#: A zero-order hold's grid nodes lie this fraction of its ramp outside it (at least 50
#: roundoffs of the times), where the input is held: a node computed at the ramp's very end fell
#: inside it by a roundoff, and the smooth step's second derivative there (``~1/ramp^2`` times a
#: roundoff over the ramp, 9e8 for a unit step) entered the quintic storage's ``A''``.
NODE_MARGIN = 1e-3


class Inputs:
    """The measured input signals of one experiment, ``u(t)``, interpolated between their samples.

    Parameters
    ----------
    t : Tensor or array ``(N,)``
        Sample times, finite and strictly increasing (the model's time unit); ``N >= 1`` for
        ``"zoh"`` (one sample: a constant input, which covers any times from its own on),
        ``N >= 2`` otherwise.
    u : Tensor or array ``(N, m)``, or ``(N,)`` for one input
        The inputs' values at those times (finite). Copied.
    names : str or sequence of str
        The ``m`` inputs' names, in the order of ``u``'s columns; they must be the model's
        ``input_names`` (in any order).
    kind : {"zoh", "linear", "cubic"}
        Interpolation between the samples (see :mod:`torchql.inputs`); default ``"linear"``.

    Attributes
    ----------
    t : Tensor ``(N,)``
    u : Tensor ``(N, m)``
    names : tuple of str
    kind : str

    Examples
    --------
    >>> u = Inputs(torch.linspace(0, 10, 101), torch.sin(torch.linspace(0, 10, 101)), names="force")
    >>> u(torch.tensor(0.05)).shape
    torch.Size([1])
    """

    def __init__(self, t, u, names: str | Sequence[str], kind: str = "linear") -> None:
        t = float_tensor(t, "inputs t")
        u = float_tensor(u, "inputs u", t.dtype)
        if isinstance(names, str):
            names = (names,)
        if not isinstance(names, Sequence) or not all(isinstance(name, str) for name in names):
            raise TypeError(f"`names` must be a string or a sequence of strings (one per input); received {names!r}")
        names = tuple(names)
        if len(set(names)) != len(names) or not names:
            raise ValueError(f"`names` must be distinct and not empty; received {list(names)}")
        if not isinstance(kind, str) or kind not in INTERPOLATIONS:
            raise ValueError(f"`kind` must be one of {list(INTERPOLATIONS)}; received {kind!r}")
        if t.dim() != 1:
            raise ValueError(f"`t` (the inputs' sample times) must be one-dimensional, shape (N,); received shape "
                             f"{tuple(t.shape)}")
        if u.dim() == 1:
            u = u.unsqueeze(-1)
        if u.dim() != 2 or u.shape[0] != t.shape[0]:
            raise ValueError(f"`u` must have shape (N, m) = ({t.shape[0]}, {len(names)}) to match `t`; received shape "
                             f"{tuple(u.shape)}")
        if u.shape[1] != len(names):
            raise ValueError(f"`u` has {u.shape[1]} columns but {len(names)} names were given ({list(names)}); give "
                             "one name per column")
        least = 1 if kind == "zoh" else 2
        if t.shape[0] < least:
            raise ValueError(f"`t` must hold at least {least} sample time{'s' if least > 1 else ''} for kind={kind!r}; "
                             f"received {t.shape[0]}")
        if not bool(torch.isfinite(t).all()) or not bool(torch.isfinite(u).all()):
            raise ValueError("the inputs' `t` and `u` must be finite; received NaN or inf")
        if t.shape[0] > 1 and not bool((t[1:] > t[:-1]).all()):
            j = int((t[1:] <= t[:-1]).nonzero()[0, 0])
            raise ValueError(f"the inputs' `t` must be strictly increasing; received t[{j}] = {t[j].item():g} followed "
                             f"by t[{j + 1}] = {t[j + 1].item():g}")
        self.t, self.u, self.names, self.kind = t.clone(), u.clone(), names, kind
        self._slopes = self._knot_slopes() if kind == "cubic" else None
        #: width of a zero-order hold's smooth steps (the model's time unit; 0 for the other kinds)
        self.ramp = _ramp(t, kind)

    def _knot_slopes(self) -> torch.Tensor:
        t = self.t.detach().cpu().double().numpy()
        columns = [knot_slopes(t, self.u[:, j].detach().cpu().double().numpy()) for j in range(self.n_inputs)]
        return torch.as_tensor(np.stack(columns, axis=1), dtype=self.u.dtype, device=self.u.device)

    @property
    def n_inputs(self) -> int:
        """Number of inputs ``m``."""
        return len(self.names)

    @property
    def nodes(self) -> torch.Tensor:
        """Times where the interpolant is not smooth, for a fit's grid (see :mod:`torchql.inputs`):
        the ends of the zero-order hold's steps, the linear samples each with a node just before
        it, or the cubic samples."""
        if self.kind == "zoh":
            inner = self.t[1:]
            half = self.ramp / 2 * (1.0 + NODE_MARGIN)
            return torch.cat([inner - half, inner + half])
        if self.kind == "linear":
            before = self.t - max(BRACKET * float(self.t[-1] - self.t[0]), 1e3 * torch.finfo(self.t.dtype).eps
                                  * float(self.t.abs().max()))
            return torch.cat([self.t, before[1:]])
        return self.t

    @property
    def jumps(self) -> torch.Tensor | None:
        """Times where an adaptive solver should restart (``jump_t``): the ends of the zero-order
        hold's steps, the linear samples' kinks; ``None`` for the cubic spline (smooth enough)."""
        if self.kind == "zoh":
            return self.nodes
        return self.t if self.kind == "linear" else None

    def covers(self, start: float, end: float) -> bool:
        """Whether the samples span ``[start, end]`` (a one-sample hold, a constant, from its time on)."""
        held = self.kind == "zoh" and self.t.shape[0] == 1
        return float(self.t[0]) <= start and (held or float(self.t[-1]) >= end)

    def to(self, dtype: torch.dtype | None = None, device: torch.device | None = None) -> "Inputs":
        """A copy in ``dtype`` on ``device``."""
        out = Inputs.__new__(Inputs)
        out.t, out.u = self.t.to(dtype=dtype, device=device), self.u.to(dtype=dtype, device=device)
        # in a coarser dtype, at least 1e5 of its roundoffs: a step narrower is a true jump there
        out.names, out.kind, out.ramp = self.names, self.kind, max(self.ramp, _ramp(out.t, self.kind))
        out._slopes = None if self._slopes is None else self._slopes.to(dtype=dtype, device=device)
        out._tables = {}
        return out

    def shifted(self, origin: float) -> "Inputs":
        """The same signals on the times ``t - origin``: a local time origin, where the times a solver
        steps through are resolved to a roundoff of the span, not of ``origin`` (at ``t ~ 1e8`` a
        zero-order hold's step held only 1e5 distinct times, and fits at rtol 1e-10 failed). The
        zero-order hold's ramp is the span's :data:`RAMP` there."""
        if origin == 0.0:
            return self
        out = self.to()
        out.t = self.t - origin
        out.ramp = _ramp(out.t, self.kind)
        return out

    def select(self, names: Sequence[str], where: str = "inputs") -> "Inputs":
        """The signals in the order of ``names`` (the model's ``input_names``); a clear error for an
        unknown or missing name. ``where`` names the argument in the error."""
        unknown = [name for name in self.names if name not in names]
        if unknown:
            raise ValueError(f"`{where}` names unknown input {unknown[0]!r}; the model's inputs are {tuple(names)}")
        missing = [name for name in names if name not in self.names]
        if missing:
            raise ValueError(f"`{where}` lacks the model's input {missing[0]!r}; it gives {self.names}, the model "
                             f"needs {tuple(names)}")
        order = [self.names.index(name) for name in names]
        if order == list(range(len(order))):
            return self
        out = self.to()
        out.u, out.names = self.u[:, order], tuple(names)
        out._slopes = None if self._slopes is None else self._slopes[:, order]
        out._tables = {}
        return out

    def for_model(self, names: Sequence[str], start: float, end: float, dtype: torch.dtype, device: torch.device,
                  *, where: str, span: str, note: str = "") -> "Inputs":
        """The signals a model with ``input_names = names`` is evaluated with: in that order
        (:meth:`select`), in ``dtype`` on ``device``, checked to cover ``[start, end]``. Errors name
        the argument ``where`` and say what must be covered (``span``, then ``note``)."""
        signals = self.select(names, where).to(dtype, device)
        if not signals.covers(start, end):
            raise ValueError(f"`{where}` must cover {span} [{start:g}, {end:g}]{note}; its samples span "
                             f"[{signals.t[0].item():g}, {signals.t[-1].item():g}]")
        return signals

    def same_as(self, other: "Inputs | None") -> bool:
        """Whether ``other`` holds the same signals (names, kind, times and values)."""
        if other is self:
            return True
        return (isinstance(other, Inputs) and other.names == self.names and other.kind == self.kind
                and other.t.shape == self.t.shape and other.u.shape == self.u.shape
                and torch.equal(other.t.to(self.t), self.t) and torch.equal(other.u.to(self.u), self.u))

    def __call__(self, t: torch.Tensor) -> torch.Tensor:
        """The inputs at times ``t``: shape ``(*t.shape, m)``; differentiable in ``t``, vmap-safe."""
        table = self._table(t.dtype, t.device)
        flat = t.reshape(-1).clone()  # a physical copy: under vmap `t` may be an expanded view
        if self.kind == "zoh":
            out = self._held(flat, table)
        else:
            knots = table["knots"]
            index = (torch.searchsorted(knots, flat, right=True) - 1).clamp(0, knots.shape[0] - 2)
            inside = flat.clamp(knots[0], knots[-1])  # the end values held outside (clamp: a full slope at the ends)
            s = ((inside - knots.index_select(0, index)) * table["inverse_width"].index_select(0, index)).unsqueeze(-1)
            piece = table["pieces"].index_select(0, index)  # (Q, 2 or 4, m)
            if self.kind == "linear":
                out = torch.lerp(piece[:, 0], piece[:, 1], s)  # exact at both samples
            else:  # cubic Hermite: values and width-scaled slopes at both ends
                b00, b10, b01, b11 = hermite_basis(s)
                out = b00 * piece[:, 0] + b10 * piece[:, 1] + b01 * piece[:, 2] + b11 * piece[:, 3]
        return out.reshape(*t.shape, self.n_inputs)

    def _table(self, dtype: torch.dtype, device: torch.device) -> dict:
        """The interpolation's tables in ``dtype`` on ``device``, built once (per dtype and device)."""
        cache = self.__dict__.setdefault("_tables", {})
        key = (dtype, device)
        if key not in cache:
            knots = self.t.to(dtype=dtype, device=device)
            values = self.u.to(dtype=dtype, device=device)
            table = {"knots": knots, "values": values}
            if knots.shape[0] > 1:
                width = knots[1:] - knots[:-1]
                table["inverse_width"] = 1.0 / width
                if self.kind == "zoh":
                    table["starts"] = knots - self.ramp / 2
                    table["pieces"] = torch.stack([values[:-1], values[1:]], dim=1)
                elif self.kind == "linear":
                    table["pieces"] = torch.stack([values[:-1], values[1:]], dim=1)
                else:
                    scaled = self._slopes.to(dtype=dtype, device=device)
                    w = width.unsqueeze(-1)
                    table["pieces"] = torch.stack([values[:-1], w * scaled[:-1], values[1:], w * scaled[1:]], dim=1)
            cache[key] = table
        return cache[key]

    def _held(self, flat: torch.Tensor, table: dict) -> torch.Tensor:
        """The zero-order hold at times ``flat (Q,)``: ``(Q, m)``, its steps smoothed over :attr:`ramp`."""
        values = table["values"]
        N = values.shape[0]
        if N == 1:
            return values.expand(flat.shape[0], self.n_inputs)
        starts = table["starts"]
        # the step into sample j: the last one begun (sample 0's counted too), or the first before any
        j = (torch.searchsorted(starts, flat, right=True) - 1).clamp(1, N - 1)
        piece = table["pieces"].index_select(0, j - 1)  # (Q, 2, m): u_{j-1}, u_j
        half = self.ramp / 2
        s = ((flat - table["knots"].index_select(0, j) + half) / self.ramp).clamp(0.0, 1.0).unsqueeze(-1)
        return torch.lerp(piece[:, 0], piece[:, 1], s * s * s * (10.0 + s * (6.0 * s - 15.0)))  # exact where held

    def __repr__(self) -> str:
        return (f"Inputs(names={list(self.names)}, N={self.t.shape[0]}, t=[{self.t[0].item():g}, "
                f"{self.t[-1].item():g}], kind={self.kind!r})")


def _ramp(t: torch.Tensor, kind: str) -> float:
    """:attr:`Inputs.ramp` of samples at times ``t (N,)``: :data:`RAMP` of their span, at most a
    hundredth of the shortest interval, at least 1e5 roundoffs of the times in their dtype."""
    if kind != "zoh" or t.shape[0] < 2:
        return 0.0
    floor = 1e5 * torch.finfo(t.dtype).eps * float(t.abs().max())
    return min(max(RAMP * float(t[-1] - t[0]), floor), 1e-2 * float((t[1:] - t[:-1]).min()))
