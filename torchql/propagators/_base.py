"""The interface every linear propagator implements."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # pragma: no cover
    from ..trajectory import IntervalSystem
    from ..transfer import Transfers


class LinearPropagator:
    """Integrates the transfers of every grid interval of a quasilinear system at once.

    Attributes
    ----------
    name : str
        The name ``linear_solver=`` selects it by.
    grid_solver : bool
        Whether ``fit`` may also solve the nonlinear model on the grid (multiple shooting from a
        predicted trajectory, :mod:`torchql.grid_solve`) wherever a prediction is at hand; if
        not, every nonlinear pass is integrated by the adaptive ``solver``.
    stiff_stable : bool
        Whether its transfers stay stable on a stiff model's linearizations (implicit or
        exponential, as ``"radau"``); an explicit one's need ever more substeps there, or fail.
    with_solution : bool
        Whether, where the reference is the model's own solution (shooting's iterates, every
        fit's final pass), the homogeneous solutions are integrated together with that solution
        by Rodas5P (:mod:`torchql.solvers.sensitivity`) instead of by this propagator's transfers.
    hermite_degree : int
        Degree of the interpolants of the reference ``z`` and of ``h f`` between grid nodes in
        the coefficients :meth:`series` receives: 3 (cubic Hermite) or 5 (quintic).
    jacobian_degree : int
        Degree of the interpolant of ``h A``: 3 (cubic Hermite), or 5 (quintic, from the second
        time derivative of ``A`` that the linearization then also gives).
    auto_solver : str or None
        The nonlinear ``solver`` that ``solver="auto"`` takes with this propagator for a model
        that is not stiff; None: :data:`torchql.stiffness.EXPLICIT_SOLVER`.
    """

    name: str = ""
    grid_solver: bool = True
    stiff_stable: bool = False
    with_solution: bool = False
    hermite_degree: int = 3
    jacobian_degree: int = 3
    auto_solver: str | None = None

    @property
    def storage_degree(self) -> int:
        """The degree that sets the storage's interpolation error (the lower of
        :attr:`hermite_degree` and :attr:`jacobian_degree`), from which ``grid="auto"`` counts its intervals."""
        return min(self.hermite_degree, self.jacobian_degree)

    def transfers(self, system: "IntervalSystem", *, rtol: float, atol: float, solver: str,
                  max_steps: int | None) -> "tuple[Transfers, int]":
        """The transfers ``T_j`` of all ``G - 1`` intervals of ``system``, each within ``rtol``/``atol``.

        Parameters
        ----------
        system : IntervalSystem
            Every interval's linear problem in local time ``s`` in ``[0, 1]``.
        rtol, atol : float
            Per-interval tolerances (already divided for the accumulation over the grid).
        solver : str
            ``fit``'s torchdiffeq method name, for propagators that integrate with it.
        max_steps : int or None
            ``fit``'s step budget, for propagators that integrate adaptively.

        Returns
        -------
        transfers : Transfers
        n_evals : int
            Evaluations of the interval system's coefficients (each one on all intervals at once).

        Raises
        ------
        IntegrationError
            When a transfer cannot be integrated to the tolerance or becomes non-finite.
        """
        raise NotImplementedError

    def series(self, coefficients, *, rtol: float, atol: float, max_substeps: int):
        """Batched transfers for :func:`torchql.fit_many`: every interval of every sample at once.

        ``coefficients``: the intervals' power-basis coefficients (``torchql.transfer._Coefficients``,
        the samples' intervals side by side); ``rtol``/``atol`` per interval. Returns ``(Y, failed,
        n_evals)``: the active rows ``(a, M+1, N)``, a per-interval failure mask ``(N,)`` (never
        raised) and the work done. A propagator without it serves ``fit`` only (``batched`` is
        ``False``).
        """
        raise NotImplementedError

    @property
    def batched(self) -> bool:
        """Whether :meth:`series` is implemented (``fit_many`` can use this propagator)."""
        return type(self).series is not LinearPropagator.series

    def __eq__(self, other: object) -> bool:
        """Equal to another propagator of the same class and name, or to its name."""
        if isinstance(other, str):
            return other == self.name
        return type(other) is type(self) and getattr(other, "name", None) == self.name

    def __hash__(self) -> int:
        return hash((type(self), self.name))

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r})"
