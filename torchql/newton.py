"""Algebraic Newton–Raphson for systems of nonlinear equations (thesis eq. 3.7)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch.func import jacrev

from ._arrays import float_tensor
from ._checks import non_negative_number

__all__ = ["newton_raphson", "NewtonResult", "ROOT_FALL"]

#: A step below ``xtol`` is convergence only where the residual fell to this fraction of the guess's,
#: or to its rounding at the guess's scale (``100 eps ||J|| max(|x|, 1)`` there: a guess at the root
#: itself): ``sin(x)`` from ``pi / 2`` (where its derivative is 6e-17) was thrown to ``x = -1.6e16``,
#: where every step is below ``xtol`` beside ``|x|``, and was reported converged with ``|sin(x)| = 0.66``.
ROOT_FALL = 1e-3


@dataclass
class NewtonResult:
    """What :func:`newton_raphson` found.

    Attributes
    ----------
    x : Tensor ``(m,)``
        The last iterate.
    success : bool
        Whether the residual fell below ``ftol``, or the step below ``xtol`` (relative) with the
        residual below :data:`ROOT_FALL` of the guess's or at the rounding of its guess's scale.
    message : str
        Why it stopped.
    iterations : int
        Number of Newton steps taken.
    history : list of Tensor ``(m,)``
        Every iterate, the initial guess first.
    residual_norms : list of float
        ``max |R(x)|`` at every iterate in ``history``.
    """

    x: torch.Tensor
    success: bool
    message: str
    iterations: int
    history: list[torch.Tensor] = field(default_factory=list)
    residual_norms: list[float] = field(default_factory=list)


def newton_raphson(
    residual: Callable[[torch.Tensor], torch.Tensor],
    x0,
    *,
    max_iter: int = 50,
    xtol: float | None = None,
    ftol: float = 0.0,
    jacobian: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> NewtonResult:
    """Solve ``R(x) = 0`` by ``x_{n+1} = x_n - J_n^{-1} R(x_n)``.

    Parameters
    ----------
    residual : callable ``R(x) -> (m,)``
        Differentiable residual function of ``x (m,)``, of its dtype.
    x0 : Tensor ``(m,)``
        Initial guess (float64 unless given otherwise).
    max_iter : int
        Maximum number of steps.
    xtol : float, optional
        Stop when ``max |dx_i| <= xtol * max(|x_i|, 1)``. Default ``1e-12`` in float64, 100 roundoffs
        in a lower precision (``1.2e-5`` in float32: a Newton step there is rounding once the
        iterate is within a few roundoffs of the root). That is success only where ``max |R(x)|``
        fell to :data:`ROOT_FALL` of the guess's, or to rounding (``100 eps ||J|| max(|x|, 1)`` at the
        guess); else no root was found, and the message says so.
    ftol : float
        Stop when ``max |R(x)| <= ftol``, a success.
    jacobian : callable ``J(x) -> (len(R(x)), m)``, optional
        Analytic Jacobian (a tensor of ``x``'s dtype); default :func:`torch.func.jacrev` of
        ``residual``. Non-square systems are solved in the least-squares sense (Gauss–Newton).

    Returns
    -------
    NewtonResult
    """
    x = float_tensor(x0, "x0", expected="a one-dimensional tensor (m,)").clone()
    if x.dim() != 1:
        raise ValueError(f"`x0` must be one-dimensional, shape (m,); received shape {tuple(x.shape)}")
    if not torch.isfinite(x).all():
        raise ValueError("`x0` must be finite")
    if xtol is None:
        xtol = 1e-12 if x.dtype == torch.float64 else 100 * torch.finfo(x.dtype).eps
    xtol, ftol = non_negative_number("xtol", xtol), non_negative_number("ftol", ftol)
    if not callable(residual):
        raise TypeError(f"`residual` must be callable as R(x) -> Tensor; received {type(residual).__name__}")
    if jacobian is not None and not callable(jacobian):
        raise TypeError(f"`jacobian` must be callable as J(x) -> Tensor; received {jacobian!r}")
    if isinstance(max_iter, bool) or not isinstance(max_iter, int) or max_iter < 0:
        raise ValueError(f"`max_iter` must be a non-negative integer; received {max_iter!r}")
    jac_fn = jacobian if jacobian is not None else jacrev(residual)
    history, norms = [x.clone()], []
    r = residual(x)
    roundoff = math.nan  # the residual's rounding at the guess's scale (set with its first Jacobian)
    if not isinstance(r, torch.Tensor) or r.dim() != 1:
        raise ValueError("`residual` must return a one-dimensional tensor (m,)")
    if r.dtype != x.dtype:
        raise TypeError(f"`residual` must return a tensor of x0's dtype {x.dtype}; received {r.dtype}")
    norms.append(float(r.abs().max()))
    message, success = "The maximum number of iterations was reached. Increase `max_iter`.", False
    it = 0
    if norms[0] <= ftol:
        return NewtonResult(x=x, success=True, message="Converged: the initial guess meets `ftol`.", iterations=0,
                            history=history, residual_norms=norms)
    for it in range(1, max_iter + 1):
        J = jac_fn(x)
        if not isinstance(J, torch.Tensor) or J.dtype != x.dtype:
            what = f"a tensor of {J.dtype}" if isinstance(J, torch.Tensor) else type(J).__name__
            raise TypeError(f"`jacobian` must return a tensor of x's dtype {x.dtype}; received {what}")
        if J.shape != (r.shape[0], x.shape[0]):
            raise ValueError(f"`jacobian` must return shape ({r.shape[0]}, {x.shape[0]}); received {tuple(J.shape)}")
        if it == 1:
            roundoff = 100 * torch.finfo(x.dtype).eps * float(J.abs().sum(dim=1).max()) * max(float(x.abs().max()), 1.0)
        if J.shape[0] == J.shape[1]:
            dx, info = torch.linalg.solve_ex(J, -r)
            if int(info) != 0 or not torch.isfinite(dx).all():
                message = "The Jacobian is singular at the current iterate. Start from another guess."
                it -= 1
                break
        else:
            dx = torch.linalg.lstsq(J, -r.unsqueeze(-1)).solution.squeeze(-1)
        x = x + dx
        r = residual(x)
        history.append(x.clone())
        norms.append(float(r.abs().max()))
        if not (torch.isfinite(x).all() and math.isfinite(norms[-1])):
            message = "The iteration diverged (non-finite iterate). Start closer to the root."
            break
        if norms[-1] <= ftol:
            message, success = "Converged.", True
            break
        if float((dx.abs() / x.abs().clamp_min(1.0)).max()) <= xtol:
            success = norms[-1] <= max(ROOT_FALL * norms[0], roundoff)
            message = ("Converged." if success else
                       f"The step fell below `xtol`, but max |R(x)| = {norms[-1]:.3g} is not below {ROOT_FALL:g} of "
                       f"the guess's {norms[0]:.3g} nor at its rounding: no root was found (the iterate is at max |x| "
                       f"= {float(x.abs().max()):.3g}, where such a step is small beside it). Start from another "
                       "guess, or give `ftol` the residual that counts as a root.")
            break
    return NewtonResult(x=x, success=success, message=message, iterations=it, history=history, residual_norms=norms)
