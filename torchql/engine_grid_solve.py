"""The engine's grid solver of the model, and what a trial over its step budget is.

For a fit of at most a few thousand sample-intervals the model's solution from a trajectory's
linear prediction is found on the storage grid by multiple shooting (:func:`~torchql.grid_solve.
solve_on_grid_batch`: every interval at once by RK4, Newton on the node defects), with at most a
number of RK4 steps per interval. A trial that needs more than that budget used to count as a
blow-up, unless the current iterate needed more too (then the grid is too coarse for the model,
and the sample's trials went to the adaptive solvers). That left a wall where a model only
becomes faster as the iterates move: a relaxation rate growing from its guess of 1 to 30 over a
grid chosen for the guess. The current iterate fits the budget and every undamped trial one step
further does not, so the damping shortened the steps to those that fit, and the fit crept along
the wall, 0.01 % a step, for 30 iterations. :meth:`GridSolve._over_budget` now integrates such a
trial adaptively instead, where it is near its current iterate (:data:`NEAR_STEP`); a trial further
away stays a blow-up, as an oscillator's damping asked 570 times its value, whose adaptive
solution through the stiff stretch it leads into took over a minute.
"""

from __future__ import annotations

import torch

from .engine_state import members
from .grid import refine
from .grid_solve import solve_on_grid_batch
from .linearize import flow_rates

__all__ = ["GridSolve", "ADAPTIVE_BLOWUP_STEPS", "NEAR_STEP"]

#: Newton iterations the grid solver gets from a trajectory's linear prediction before the
#: adaptive solver takes over (from a good prediction it needs two or three).
_GRID_NEWTON = 8
#: Most steps of the adaptive solver for a trial over the grid solver's budget (whose current
#: iterate fits it): a trial that needs more is a blow-up. A step of the batched explicit pairs
#: costs 7 to 12 evaluations; 2,048 of them are about the grid solver's own ceiling for a blow-up
#: (16,384 RK4 steps over the span, :data:`~torchql.engine_evaluate._BLOWUP_STEPS`).
ADAPTIVE_BLOWUP_STEPS = 2048
#: Largest scaled step (``max_i |du_i| / max(|u_i|, s_i)``, as the convergence test scales it) from the
#: current iterate of a trial over the grid solver's budget that :meth:`GridSolve._over_budget` tries:
#: a rate that at most doubles (the steps of a relaxation rate growing from its guess), not a far step
#: into a stiff stretch (an oscillator's damping asked 570 times its value, whose adaptive solution
#: took over a minute, and whose rejection the damping answers at once).
NEAR_STEP = 1.0


