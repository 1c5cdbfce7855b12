"""Why a fit stopped: one set of statuses for every fit, each value the message a user acts on.

A leaf module: results, reports and plots all read it, and it imports nothing of the package.
"""

from __future__ import annotations

import enum

__all__ = ["Status"]


class Status(enum.Enum):
    """Why a fit stopped. Each value is the message a user needs to act on."""

    CONVERGED = "Converged: the update alpha and the change in the estimates fell below `xtol`."
    CONVERGED_SSE = "Converged: the weighted sum of squares stopped changing (relative change below `ftol`)."
    MAX_ITER = (
        "The maximum number of iterations was reached before convergence. Increase `max_iter`, "
        "or start from guesses closer to the solution."
    )
    MAX_TIME = (
        "The time budget `max_time` ran out before convergence; the estimates are the last accepted "
        "iterate's. Increase `max_time`, or start from guesses closer to the solution."
    )
    DIVERGED = (
        "The iteration diverged: the estimates ran away, or the update, the trajectory or the sum of squares "
        "became non-finite or grew without bound. Start from guesses closer to the solution, use `bounds` to "
        "keep the unknowns in a sensible range, or observe more of the trajectory."
    )
    INTEGRATION_FAILED = (
        "The ODE solver failed. Start from better guesses (the model may blow up there), loosen "
        "`rtol`/`atol`, or choose another `solver`."
    )
    STALLED = (
        "The iteration stalled: its steps stopped lowering the sum of squares before converging (no damped "
        "step lowered it, the Levenberg-Marquardt damping reaching its limit, or only steps too short to matter "
        "did), and Gauss-Newton steps on the model itself did not reach its optimum. Start from guesses closer "
        "to the solution, use `bounds` to keep "
        "the unknowns in a sensible range, or try several starts (torchql.multistart)."
    )
    NOT_IDENTIFIABLE = (
        "The data do not determine every unknown: the least-squares problem is rank deficient. "
        "Fix the named unknowns (`params=`, `fixed_x0=`), or observe more states or times."
    )
    EXACT_INFEASIBLE = (
        "The observations marked `exact` cannot all be met: they are linearly dependent or "
        "contradictory. Mark fewer values exact."
    )

    @property
    def success(self) -> bool:
        """Whether this status is a successful convergence."""
        return self in (Status.CONVERGED, Status.CONVERGED_SSE)
