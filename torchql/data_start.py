"""``initial_trajectory="data"``: a first Kantorovich reference built from the data, no integration.

The observed states are the data, smoothed (:func:`torchql.smoothing.smooth`) and interpolated
on the storage grid; the unobserved ones are derived from the model where the observed states'
equations involve them (``y' = v`` gives ``v`` from the smoothed ``y``); the first coefficients
are fitted to the data's slopes (gradient matching). None of this integrates the model, so it
does not depend on how poor the guesses are (the thesis' wide-basin start). One sample at a
time: :func:`torchql.fit` calls it once, :func:`torchql.fit_many` once per sample.
"""

from __future__ import annotations

import math

import torch
from torch.func import jacrev, vmap

from .lstsq import solve_update
from .options import DAMPING_MAX as _DAMPING_MAX, DAMPING_START as _DAMPING_START
from .smoothing import interpolate, smooth

__all__ = ["data_reference", "slopes"]

#: Gauss–Newton steps of the gradient matching that gives the first coefficients from the data.
MATCH_STEPS = 30
#: Gauss–Newton steps that derive unobserved states for a first trajectory from the data.
DERIVE_STEPS = 8


def slopes(grid: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """Node slopes of values ``z (G, M)`` on ``grid`` by finite differences (zeros on a one-node grid)."""
    return torch.gradient(z, spacing=(grid,), dim=0)[0] if grid.shape[0] > 1 else torch.zeros_like(z)


def data_reference(system, grid: torch.Tensor, t_obs: torch.Tensor, y: torch.Tensor, sigma: torch.Tensor,
                   rows_mask: torch.Tensor, observed_states: list, z0: torch.Tensor, unknown_index: torch.Tensor,
                   bounds, rcond: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The first reference of one sample, built from its data.

    Parameters
    ----------
    system : AugmentedSystem
    grid : Tensor ``(G,)``
        The storage grid.
    t_obs : Tensor ``(T,)``; y, sigma : Tensor ``(T, K)``; rows_mask : bool Tensor ``(T, K)``
        The data, their standard deviations, and which values are used.
    observed_states : list
        For each output, the state it reads directly (``None`` otherwise).
    z0 : Tensor ``(M,)``
        The guesses (states, then coefficients).
    unknown_index : Tensor ``(m,)`` of int; bounds : Bounds; rcond : float
        The unknowns, their bounds, and the rank threshold, for the gradient matching.

    Returns
    -------
    z_ref, z_dot : Tensor ``(G, M)``
        The reference and its slopes at the nodes.
    z0 : Tensor ``(M,)``
        The guesses with the coefficients from the gradient matching (when some state is observed).
    """
    z_ref = z0.unsqueeze(0).repeat(grid.shape[0], 1)
    observed = []
    for k, i in enumerate(observed_states):
        if i is None:
            continue
        ok = rows_mask[:, k]
        if int(ok.sum()) >= 1:
            values = smooth(t_obs[ok], y[ok, k], sigma[ok, k] ** -2)
            z_ref[:, i] = interpolate(t_obs[ok], values, grid)
            observed.append(i)
    z_dot = slopes(grid, z_ref)
    hidden = [i for i in range(system.n) if i not in observed]
    if observed and hidden:
        z_ref = _derive_hidden(system, grid, z_ref, z_dot, observed, hidden)
        z_dot = slopes(grid, z_ref)
    if observed and system.P:
        z_ref = _match_slopes(system, grid, z_ref, z_dot, z0, unknown_index, bounds, rcond)
        z0 = torch.cat([z0[: system.n], z_ref[0, system.n:]])
    return z_ref, z_dot, z0


def _match_slopes(system, grid, z_ref, z_dot, z0, unknown_index, bounds, rcond) -> torch.Tensor:
    """First coefficients from the data's slopes: ``min_p sum_j ||(z'_j - f(t_j, z_j; p)) / s||^2``.

    With the trajectory fixed at the smoothed data, the coefficients enter only the
    right-hand side, so this small least-squares problem (gradient matching) needs no
    integration and does not depend on how poor the guesses are; a few damped
    Gauss–Newton steps from the guesses solve it (bounds honoured). ``s`` scales each
    state's slopes to unit size. Returns ``z_ref`` with its coefficient columns replaced.
    """
    n = system.n
    scale = z_dot[:, :n].abs().amax(dim=0)
    scale = torch.where(scale > 0, scale, torch.ones_like(scale))

    def mismatch(p, t, z, zd):
        return (system.f(t, torch.cat([z[:n], p]))[:n] - zd[:n]) / scale

    value = vmap(mismatch, in_dims=(None, 0, 0, 0))
    jac = vmap(jacrev(mismatch), in_dims=(None, 0, 0, 0))
    m_states = unknown_index.numel() - system.P
    u = z0[unknown_index].clone()
    p = z0[n:].clone()
    with torch.no_grad():
        r = value(p, grid, z_ref, z_dot).reshape(-1)
        cost = float(r.square().sum())
        if not math.isfinite(cost):
            return z_ref
        damping = 0.0
        rows = torch.ones_like(r)
        none = torch.zeros_like(r, dtype=torch.bool)
        for _ in range(MATCH_STEPS):
            J = jac(p, grid, z_ref, z_dot).reshape(-1, system.P)
            if bounds.active:
                J = J * bounds.derivative(u)[m_states:]
            accepted = False
            while damping <= _DAMPING_MAX:
                sol = solve_update(J, -r, rows, none, rcond, damping)
                step = torch.cat([torch.zeros(m_states, dtype=u.dtype, device=u.device), sol.alpha])
                change, _ = bounds.step(u, step)
                p_new = p + change[m_states:]
                r_new = value(p_new, grid, z_ref, z_dot).reshape(-1)
                new_cost = float(r_new.square().sum())
                if math.isfinite(new_cost) and new_cost < cost:
                    accepted = True
                    break
                damping = _DAMPING_START if damping == 0.0 else 10 * damping
            if not accepted:
                break
            small = bool((change.abs() <= 1e-10 * (u.abs() + 1e-300)).all())
            p, u, r, cost, damping = p_new, u + change, r_new, new_cost, damping / 10
            if small:
                break
    out = z_ref.clone()
    out[:, n:] = p
    return out

def _derive_hidden(system, grid, z_ref, z_dot, observed: list[int], hidden: list[int]) -> torch.Tensor:
    """Unobserved states at every node, from the model: ``min ||x_o' - f_o(x_o, x_h)||`` over ``x_h``.

    Where the observed states' equations involve the hidden ones (``y' = v`` gives ``v``
    from the smoothed ``y``), a few vectorized Gauss–Newton steps from the guess ``x0``
    find them at each node; nodes where this does not lower the mismatch, or becomes
    non-finite, keep the guess.
    """
    obs = torch.tensor(observed, device=z_ref.device)
    hid = torch.tensor(hidden, device=z_ref.device)

    def mismatch(xh, t, z, zd):
        return system.f(t, z.index_put((hid,), xh))[obs] - zd[obs]

    jac = vmap(jacrev(mismatch))
    value = vmap(mismatch)
    xh = z_ref[:, hid].clone()
    with torch.no_grad():
        r = value(xh, grid, z_ref, z_dot)
        best = r.square().sum(-1)
        for _ in range(DERIVE_STEPS):
            J = jac(xh, grid, z_ref, z_dot)
            step = torch.linalg.pinv(J, rtol=1e-8) @ r.unsqueeze(-1)
            trial = xh - step.squeeze(-1)
            r_trial = value(trial, grid, z_ref, z_dot)
            norm = r_trial.square().sum(-1)
            better = torch.isfinite(norm) & (norm < best)
            xh = torch.where(better.unsqueeze(-1), trial, xh)
            r = torch.where(better.unsqueeze(-1), r_trial, r)
            best = torch.where(better, norm, best)
    out = z_ref.clone()
    out[:, hid] = xh
    return out
