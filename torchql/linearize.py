"""Linearization of the augmented right-hand side: ``A_n = df/dz`` and ``B_n = f - A_n z_n``.

Over a grid of times the linearization is one :func:`torch.func.vmap` call: a whole iteration's
linearization costs a single batched evaluation of the model's derivatives. The same call
carries a forward-mode tangent along the trajectory (:func:`torch.func.jvp`), which gives the
time derivatives of ``f`` and of ``A`` at the nodes for the cubic Hermite interpolation between
them. ``d/dt A`` is the Jacobian of that tangent ``f_t + A z'`` in ``z`` (``z'`` held fixed).

Three ways of differentiating give the same values (to rounding), at different costs:

* **torch.autograd** through the vmapped model: a node's outputs depend on its own inputs only,
  so one backward pass of a state's output summed over all the nodes gives that row of every
  node's ``A`` (and ``f_t``), and a second (a Hessian-vector product) the row of ``d/dt A``:
  ``2 n`` passes, each one C++ kernel per model operation, whatever the grid size. The fastest
  for few states: on 41 to 2e4 nodes of 1- to 4-state models it takes 0.4 to 0.75 of the time of
  reverse over forward and no more than forward over forward; with 8 states (HIRES) it takes
  twice reverse mode's time on small grids.
* **reverse over forward** (:func:`torch.func.jacrev` of the tangent): torch runs each model
  operation as one kernel; the backward pass costs about ``2 M`` vector products per node.
  On small grids: on 50 to 1,000 nodes of 3- to 6-component models it takes 0.4 to 0.6 of the
  time of forward over forward.
* **forward over forward** (:func:`torch.func.jvp` of :func:`torch.func.jacfwd`): nested
  forward mode makes torch run each elementwise model operation through a Python reference
  implementation (about 0.1 ms each, whatever the grid size), but the arithmetic is ``M``
  forward passes per node. On large grids (batches of samples) of larger models: 0.31 to 0.35 of
  the time of reverse over forward on ``10^5`` nodes.

:func:`linearize` takes autograd for models of at most :data:`AUTOGRAD_STATES` states; for
larger ones reverse over forward while ``nodes * M**2`` is at most :data:`REVERSE_WORK_LIMIT`,
forward over forward above. :func:`node_jacobian` gives other per-node Jacobians (the grid
solver's, the data start's) the same way.
"""

from __future__ import annotations

import functools
import warnings
from typing import NamedTuple

import torch
from torch.func import jacfwd, jacrev, jvp, vmap

from .model import AugmentedSystem

__all__ = ["Linearization", "SecondLinearization", "map_fields", "linearize", "node_jacobian", "flow_rates",
           "load_forward_mode", "REVERSE_WORK_LIMIT", "AUTOGRAD_STATES"]


@functools.cache
def load_forward_mode() -> None:
    """Load torch's forward-mode decompositions, once, as its first ``jvp`` would (a problem's
    set-up calls this before its first linearization). torch 2.13 scripts them with
    ``torch.jit.script``, which warns that it is deprecated: torch's own warning, which under
    ``-W error`` (a test suite's ``filterwarnings = error``) failed a user's first fit as a model
    that cannot be differentiated."""
    load = getattr(torch.autograd.forward_ad, "_maybe_load_decompositions", None)
    if load is not None:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=r"`torch\.jit\.", category=DeprecationWarning)
            load()


#: Largest ``nodes * M**2`` linearized in reverse over forward mode (see the module docstring).
#: Measured crossovers: 7e4 to 1.5e5 on 3- to 6-component nonlinear models, below 6.4e4 on a
#: 16-component linear one (few operations, so little Python-kernel overhead to save).
REVERSE_WORK_LIMIT = 16_384
#: Most model states linearized by torch.autograd (see the module docstring): its cost grows with
#: the states (two backward passes each), the others' with the augmented dimension.
AUTOGRAD_STATES = 4


