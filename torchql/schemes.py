"""Iteration schemes: how a fit makes its trial iterate from the current one and an update ``alpha``.

``method=`` of :func:`torchql.fit` and :func:`torchql.fit_many` takes a registered name
(:data:`METHODS`: ``"kantorovich"``, the default, or ``"shooting"``) or a :class:`Scheme` object;
adding a scheme is a subclass registered by :func:`register_scheme`.

Both schemes update the unknowns alike: the superposition ``W_0 + sum_k alpha_k W_k`` of the
particular and homogeneous solutions of the linearized model predicts the new trajectory on the
grid, and the initial state and coefficients move by ``alpha``. They differ in what the next
reference is:

* **Kantorovich** (the thesis' method): the prediction itself, the model linearized about it. An
  iterate need not solve the model until the iteration converges, so a first reference may be
  built from the data, and each trial costs one linearization and one propagation.
* **Shooting**: the model integrated from the updated initial state and coefficients (the
  prediction its guess), with its sensitivities. Every iterate solves the model, and its merit
  is the model's own sum of squares.
"""

from __future__ import annotations

import torch

from . import engine_evaluate
from .engine_state import _pick, bound_of
from .linearize import map_fields
from .registry import Registry
from .trajectory import model_defect

__all__ = ["Scheme", "Kantorovich", "Shooting", "METHODS", "register_scheme", "scheme_strategy"]


class Scheme:
    """An iteration scheme.

    Attributes
    ----------
    name : str
        The name ``method=`` takes.
    integrates_model : bool
        Whether every iterate is the model's own solution from its estimates (then its merit is
        the model's sum of squares, the first reference is integrated strictly, and no iterate is
        re-anchored). Otherwise a first reference may be built from the data.
    """

    name: str = "base"
    integrates_model: bool = False

    def propose(self, engine, act: torch.Tensor, cur: dict, alpha: torch.Tensor) -> tuple[dict, torch.Tensor]:
        """The trial iterates of samples ``act`` (rows of ``cur``) with updates ``alpha (S, m)``:
        the evaluated trial (as :meth:`torchql.engine_evaluate.Evaluation._evaluate` returns it,
        with its ``defect``) and ``ok (S,)`` where it is usable."""
        W = _pick(cur["W"], act)
        z_new = W[..., 0] + torch.einsum("sgmk,sk->sgm", W[..., 1:], alpha)
        z0_new = engine.spec.shifted(_pick(cur["z0"], act), alpha)
        return self.trial(engine, act, cur, z0_new, z_new)

    def trial(self, engine, act, cur, z0_new: torch.Tensor, z_new: torch.Tensor) -> tuple[dict, torch.Tensor]:
        """The trial iterates from the new estimates ``z0_new (S, M)`` and the predicted
        trajectories ``z_new (S, G, M)``."""
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r})"

    def __eq__(self, other) -> bool:
        """Schemes of one class and name are one scheme (a copy, unpickled, equals the registered one)."""
        return type(other) is type(self) and other.name == self.name

    def __hash__(self) -> int:
        return hash((type(self), self.name))


def _usable(trial: dict, *more: torch.Tensor) -> torch.Tensor:
    """Samples whose trial propagated and has a finite merit and matrix (and each of ``more``)."""
    ok = ~trial["failed"] & torch.isfinite(trial["merit"]) & torch.isfinite(trial["C"]).flatten(1).all(dim=1)
    for condition in more:
        ok = ok & condition
    return ok


class Kantorovich(Scheme):
    """The thesis' scheme: the next reference is the predicted trajectory."""

    name = "kantorovich"

    def trial(self, engine, act, cur, z0_new, z_new):
        finite = torch.isfinite(z_new).flatten(1).all(dim=1)
        z_ref = _pick(cur["rz"], act)
        z_safe = torch.where(finite.reshape(-1, 1, 1), z_new, z_ref)
        lin_ref = cur["lin"]
        z_dot = _pick(lin_ref.f, act) + torch.einsum("sgij,sgj->sgi", _pick(lin_ref.jac, act), z_safe - z_ref)
        lin = engine._linearize(act, z_safe, z_dot)
        defect = model_defect(lin.f, z_dot, engine.system.n)
        trial = engine._evaluate_unless_rejected(act, cur, z0_new, z_safe, z_dot, lin, defect, finite)
        trial["defect"] = defect
        return trial, _usable(trial, finite)


