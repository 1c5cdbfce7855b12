"""Boehm et al. (2014), J. Proteome Res. 13:5685: STAT5A/STAT5B dimerization and nuclear shuttling.

Erythropoietin (Epo) stimulation phosphorylates the transcription factors STAT5A and STAT5B, which
dimerize to three species (homodimers pApA, pBpB and the heterodimer pApB), are imported into the
nucleus and exported again as monomers. The Epo signal decays exponentially from ``t = 0``.
Time in minutes, 0-240; one experiment (condition ``model1_data1``).

The observables are the relative phosphorylation of STAT5A and STAT5B and the relative abundance of
STAT5A measured by mass spectrometry; ``specC17`` is the fraction of STAT5A among total STAT5.

The system is stiff: the homodimer import rate ``k_imp_homo ~ 1e5 /min`` against the 240 min horizon
(``experiments/petab_nllh.py`` prints the stiffness ratio along the nominal trajectory).
"""

from __future__ import annotations

import torch

import torchql

from .spec import ProblemSpec

__all__ = ["BoehmSTAT5", "SPEC"]

#: Total STAT5 (in the states' concentration units), split between STAT5A and STAT5B at ``t = 0`` as ``ratio``.
TOTAL_STAT5 = 207.6
#: The phosphorylation rate law's factor in front of ``k_phos`` (the SBML model's unit scaling).
PHOS_SCALE = 1.25e-7


class BoehmSTAT5(torchql.ODEModel):
    """Phosphorylation, dimerization and nuclear import/export of STAT5A and STAT5B.

    Cytoplasmic STAT5A (``A``) and STAT5B (``B``) dimerize upon phosphorylation at the Epo-driven rate
    ``e(t) = 1.25e-7 k_phos exp(-Epo_degradation_BaF3 t)``::

        A + A -> pApA   rate e(t) A^2        A + B -> pApB   rate e(t) A B        B + B -> pBpB   rate e(t) B^2

    The dimers are imported into the nucleus (first order, ``k_imp_homo`` for the homodimers,
    ``k_imp_hetero`` for the heterodimer) and exported back as two monomers (``k_exp_homo``,
    ``k_exp_hetero``). Rates are per cytoplasmic volume on import and per nuclear volume on export, so
    a species in the other compartment changes by the volume ratio (``cyt / nuc`` into the nucleus,
    ``nuc / cyt`` back): the states are concentrations in their own compartment.

    States ``(STAT5A, STAT5B, pApB, pApA, pBpB, nucpApA, nucpApB, nucpBpB)``; rate constants in 1/min
    (``k_phos`` scaled by 1.25e-7 to 1/(concentration min)); the compartment volumes ``cyt = 1.4`` and
    ``nuc = 0.45`` (only their ratio matters) are constants. Defaults: the SBML model's values.
    """

    state_names = ("STAT5A", "STAT5B", "pApB", "pApA", "pBpB", "nucpApA", "nucpApB", "nucpBpB")
    constants = ("cyt", "nuc")

    def __init__(self, Epo_degradation_BaF3: float = 0.0269738286367359, k_exp_hetero: float = 1.00094251286741e-05,
                 k_exp_homo: float = 0.00617193081581346, k_imp_hetero: float = 0.0163708512310568,
                 k_imp_homo: float = 96945.5391768823, k_phos: float = 15766.8336642826, cyt: float = 1.4,
                 nuc: float = 0.45) -> None:
        super().__init__()
        values = dict(Epo_degradation_BaF3=Epo_degradation_BaF3, k_exp_hetero=k_exp_hetero, k_exp_homo=k_exp_homo,
                      k_imp_hetero=k_imp_hetero, k_imp_homo=k_imp_homo, k_phos=k_phos, cyt=cyt, nuc=nuc)
        for name, value in values.items():
            self.register_buffer(name, torch.as_tensor(value, dtype=torch.float64).clone())

    def forward(self, t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        A, B, pApB, pApA, pBpB, nucpApA, nucpApB, nucpBpB = x.unbind(-1)
        epo = PHOS_SCALE * self.k_phos * torch.exp(-self.Epo_degradation_BaF3 * t)
        dimer_AA, dimer_AB, dimer_BB = epo * A * A, epo * A * B, epo * B * B
        import_AA, import_AB, import_BB = self.k_imp_homo * pApA, self.k_imp_hetero * pApB, self.k_imp_homo * pBpB
        export_AA, export_AB, export_BB = (self.k_exp_homo * nucpApA, self.k_exp_hetero * nucpApB,
                                           self.k_exp_homo * nucpBpB)
        to_nucleus, to_cytoplasm = self.cyt / self.nuc, self.nuc / self.cyt
        return torch.stack((
            -2 * dimer_AA - dimer_AB + to_cytoplasm * (2 * export_AA + export_AB),
            -dimer_AB - 2 * dimer_BB + to_cytoplasm * (export_AB + 2 * export_BB),
            dimer_AB - import_AB,
            dimer_AA - import_AA,
            dimer_BB - import_BB,
            to_nucleus * import_AA - export_AA,
            to_nucleus * import_AB - export_AB,
            to_nucleus * import_BB - export_BB,
        ), dim=-1)


def initial_state(s):
    """All STAT5 unphosphorylated and cytoplasmic, split ``ratio : 1 - ratio`` between A and B, (8,)."""
    a = TOTAL_STAT5 * s["ratio"]
    zero = torch.zeros_like(a)
    return torch.stack((a, TOTAL_STAT5 - a, zero, zero, zero, zero, zero, zero))


def p_stat5a_rel(x, s, p):
    """Phosphorylated STAT5A as a percentage of total STAT5A, from the peptides' signals (``specC17``
    is the fraction of STAT5A among the measured STAT5)."""
    c = s["specC17"]
    return 100 * (x["pApB"] + 2 * c * x["pApA"]) / (x["pApB"] + c * (x["STAT5A"] + 2 * x["pApA"]))


def p_stat5b_rel(x, s, p):
    """Phosphorylated STAT5B as a percentage of total STAT5B (``1 - specC17`` is the fraction of STAT5B)."""
    c = 1 - s["specC17"]
    return 100 * (x["pApB"] + 2 * c * x["pBpB"]) / (x["pApB"] + c * (x["STAT5B"] + 2 * x["pBpB"]))


def r_stat5a_rel(x, s, p):
    """STAT5A as a percentage of all STAT5 (monomers and the cytoplasmic dimers)."""
    a, b = s["specC17"], 1 - s["specC17"]
    stat5a = x["pApB"] + a * (x["STAT5A"] + 2 * x["pApA"])
    return 100 * stat5a / (stat5a + x["pApB"] + b * (x["STAT5B"] + 2 * x["pBpB"]))


def first_noise_parameter(x, s, p):
    """``sigma = noiseParameter1`` (the row's own standard deviation, here an estimated parameter)."""
    return p[0]


SPEC = ProblemSpec(
    name="Boehm_JProteomeRes2014",
    model=BoehmSTAT5,
    initial_state=initial_state,
    observables={"pSTAT5A_rel": p_stat5a_rel, "pSTAT5B_rel": p_stat5b_rel, "rSTAT5A_rel": r_stat5a_rel},
    noise={"pSTAT5A_rel": first_noise_parameter, "pSTAT5B_rel": first_noise_parameter,
           "rSTAT5A_rel": first_noise_parameter},
    solver="rodas5p",
    rtol=1e-8,
    atol=1e-10,
)