class Linearization(NamedTuple):
    """The augmented right-hand side and its derivatives along a trajectory, at its nodes.

    Attributes
    ----------
    f : Tensor ``(G, M)``
        ``f(t_j, z_j)``.
    jac : Tensor ``(G, M, M)``
        ``A_j = df/dz (t_j, z_j)``.
    f_dot : Tensor ``(G, M)``
        ``d/dt f(t, z(t))`` at the nodes: ``A_j z'_j + df/dt``.
    jac_dot : Tensor ``(G, M, M)``
        ``d/dt A(t, z(t))`` at the nodes.
    """

    f: torch.Tensor
    jac: torch.Tensor
    f_dot: torch.Tensor
    jac_dot: torch.Tensor


class SecondLinearization(NamedTuple):
    """A :class:`Linearization` with the second time derivative of ``A`` (``linearize(...,
    second=True)``, for the quintic interpolant of ``h A``, :mod:`torchql.propagators.quintic`).

    Attributes
    ----------
    f, jac, f_dot, jac_dot
        As :class:`Linearization`'s.
    jac_ddot : Tensor ``(G, M, M)``
        ``d^2/dt^2 A(t, z(t))`` at the nodes, with ``z'' = f'``.
    """

    f: torch.Tensor
    jac: torch.Tensor
    f_dot: torch.Tensor
    jac_dot: torch.Tensor
    jac_ddot: torch.Tensor


def map_fields(lin, fn):
    """``lin`` (a :class:`Linearization` or :class:`SecondLinearization`) with ``fn`` applied to every field."""
    return type(lin)(*(fn(v) for v in lin))


def linearize(system: AugmentedSystem, t: torch.Tensor, z: torch.Tensor,
              z_dot: torch.Tensor | None = None, order: str | None = None, second: bool = False) -> Linearization:
    """Linearize ``f`` along a trajectory given at nodes ``(t_j, z_j)`` with slopes ``z'_j``.

    Parameters
    ----------
    system : AugmentedSystem
    t : Tensor ``(G,)``
        Times.
    z : Tensor ``(G, M)``
        Augmented states.
    z_dot : Tensor ``(G, M)``, optional
        Slopes of the trajectory; default ``f(t_j, z_j)`` (a solution of the model).
    order : {"autograd", "reverse", "forward"}, optional
        ``"autograd"``, ``"reverse"`` (reverse over forward) or ``"forward"`` (forward over
        forward); default by :data:`AUTOGRAD_STATES` and :data:`REVERSE_WORK_LIMIT`, among
        ``system.linearization_orders``, the ways torch can take on the model as far as known:
        reverse mode stands in where autograd (a backward without a derivative) or forward mode
        (an operation without a forward-mode derivative) fails, and the failed way is not tried
        again (:class:`~torchql.problem.Problem` linearizes one node so before a fit, to name a
        model that no way takes). All give the same values to rounding.

    second : bool
        Also ``jac_ddot``, the second time derivative of ``A`` along the trajectory (one more
        backward pass per state by autograd; a second forward-mode tangent otherwise).

    Returns
    -------
    Linearization
    """
    if z_dot is None:
        z_dot = vmap(system.f)(t, z)
    lin = _linearize_first(system, t, z, z_dot, order, second)
    if second and not isinstance(lin, SecondLinearization):
        try:
            lin = SecondLinearization(*lin, _second_by_jets(system.f, t, z, z_dot, lin.f_dot))
        except Exception as exc:  # noqa: BLE001 -- an operation without a forward-mode derivative
            raise ValueError("the quintic interpolant of `h A` (linear_solver=\"taylor_quintic\") needs the "
                             "second time derivative of the model's Jacobian, which torch could not take through "
                             f"this model ({type(exc).__name__}: {exc}); use linear_solver=\"taylor\"") from exc
    return lin


def _linearize_first(system: AugmentedSystem, t, z, z_dot, order: str | None, second: bool) -> Linearization:
    """:func:`linearize` in the order chosen (``second``: autograd gives ``jac_ddot`` in its passes)."""
    if order is None:
        if system.n <= AUTOGRAD_STATES and "autograd" in system.linearization_orders:
            try:
                return _linearize("autograd", system.f, t, z, z_dot, system.n, second)
            except Exception:  # noqa: BLE001 -- the model's forward does not take double backward
                system.linearization_orders = tuple(o for o in system.linearization_orders if o != "autograd")
        order = "reverse" if t.shape[0] * system.M**2 <= REVERSE_WORK_LIMIT else "forward"
        if order not in system.linearization_orders:
            order = "reverse"
        if order == "forward":
            try:
                return _linearize(order, system.f, t, z, z_dot, system.n)
            except Exception:  # noqa: BLE001 -- the model's forward does not take nested forward mode
                system.linearization_orders = ("reverse",)
                order = "reverse"
    return _linearize(order, system.f, t, z, z_dot, system.n, second)