class Shooting(Scheme):
    """The next reference is the model integrated from the new estimates, with its sensitivities."""

    name = "shooting"
    integrates_model = True

    def trial(self, engine, act, cur, z0_new, z_new):
        guess = torch.where(torch.isfinite(z_new), z_new, z0_new.unsqueeze(1).expand_as(z_new))
        # the solution and its sensitivities in one pass (finite where failed) for the propagators that
        # integrate them so, and for the samples whose model is too fast for their grid (``coarse_grid``):
        # the grid's sensitivities miss it as its solver does (a relaxation rate 100 times its guess
        # crept 8 % of the way a step, to max_iter)
        joint = engine._in_coarse_grid(act) | engine._joint_sensitivities
        traj, W, errors = guess.clone(), None, [None] * act.numel()
        together, alone = joint.nonzero().flatten(), (~joint).nonzero().flatten()
        if together.numel():
            traj_j, W_j, errors_j = engine._solve_with_sensitivities(act[together], z0_new[together], trial=True)
            traj[together], W = traj_j, W_j.new_full((act.numel(), *W_j.shape[1:]), float("nan"))
            W[together] = W_j
            for k, e in zip(together.tolist(), errors_j):
                errors[k] = e
        if alone.numel():
            part = act[alone]
            traj[alone], errors_a = engine._nonlinear(part, z0_new[alone], loose=False, guess=guess[alone],
                                                      budget_is_final=True, stop=_above_current(engine, part, cur),
                                                      reference=(_pick(cur["z0"], part), _pick(cur["rz"], part)))
            for k, e in zip(alone.tolist(), errors_a):
                errors[k] = e
        integrated = torch.tensor([e is None for e in errors], dtype=torch.bool, device=z0_new.device)
        traj = torch.where(integrated.reshape(-1, 1, 1), traj, guess)  # failed samples: any finite stand-in
        lin = engine._linearize(act, traj)
        failed = None
        if W is not None and alone.numel():  # the others' sensitivities propagated on their grids
            lin_alone = map_fields(lin, lambda v: None if v is None else v[alone])
            W[alone], failed = engine._propagate(act[alone], traj[alone], lin_alone.f, lin_alone,
                                                 engine.spec.columns(z0_new[alone]))
        trial = engine._evaluate(act, z0_new, traj, lin.f, lin, solution=True, W=W)
        if failed is not None:
            trial["failed"][alone] |= failed
        trial["defect"] = torch.zeros_like(trial["merit"])
        return trial, _usable(trial, integrated)


def _above_current(engine, act, cur):
    """The test that ends the integration of a shooting trial of the samples ``act`` once its
    objective over the data passed exceeds the current iterate's merit: the trial is then rejected
    whatever the rest of it (its merit is the model's own objective, and the terms left only add
    to it), so the adaptive solver need not integrate the rest (a long step into fast dynamics).
    None where every trial is taken (a damping that does not filter), the trial's weights are not
    the iterate's (a ``sigma(p)`` function), or :data:`~torchql.engine_evaluate.STOP_EARLY` is off."""
    spec = engine.spec
    if not spec.damping.filters or spec.sigma_function is not None or not engine_evaluate.STOP_EARLY:
        return None
    return engine._exceeds(act, _pick(cur["w"], act), _pick(cur["log"], act), bound_of(_pick(cur["merit"], act)))


_REGISTRY = Registry(Scheme, "torchql.schemes.Scheme", "an iteration scheme")


def register_scheme(scheme: Scheme) -> Scheme:
    """Register ``scheme`` under its :attr:`~Scheme.name` (replacing one of that name); returns it."""
    return _REGISTRY.register(scheme)


register_scheme(Kantorovich())
register_scheme(Shooting())

#: The registered scheme names.
METHODS: tuple[str, ...] = _REGISTRY.names


def scheme_strategy(method) -> Scheme:
    """The scheme ``method`` names, or ``method`` itself when it is a :class:`Scheme`;
    ``TypeError``/``ValueError`` naming the registered ones otherwise."""
    found = _REGISTRY.find(method)
    if found is not None:
        return found
    if not isinstance(method, str):
        raise TypeError(f"`method` must be a string, one of {_REGISTRY.names}, or a {_REGISTRY.public_name}; "
                        f"received {type(method).__name__}")
    raise ValueError(f"`method` must be one of {_REGISTRY.names}; received {method!r}")
