"""The fit's local time: the data's times less the earliest ``t0``.

A fit's storage grid, data-built first reference and interpolants work on the data's times. At clock
times (``t ~ 1e8`` to ``1e9`` s) those are resolved only to ``eps t``: a grid at ``t = 1.7e9`` held its
nodes to 2.4e-7 (its intervals 0.007 long), a smooth oscillator's fit took 22 iterations instead of
5, and a note said the grid missed a change of the model; a held input's step spanned 1e5 roundoffs
of ``t``, and fits failed. So a fit runs in local time ``s = t - origin``
(:meth:`torchql.problem.Problem._local_time`), where the model is given the data's time:

* a model with inputs through :func:`torchql.model.attach_inputs` (its signals shifted too);
* a model whose forward does not read ``t`` (:func:`reads_time`) needs nothing, where its times are
  clock times (:data:`CLOCK_RATIO`);
* a model whose forward reads ``t`` (a forcing ``cos(t)``) and has no inputs is fitted on the data's
  own times, as given: every copy of it that a solver integrates would need the shift.
"""

from __future__ import annotations

import torch

__all__ = ["CLOCK_RATIO", "local_origin", "reads_time"]

#: A model that does not read ``t`` is fitted in local time where ``|t0|`` exceeds this many times
#: the data's span: there a grid of 1,000 intervals resolves its nodes to ``eps |t0| / span`` of an
#: interval, ``2e-10`` and more (at ``t = 1.7e9`` over 7 s, 5e-5). Nearer 0 the data's own times
#: serve, and a forward that reads ``t`` where no probe sees it (a switch between two observation
#: times) is given them, as it is given the data's times everywhere else.
CLOCK_RATIO = 1e3


def reads_time(system, t0: torch.Tensor, t_obs: torch.Tensor, z0: torch.Tensor) -> bool:
    """Whether the forward of ``system``'s model reads ``t``: at the augmented state ``z0 (M,)`` (a
    sample's guesses) its value differs between ``t0``, the data's times ``t_obs`` and the midpoints
    between them, or depends on ``t`` in autograd's graph at ``t0`` (a smooth use of ``t``, whatever
    its values there). No probe proves that a forward ignores ``t``: a switch that none of these
    times crosses goes unseen, which :data:`CLOCK_RATIO` confines to clock times."""
    t = torch.cat([t0.reshape(-1)[:1], t_obs.reshape(-1)])
    t = torch.cat([t, 0.5 * (t[1:] + t[:-1])])  # (and between them: a switch between two observations)
    with torch.no_grad():
        values = torch.vmap(system.f)(t, z0.expand(t.numel(), -1))
    if bool((values != values[:1]).any()):
        return True
    with torch.enable_grad():
        return bool(system.f(t[0].detach().clone().requires_grad_(True), z0.detach()).requires_grad)


def local_origin(t0: torch.Tensor, t_obs: torch.Tensor, per_sample: bool) -> float | torch.Tensor:
    """The origin of a fit's local time: the earliest ``t0`` (``()`` or ``(B,)``; a fit with inputs).
    With ``per_sample`` (a model that does not read ``t``): a sample's ``t0`` where it lies farther
    than :data:`CLOCK_RATIO` times its span from 0, else 0 (the data's own times), decided for
    each sample that has its own times ``t_obs (B, T)`` (``(B,)``: a sample of a batch computes on
    the times of its own fit), or for all with a shared ``t0``; samples of their own ``t0`` over
    shared times keep the data's times."""
    if not per_sample:
        return float(t0.min())
    far = t0.abs() > CLOCK_RATIO * (t_obs[..., -1] - t0).abs()  # () or (B,)
    if not bool(far.any()) or (t0.dim() == 1 and t_obs.dim() == 1):
        return 0.0
    if t_obs.dim() == 2:  # each sample its own times: its own decision, as its own fit's
        return torch.where(far, t0.expand_as(far), torch.zeros_like(far, dtype=t0.dtype))
    return float(t0)