def _linearize(order: str, f, t, z, z_dot, n: int, second: bool = False) -> Linearization:
    """The linearization in ``order`` (``"autograd"``, ``"reverse"`` or ``"forward"``) at every node;
    ``n``: the model's states (the rows autograd differentiates); ``second``: autograd's with ``jac_ddot``."""
    if order == "autograd":
        return _by_autograd(f, t, z, z_dot, n, second=True) if second else _by_autograd(f, t, z, z_dot, n)
    if order == "reverse":
        value, jac, value_dot, jac_dot = vmap(_reverse_over_forward(f))(t, z, z_dot)
    else:
        (value, jac), (value_dot, jac_dot) = vmap(_forward_over_forward(f))(t, z, z_dot)
    return Linearization(f=value, jac=jac, f_dot=value_dot, jac_dot=jac_dot)


def _reverse_over_forward(f):
    """``(t, z, z') -> (f, A, f_t + A z', d/dt A)`` at one node: ``jacrev`` of the tangent."""

    def node(ti, zi, zdi):
        def value_and_tangent(zz):
            both = jvp(f, (ti, zz), (torch.ones_like(ti), zdi))
            return both, both

        (jac, jac_dot), (value, value_dot) = jacrev(value_and_tangent, has_aux=True)(zi)
        return value, jac, value_dot, jac_dot

    return node


def _forward_over_forward(f):
    """``(t, z, z') -> ((f, A), (f_t + A z', d/dt A))`` at one node: ``jvp`` of ``jacfwd``."""

    def value_and_jacobian(ti, zi):
        return f(ti, zi), jacfwd(f, argnums=1)(ti, zi)

    def node(ti, zi, zdi):
        return jvp(value_and_jacobian, (ti, zi), (torch.ones_like(ti), zdi))

    return node


def _by_autograd(f, t: torch.Tensor, z: torch.Tensor, z_dot: torch.Tensor, n: int, second: bool = False
                 ) -> Linearization:
    """The linearization by torch.autograd through the model vmapped over the nodes: ``2 n`` backward
    passes over the whole grid at once (a node's outputs depend on its own inputs only, so the
    gradient of an output summed over the nodes is, at each node, that node's derivative).

    For each state ``i < n``: ``g = d f_i / d(z, t)`` with a graph (row ``i`` of ``A`` and ``f_t``),
    then ``d/dt A_i = d/dz (g_z . z' + g_t)``, a Hessian-vector product. The coefficients' rows are
    zero (``p' = 0``). With ``second``, ``n`` passes more: ``d^2/dt^2 A_i = d/dz (h . z' + g_z . z'' +
    d/dt (g_z . z' + g_t))`` with ``h = d/dz (g_z . z' + g_t)`` and ``z'' = f'`` (``z'`` and ``z''``
    held fixed: the third derivatives of ``f`` contracted twice with the tangent, the second ones
    once with ``z''``, and the explicit time terms).
    """
    G, M = z.shape
    jac = torch.zeros(G, M, M, dtype=z.dtype, device=z.device)
    jac_dot = torch.zeros_like(jac)
    jac_ddot = torch.zeros_like(jac) if second else None
    value_dot = torch.zeros_like(z)
    with torch.enable_grad():
        tt = t.detach().requires_grad_()
        zz = z.detach().requires_grad_()
        value = vmap(f)(tt, zz)
        rows = []
        for i in range(n):
            g_z, g_t = torch.autograd.grad(value[:, i].sum(), (zz, tt), create_graph=True, allow_unused=True)
            if g_z is None:
                continue  # f_i constant (its rows stay zero)
            tangent = (g_z * z_dot).sum(dim=1) + (g_t if g_t is not None else 0.0)
            jac[:, i] = g_z.detach()
            value_dot[:, i] = tangent.detach()
            rows.append((i, g_z, tangent))
        for k, (i, g_z, tangent) in enumerate(rows):
            if not tangent.requires_grad:
                continue
            last = k == len(rows) - 1
            wrt = (zz, tt) if second else (zz,)
            h, *h_t = torch.autograd.grad(tangent.sum(), wrt, create_graph=second, retain_graph=second or not last,
                                          allow_unused=True)
            if h is None:
                continue
            jac_dot[:, i] = h.detach()
            if second:
                twice = (h * z_dot).sum(dim=1) + (g_z * value_dot).sum(dim=1)
                if h_t and h_t[0] is not None:
                    twice = twice + h_t[0]
                if twice.requires_grad:
                    (h2,) = torch.autograd.grad(twice.sum(), zz, retain_graph=not last, allow_unused=True)
                    if h2 is not None:
                        jac_ddot[:, i] = h2
    if second:
        return SecondLinearization(value.detach(), jac, value_dot, jac_dot, jac_ddot)
    return Linearization(f=value.detach(), jac=jac, f_dot=value_dot, jac_dot=jac_dot)


