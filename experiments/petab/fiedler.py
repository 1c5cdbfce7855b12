"""Fiedler et al. (2016), BMC Syst. Biol. 10:80: the RAF/MEK/ERK cascade under kinase inhibitors.

A three-tier phosphorylation cascade with negative feedback of phospho-ERK on RAF activation, pulsed by
a stimulus at ``t = 0``. Three experiments: control (``model1_data1``), the RAF inhibitor Sorafenib at
dose 5 (``model1_data2``) and the MEK inhibitor UO126 at dose 30 (``model1_data3``); the inhibitors are
inputs switched per condition. Concentrations relative to the totals
(``RAF_total = MEK_total = ERK_total = 1``), times 0-10.

Every experiment starts from the steady state of the unstimulated, uninhibited cascade. pMEK and pERK
are measured by Western blots on four gels (two dates, two gels each): each gel has its own scaling
``s_<observable>_<date>_<gel>``, and the noise is proportional to it, ``sigma = s * sigma_<observable>``.
"""

from __future__ import annotations

import torch

import torchql

from .spec import ProblemSpec

__all__ = ["FiedlerMAPK", "SPEC", "steady_state"]


class FiedlerMAPK(torchql.ODEModel):
    """RAF -> MEK -> ERK activation with ERK feedback, a transient stimulus and two inhibitors.

    ``u(t) = k10 + k11 (1 - exp(-t / tau1)) exp(-t / tau2)`` is the stimulus: the basal activation
    ``k10`` plus a pulse rising with ``tau1`` and decaying with ``tau2``. The reactions::

        RAF -> pRAF   rate u(t) RAF K_1 / (K_1 + pERK)         pRAF -> RAF   rate k2 pRAF
        MEK -> pMEK   rate k3 pRAF MEK K_2 / (K_2 + Sorafenib)   pMEK -> MEK   rate k4 pMEK
        ERK -> pERK   rate k5 pMEK ERK K_3 / (K_3 + UO126)       pERK -> ERK   rate k6 pERK

    States ``(RAF, pRAF, MEK, pMEK, ERK, pERK)``, relative concentrations; rate constants in 1/time;
    ``K_1`` (feedback) in concentration units, ``K_2`` and ``K_3`` in the units of the inhibitor inputs
    ``Sorafenib`` and ``UO126``, which are constants (set per condition). The model's one compartment
    (``cyt = 1``) holds every species, so its volume does not enter. Defaults: the SBML model's values.
    """

    state_names = ("RAF", "pRAF", "MEK", "pMEK", "ERK", "pERK")
    constants = ("Sorafenib", "UO126")

    def __init__(self, K_1: float = 1.00341445073941e-05, K_2: float = 1.51138632474898, K_3: float = 0.961738099369118,
                 k10: float = 0.0233013569106142, k11: float = 149.597826906266, k2: float = 1.22516651895562,
                 k3: float = 869.31180702032, k4: float = 2.90831656859387, k5: float = 578.350366636763,
                 k6: float = 3.61401250365661, tau1: float = 0.251674841461275, tau2: float = 0.0210740597705876,
                 Sorafenib: float = 0.0, UO126: float = 0.0) -> None:
        super().__init__()
        values = dict(K_1=K_1, K_2=K_2, K_3=K_3, k10=k10, k11=k11, k2=k2, k3=k3, k4=k4, k5=k5, k6=k6, tau1=tau1,
                      tau2=tau2, Sorafenib=Sorafenib, UO126=UO126)
        for name, value in values.items():
            self.register_buffer(name, torch.as_tensor(value, dtype=torch.float64).clone())

    def stimulus(self, t: torch.Tensor) -> torch.Tensor:
        """``u(t)`` (1/time), shape of ``t``."""
        return self.k10 + self.k11 * (1 - torch.exp(-t / self.tau1)) * torch.exp(-t / self.tau2)

    def forward(self, t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        RAF, pRAF, MEK, pMEK, ERK, pERK = x.unbind(-1)
        raf = self.stimulus(t) * RAF * self.K_1 / (self.K_1 + pERK) - self.k2 * pRAF
        mek = self.k3 * pRAF * MEK * self.K_2 / (self.K_2 + self.Sorafenib) - self.k4 * pMEK
        erk = self.k5 * pMEK * ERK * self.K_3 / (self.K_3 + self.UO126) - self.k6 * pERK
        return torch.stack((-raf, raf, -mek, mek, -erk, erk), dim=-1)


def steady_state(s):
    """The cascade's steady state under the basal stimulus ``k10``, without inhibitors, (6,).

    With ``p = pRAF`` and the totals ``R, M, E``: MEK and ERK balance at ``pMEK = M k3 p / (k4 + k3 p)``
    and ``pERK = alpha p / (beta + gamma p)`` (``alpha = E M k3 k5``, ``beta = k4 k6``,
    ``gamma = k3 (k6 + M k5)``); RAF balances at ``p (K_1 + a + pERK) = R a`` with ``a = K_1 k10 / k2``.
    Together a quadratic ``A p^2 + B p - C = 0`` with ``A, C > 0``, whose one positive root is taken in
    the form free of cancellation.
    """
    R, M, E = s["RAF_total"], s["MEK_total"], s["ERK_total"]
    k3, k4, k5, k6 = s["k3"], s["k4"], s["k5"], s["k6"]
    a = s["K_1"] * s["k10"] / s["k2"]
    alpha, beta, gamma = E * M * k3 * k5, k4 * k6, k3 * (k6 + M * k5)
    A = gamma * (s["K_1"] + a) + alpha
    B = (s["K_1"] + a) * beta - R * a * gamma
    C = R * a * beta
    root = torch.sqrt(B * B + 4 * A * C)
    pRAF = torch.where(B > 0, 2 * C / (B + root), (root - B) / (2 * A))
    pMEK = M * k3 * pRAF / (k4 + k3 * pRAF)
    pERK = alpha * pRAF / (beta + gamma * pRAF)
    return torch.stack((R - pRAF, pRAF, M - pMEK, pMEK, E - pERK, pERK))


def p_erk(x, s, p):
    """Phospho-ERK on the row's gel: ``observableParameter1 * pERK``."""
    return p[0] * x["pERK"]


def p_mek(x, s, p):
    """Phospho-MEK on the row's gel: ``observableParameter1 * pMEK``."""
    return p[0] * x["pMEK"]


def scaled_noise(x, s, p):
    """``sigma = noiseParameter1 * noiseParameter2``: the gel's scaling times the relative noise."""
    return p[0] * p[1]


SPEC = ProblemSpec(
    name="Fiedler_BMCSystBiol2016",
    model=FiedlerMAPK,
    initial_state=steady_state,
    observables={"pErk": p_erk, "pMek": p_mek},
    noise={"pErk": scaled_noise, "pMek": scaled_noise},
    unused_symbols=("cyt",),
    solver="dopri5",
    rtol=1e-8,
    atol=1e-10,
)
