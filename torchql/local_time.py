"""The fit's local time: the data's times less the earliest ``t0``.

A fit's storage grid, data-built first reference and interpolants work on the data's times. At clock
times (``t ~ 1e8`` to ``1e9`` s) those are resolved only to ``eps t``: a grid at ``t = 1.7e9`` held its
nodes to 2.4e-7 (its intervals 0.007 long), a smooth oscillator's fit took 22 iterations instead of
5, and a note said the grid missed a change of the model; a held input's step spanned 1e5 roundoffs
of ``t``, and fits failed. So a fit runs in local time ``s = t - origin``
(:meth:`torchql.problem.Problem._local_time`), where the model is given the data's time:

* a model with inputs through :func:`torchql.model.attach_inputs` (its signals shifted too);
* a model whose forward does not read ``t`` (:func:`reads_time`) needs nothing;
* a model whose forward reads ``t`` (a forcing ``cos(t)``) and has no inputs is fitted on the data's
  own times, as given: every copy of it that a solver integrates would need the shift.
"""

from __future__ import annotations

import torch

__all__ = ["local_origin", "reads_time"]


def reads_time(system, t0: torch.Tensor, t_obs: torch.Tensor, z0: torch.Tensor) -> bool:
    """Whether the forward of ``system``'s model reads ``t``: at the augmented state ``z0 (M,)`` (a
    sample's guesses) its value differs between ``t0`` and the data's times ``t_obs``, or depends on
    ``t`` in autograd's graph at ``t0`` (a smooth use of ``t``, whatever its values there)."""
    t = torch.cat([t0.reshape(-1)[:1], t_obs.reshape(-1)])
    with torch.no_grad():
        values = torch.vmap(system.f)(t, z0.expand(t.numel(), -1))
    if bool((values != values[:1]).any()):
        return True
    with torch.enable_grad():
        return bool(system.f(t[0].detach().clone().requires_grad_(True), z0.detach()).requires_grad)


def local_origin(t0: torch.Tensor, t_obs: torch.Tensor, per_sample: bool) -> float | torch.Tensor:
    """The origin of a fit's local time: the earliest ``t0`` (``()`` or ``(B,)``); with ``per_sample``,
    where each sample has its own ``t0`` and its own times ``t_obs (B, T)``, each sample's ``t0``
    ``(B,)``, so that a sample of a batch computes on the local times of its own fit."""
    if per_sample and t0.dim() == 1 and t_obs.dim() == 2:
        return t0.clone()
    return float(t0.min())