def _second_by_jets(f, t: torch.Tensor, z: torch.Tensor, z_dot: torch.Tensor, z_ddot: torch.Tensor) -> torch.Tensor:
    """``d^2/dt^2 A (G, M, M)`` along the trajectory through the nodes ``(t, z)`` with slopes ``z_dot``
    and second derivatives ``z_ddot``: the second derivative in ``tau`` at 0 of ``A(t + tau, z +
    tau z' + tau^2 z'' / 2)``, by nested forward mode over ``jacrev`` (the way for the models
    autograd does not take)."""

    def node(ti, zi, zdi, zddi):
        one, zero = torch.ones_like(ti), torch.zeros_like(ti)

        def jacobian(tt, zz):
            return jacrev(f, argnums=1)(tt, zz)

        def along(tt, zz, dt, dz):
            return jvp(jacobian, (tt, zz), (dt, dz))[1]

        curvature = jvp(lambda tt, zz: along(tt, zz, one, zdi), (ti, zi), (one, zdi))[1]
        return curvature + along(ti, zi, zero, zddi)

    return vmap(node)(t, z, z_dot, z_ddot)


def node_jacobian(f, args: tuple, wrt: tuple[int, ...], rows: int, vectorize: bool = True,
                  replicate: bool = False, batched=None) -> tuple[torch.Tensor, tuple]:
    """A per-node function over many nodes, with the Jacobians of its first ``rows`` outputs.

    Up to :data:`AUTOGRAD_STATES` rows by torch.autograd through ``vmap(f)``: one backward pass
    per row over all the nodes at once (node ``j``'s outputs depend on row ``j`` of the arguments
    only, so the gradient of an output summed over the nodes is, at each node, that node's
    derivative); more by :func:`torch.func.jacrev` under :func:`torch.func.vmap`, which also stands
    in where autograd fails.

    Parameters
    ----------
    f : callable
        One node's function: ``f(*node_args) -> (K,)``.
    args : tuple of Tensor
        Its arguments over ``N`` nodes, each with the nodes first: ``(N,)`` or ``(N, D)``.
    wrt : tuple of int
        The arguments to differentiate in.
    rows : int
        The Jacobians' rows: those of the first ``rows`` outputs.
    vectorize : bool
        ``False``: one node (``N = 1``), ``f`` called on it directly, without :func:`torch.func.vmap`
        (which spares its overhead and allows Python control flow on tensor values in ``f``).
    replicate : bool
        With ``vectorize``: one backward pass through ``rows`` copies of every node (copy ``i``
        seeded with output ``i``) instead of ``rows`` passes. The forward work is ``rows`` times
        larger, the operations fewer: the better choice where the nodes are few and each call's
        overhead dominates (the implicit solver's Jacobian at the current point of ``S`` samples).
    batched : callable, optional
        ``f`` over all the nodes at once, in place of ``vmap(f)`` (a model that takes a batch of
        states itself), for the backward passes.

    Returns
    -------
    value : Tensor ``(N, K)``
    jacobians : tuple of Tensor, one per ``wrt``: ``(N, rows, *arg.shape[1:])``.
    """
    if rows <= AUTOGRAD_STATES:
        batched_f = ((batched or vmap(f)) if vectorize
                     else (lambda *one: f(*(a[0] for a in one)).unsqueeze(0)))
        try:
            if replicate and vectorize:
                return _node_jacobian_by_copies(batched_f, args, wrt, rows)
            return _node_jacobian_by_autograd(batched_f, args, wrt, rows)
        except Exception:  # noqa: BLE001 -- functorch's error (or the same one) comes below
            pass

    def first_rows(*node_args):
        value = f(*node_args)
        return value[:rows], value

    derivatives = jacrev(first_rows, argnums=wrt, has_aux=True)
    if vectorize:
        jacobians, value = vmap(derivatives)(*args)
        return value, tuple(jacobians)
    jacobians, value = derivatives(*(a[0] for a in args))
    return value.unsqueeze(0), tuple(j.unsqueeze(0) for j in jacobians)