class GridSolve:
    """The grid solver (mixed into :class:`torchql.engine.Engine` with :class:`~torchql.engine_evaluate.Evaluation`)."""

    def _on_grid(self, idx, z0, guess, rtol, atol, substeps, budget_is_final, traj, ok, errors,
                 reference=None, stop=None) -> None:
        """:meth:`_nonlinear`'s grid solver, from ``guess``, for the samples whose guess is finite;
        fills ``traj`` and ``ok`` in place, and with ``budget_is_final`` the blow-ups' ``errors``:
        the samples over the budget, where no current iterate is given; where its ``reference``
        needs more steps too, none (the grid is too coarse for the sample's model: the adaptive
        solvers take its trials from now on); else, for a trial near its current iterate
        (:meth:`_near`), as :meth:`_over_budget` finds, and for one further away, the samples over."""
        over = self._grid_solve(idx, z0, guess, rtol, atol, substeps, traj, ok)
        if not budget_is_final:
            return
        over &= ~ok
        if reference is not None and bool(over.any()):
            # the current iterates not yet seen to fit in the budget (one check per accepted iterate)
            keys = {int(r): reference[0][r].detach().cpu().numpy().tobytes() for r in over.nonzero().flatten()}
            rows = torch.tensor([r for r, key in keys.items() if self.fits_grid.get(int(idx[r])) != key],
                                dtype=torch.long, device=over.device)
            if rows.numel():
                ref_traj = torch.full_like(traj[rows], float("nan"))
                ref_ok = torch.zeros_like(ok[rows])
                ref_over = self._grid_solve(idx[rows], reference[0][rows], reference[1][rows], rtol, atol, substeps,
                                            ref_traj, ref_ok)
                for k, r in enumerate(rows.tolist()):
                    if bool(ref_over[k]):
                        self.coarse_grid.add(int(idx[r]))
                        over[r] = False  # the adaptive solvers take it
                    else:
                        self.fits_grid[int(idx[r])] = keys[r]
            near = over & self._near(idx, z0, reference[0])
            if bool(near.any()):
                self._over_budget(idx, near.nonzero().flatten(), z0, rtol, atol, traj, ok, errors, stop)
                over &= ~near
        for s in over.nonzero().flatten().tolist():
            errors[s] = f"a grid interval needed more than the grid solver's {substeps} steps (a blow-up)"

    def _near(self, idx, z0, current) -> torch.Tensor:
        """Whether the trials' estimates ``z0 (S, M)`` of the chunk's samples ``idx`` are within
        :data:`NEAR_STEP` of their current iterates' ``current (S, M)`` (scaled as the convergence
        test scales a step, :meth:`~torchql.engine.Engine._scaled_step`), ``(S,)``."""
        index = self.spec.unknown_index
        return self._scaled_step(idx, current, z0[:, index] - current[:, index]) <= NEAR_STEP

    def _in_coarse_grid(self, idx) -> torch.Tensor:
        """Whether each of the chunk's samples ``idx`` is one whose model is too fast for its grid's
        solver (``coarse_grid``: the adaptive solvers take its solutions), bool ``(S,)``."""
        return members(self.coarse_grid, idx)

    def _over_budget(self, idx, rows, z0, rtol, atol, traj, ok, errors, stop) -> None:
        """The trials of the samples ``rows`` (positions in ``idx``) that need more steps than the
        grid solver's budget where their current iterates do not: integrated by the adaptive
        solver, with at most :data:`ADAPTIVE_BLOWUP_STEPS` steps and the ``stop`` test (of positions
        in ``idx``). One that integrates is a model faster than its grid at the current iterate,
        not a blow-up: its sample's trials go to the adaptive solvers from now on. One that fails
        there (non-finite, over the steps, stopped as no better than the current iterate, or found
        stiff) is a blow-up, with the solver's words. Fills ``traj``, ``ok`` and ``errors``."""
        sub_traj, sub_ok = traj[rows].clone(), ok[rows].clone()
        sub_errors: list = [None] * rows.numel()
        asked = None if stop is None else (lambda pos, y, reached: stop(rows[pos], y, reached))
        # (a rejected trial's stiff stretch says nothing of the fit's: the sample is not marked stiff)
        self._adaptive(idx[rows], z0[rows], rtol, atol, sub_traj, sub_ok, sub_errors, asked, ADAPTIVE_BLOWUP_STEPS,
                       note_stiff=False)
        traj[rows], ok[rows] = sub_traj, sub_ok
        for k, r in enumerate(rows.tolist()):
            if bool(sub_ok[k]):
                self.coarse_grid.add(int(idx[r]))
            else:
                errors[r] = ("a grid interval needed more than the grid solver's steps, and the adaptive solver "
                             f"failed: {sub_errors[k] or 'stopped'} (a blow-up)")

    def _grid_solve(self, idx, z0, guess, rtol, atol, substeps, traj, ok) -> torch.Tensor:
        """The grid solver from ``guess`` for the samples whose guess is finite; fills ``traj`` and
        ``ok`` in place and returns ``over (S,)``: the samples that exceeded ``substeps``."""
        grid = self._grid_of(idx)
        sub = torch.isfinite(guess).flatten(1).all(dim=1).nonzero().flatten()
        over = torch.zeros_like(ok)
        if not sub.numel():
            return over
        k = self._split
        grid = grid if grid.dim() == 1 else grid[sub]
        slopes, curvatures = self._guess_derivatives(grid, guess[sub])
        grid, guess = refine(grid, guess[sub], slopes, k, curvatures)
        solved = solve_on_grid_batch(self.system, z0[sub], grid, rtol=rtol, atol=atol, guess=guess,
                                     max_newton=_GRID_NEWTON, max_substeps=substeps)
        self.nfev += solved.n_evals
        good = solved.ok
        traj[sub[good]], ok[sub[good]], over[sub] = solved.traj[good][:, ::k], True, solved.over_budget
        return over

    def _guess_derivatives(self, grid: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """What the grid solver's interpolant of its guess ``z (S, G, M)`` on ``grid`` (``(G,)`` or
        ``(S, G)``) takes at the nodes: the augmented model's slopes (zeros, not evaluated, where it
        splits no interval), and for a storage of quintic interpolants, whose grids are coarser (a
        cubic interpolant on their sub-intervals would cost Newton an iteration), their rates
        ``d/dt f = f_t + A f`` along the flow (:func:`torchql.linearize.flow_rates`; the
        coefficients' rows zero); otherwise None (the cubic interpolant)."""
        if self._split == 1:
            return torch.zeros_like(z), None
        S, G, M = z.shape
        t = grid.expand(S, -1).reshape(-1)
        if self.spec.linear_solver.storage_degree < 5:
            return torch.vmap(self.system.f)(t, z.reshape(-1, M)).reshape(z.shape), None
        n = self.system.n
        slopes, rates = flow_rates(self.system.f, t, z.reshape(-1, M), n)
        curvatures = torch.zeros_like(z)
        curvatures[..., :n] = rates.reshape(S, G, n)
        return slopes.reshape(z.shape), curvatures
