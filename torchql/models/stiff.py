"""Stiff models: Robertson's chemistry, van der Pol's relaxation oscillator, HIRES, enzyme kinetics.

Their fast and slow time scales differ by many orders of magnitude, so explicit solvers
(``"dop853"``, ``"dopri5"``) take steps of the fastest scale over the whole interval. The default
``solver="auto"`` of :func:`torchql.simulate` and :func:`torchql.fit` finds them stiff and integrates
them by ``"rodas5p"`` (:mod:`torchql.solvers`), which may also be asked for by name. Reference solutions: the Test Set for IVP Solvers,
F. Mazzia and C. Magherini, release 2.4 (2008), University of Bari
(https://archimede.uniba.it/~testset/), problems ROBER and HIRES.
"""

from __future__ import annotations

import torch

from ..model import ODEModel

__all__ = ["Robertson", "VanDerPol", "HIRES", "MichaelisMentenEnzyme", "ROBERTSON_REFERENCE_1E11", "HIRES_REFERENCE"]


def _register(module: ODEModel, values: dict[str, float]) -> None:
    for name, value in values.items():
        module.register_buffer(name, torch.tensor(float(value), dtype=torch.float64))


class Robertson(ODEModel):
    """Robertson's autocatalytic reactions (1966), the classic stiff chemistry problem.

    ``A -k1-> B``, ``B + B -k2-> C + B``, ``B + C -k3-> A + C``:

    ``y1' = -k1 y1 + k3 y2 y3``, ``y2' = k1 y1 - k3 y2 y3 - k2 y2^2``, ``y3' = k2 y2^2``.

    States ``(y1, y2, y3)``: concentrations (dimensionless; ``y1 + y2 + y3`` is conserved).
    Rate constants ``k1 = 0.04`` (1/time), ``k2 = 3e7`` and ``k3 = 1e4`` (1/(concentration time)).
    The standard start is ``(1, 0, 0)`` at ``t = 0``; ``y2`` rises to a peak of about ``3.65e-5``
    near ``t = 4.5e-3`` (``2.9e-5`` at ``1e-3``) and then decays slowly over ``t`` up to ``1e11`` (the IVP test set's ROBER interval).
    Eigenvalues of the Jacobian reach ``-1e4`` and beyond: explicit solvers are impractical.
    """

    state_names = ("y1", "y2", "y3")

    def __init__(self, k1: float = 0.04, k2: float = 3e7, k3: float = 1e4) -> None:
        super().__init__()
        _register(self, {"k1": k1, "k2": k2, "k3": k3})

    def forward(self, t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        y1, y2, y3 = x.unbind(-1)
        r1, r2, r3 = self.k1 * y1, self.k2 * y2 * y2, self.k3 * y2 * y3
        return torch.stack((-r1 + r3, r1 - r3 - r2, r2), dim=-1)


class VanDerPol(ODEModel):
    """Van der Pol's oscillator ``y'' - mu (1 - y^2) y' + y = 0`` in first-order form.

    States ``(y, v = y')``: ``y' = v``, ``v' = mu (1 - y^2) v - y`` (dimensionless). For large
    ``mu`` (default 1000) the limit cycle alternates slow drifts along ``|y|`` from 2 to 1,
    lasting about ``(3/2 - ln 2) mu ~ 807`` time units each at ``mu = 1000`` (the period is
    ``(3 - 2 ln 2) mu ~ 1614``; from ``(2, 0)`` the first jump comes at ``t = 807``), with jumps of
    duration ``O(mu^(-1/3))``: a standard stiff test (Hairer and Wanner, *Solving ODEs II*, IV.1).
    The usual start is ``(2, 0)``.
    """

    state_names = ("y", "v")

    def __init__(self, mu: float = 1000.0) -> None:
        super().__init__()
        _register(self, {"mu": mu})

    def forward(self, t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        y, v = x.unbind(-1)
        return torch.stack((v, self.mu * (1 - y * y) * v - y), dim=-1)


class HIRES(ODEModel):
    """HIRES: the High Irradiance RESponse of photomorphogenesis (Schäfer 1975), 8 states.

    The IVP test set's problem HIRES (Hairer and Wanner, *Solving ODEs II*, IV.10), with its rate
    constants ``k1 .. k9`` (1/time; ``k7`` in 1/(concentration time)) and the source term ``oks``
    (concentration/time)::

        y1' = -k1 y1 + k2 y2 + k6 y3 + oks
        y2' =  k1 y1 - (k2 + k3) y2
        y3' = -(k6 + k1) y3 + k2 y4 + k5 y5
        y4' =  k3 y2 + k1 y3 - (k4 + k2) y4
        y5' = -(k5 + k1) y5 + k2 (y6 + y7)
        y6' = -k7 y6 y8 + k8 y4 + k1 y5 - k2 y6 + k8 y7
        y7' =  k7 y6 y8 - (k2 + k8 + k9) y7
        y8' = -k7 y6 y8 + (k2 + k8 + k9) y7

    Defaults: ``k = (1.71, 0.43, 8.32, 0.69, 0.035, 8.32, 280, 0.69, 0.69)``, ``oks = 0.0007``.
    The standard start is ``(1, 0, 0, 0, 0, 0, 0, 0.0057)`` at ``t = 0``, integrated to
    ``t = 321.8122``; the test set publishes the solution there (see :data:`HIRES_REFERENCE`).
    """

    state_names = ("y1", "y2", "y3", "y4", "y5", "y6", "y7", "y8")

    def __init__(self, k1: float = 1.71, k2: float = 0.43, k3: float = 8.32, k4: float = 0.69, k5: float = 0.035,
                 k6: float = 8.32, k7: float = 280.0, k8: float = 0.69, k9: float = 0.69, oks: float = 0.0007) -> None:
        super().__init__()
        _register(self, {"k1": k1, "k2": k2, "k3": k3, "k4": k4, "k5": k5, "k6": k6, "k7": k7, "k8": k8, "k9": k9,
                         "oks": oks})

    def forward(self, t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        y1, y2, y3, y4, y5, y6, y7, y8 = x.unbind(-1)
        k1, k2, k3, k4, k5, k6, k7, k8, k9 = (self.k1, self.k2, self.k3, self.k4, self.k5, self.k6, self.k7,
                                              self.k8, self.k9)
        binding = k7 * y6 * y8
        release = (k2 + k8 + k9) * y7
        return torch.stack((
            -k1 * y1 + k2 * y2 + k6 * y3 + self.oks,
            k1 * y1 - (k2 + k3) * y2,
            -(k6 + k1) * y3 + k2 * y4 + k5 * y5,
            k3 * y2 + k1 * y3 - (k4 + k2) * y4,
            -(k5 + k1) * y5 + k2 * (y6 + y7),
            -binding + k8 * y4 + k1 * y5 - k2 * y6 + k8 * y7,
            binding - release,
            -binding + release,
        ), dim=-1)


class MichaelisMentenEnzyme(ODEModel):
    """Enzyme kinetics by mass action, ``E + S <-> C -> E + P``, with fast binding.

    ``S' = -kf E S + kr C``, ``E' = -kf E S + (kr + kcat) C``, ``C' = kf E S - (kr + kcat) C``,
    ``P' = kcat C``. States ``(S, E, C, P)``: concentrations of substrate, free enzyme, complex and
    product (µM; ``E + C`` and ``S + C + P`` are conserved). Rate constants ``kf`` (1/(µM s)),
    ``kr`` and ``kcat`` (1/s). The defaults ``kf = 1e3``, ``kr = 1e3``, ``kcat = 1`` give
    ``K_M = (kr + kcat) / kf ~ 1`` µM and binding a thousand times faster than turnover: from
    ``(S, E, C, P) = (10, 1, 0, 0)`` the complex approaches its quasi-steady state with a time
    constant of about ``1e-4`` s (within a few percent by ``5e-4`` s), then the substrate is converted over about 20 s (the regime where the
    Michaelis–Menten rate law ``P' = kcat E_T S / (K_M + S)`` holds; Segel and Slemrod, SIAM Rev.
    31 (1989)). The fast binding makes the system stiff (eigenvalue ``~ -kf (E + S + K_M)``).
    """

    state_names = ("S", "E", "C", "P")

    def __init__(self, kf: float = 1e3, kr: float = 1e3, kcat: float = 1.0) -> None:
        super().__init__()
        _register(self, {"kf": kf, "kr": kr, "kcat": kcat})

    def forward(self, t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        S, E, C, _ = x.unbind(-1)
        binding, unbinding, turnover = self.kf * E * S, self.kr * C, self.kcat * C
        return torch.stack((-binding + unbinding, -binding + unbinding + turnover, binding - unbinding - turnover,
                            turnover), dim=-1)


#: The IVP test set's reference solution of ROBER at ``t = 1e11`` from ``(1, 0, 0)`` at 0.
ROBERTSON_REFERENCE_1E11 = (0.2083340149701255e-07, 0.8333360770334713e-13, 0.9999999791665050)
#: The IVP test set's reference solution of HIRES at ``t = 321.8122`` from its standard start.
HIRES_REFERENCE = (0.7371312573325668e-3, 0.1442485726316185e-3, 0.5888729740967575e-4, 0.1175651343283149e-2,
                   0.2386356198831331e-2, 0.6238968252742796e-2, 0.2849998395185769e-2, 0.2850001604814231e-2)