def flow_rates(f, t: torch.Tensor, z: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The slopes ``f (N, M)`` at the nodes ``(t (N,), z (N, M))`` and the rates of change of the first
    ``n`` of them along the model's flow, ``d/dt f = f_t + A f (N, n)``, from the states' rows of the
    Jacobian (:func:`node_jacobian`: by autograd for a small model, as the engine linearizes it)."""
    slopes, (f_t, f_z) = node_jacobian(f, (t, z), (0, 1), n)
    slopes, f_t, f_z = slopes.detach(), f_t.detach(), f_z.detach()
    return slopes, f_t + (f_z @ slopes.unsqueeze(-1)).squeeze(-1)


def _node_jacobian_by_autograd(batched_f, args, wrt, rows):
    """:func:`node_jacobian` by ``rows`` backward passes through ``batched_f``, each seeded with one
    output row at every node."""
    with torch.enable_grad():
        inputs = [a.detach().requires_grad_() if k in wrt else a for k, a in enumerate(args)]
        value = batched_f(*inputs)
        targets = [inputs[k] for k in wrt]
        columns: list[list] = [[] for _ in targets]
        if value.requires_grad:  # (an output free of them: zero Jacobians)
            seeds = torch.zeros(rows, *value.shape, dtype=value.dtype, device=value.device)
            seeds.diagonal(dim1=0, dim2=2).fill_(1.0)  # seeds[i] selects output row i at every node
            for i in range(rows):
                grads = torch.autograd.grad(value, targets, grad_outputs=seeds[i], retain_graph=i < rows - 1,
                                            allow_unused=True)
                for column, g, a in zip(columns, grads, targets):
                    column.append(torch.zeros_like(a) if g is None else g)
        jacobians = tuple(torch.stack(column, dim=1) if column else
                          torch.zeros(value.shape[0], rows, *a.shape[1:], dtype=a.dtype, device=a.device)
                          for column, a in zip(columns, targets))
    return value.detach(), jacobians


def _node_jacobian_by_copies(batched_f, args, wrt, rows):
    """:func:`node_jacobian` by one backward pass through ``rows`` copies of every node."""
    N = args[0].shape[0]
    with torch.enable_grad():
        inputs = [a.detach().repeat_interleave(rows, dim=0) for a in args]
        inputs = [a.requires_grad_() if k in wrt else a for k, a in enumerate(inputs)]
        value = batched_f(*inputs)  # (N rows, K): copy i of node j in row j rows + i
        targets = [inputs[k] for k in wrt]
        grads = [None] * len(targets)
        if value.requires_grad:  # (an output free of them: zero Jacobians)
            seeds = torch.eye(rows, value.shape[1], dtype=value.dtype, device=value.device).repeat(N, 1)
            grads = torch.autograd.grad(value, targets, grad_outputs=seeds, allow_unused=True)
    # (autograd may hand back an expanded gradient, which later in-place updates must not receive)
    jacobians = tuple((torch.zeros_like(a) if g is None else g.contiguous()).view(N, rows, *a.shape[1:])
                      for g, a in zip(grads, targets))
    return value.detach().view(N, rows, -1)[:, 0], jacobians
