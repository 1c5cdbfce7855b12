"""Bruno et al. (2016), J. Exp. Bot. 67:5993: carotenoid cleavage into apocarotenoids in vitro.

Six experiments (conditions ``model1_data1`` to ``model1_data6``) each start from one substrate: the
carotenoids beta-carotene (``bcar``), beta-cryptoxanthin (``bcry``) and zeaxanthin (``zea``), or the
cleavage products ``b10`` (beta-10') and ``ohb10`` (OH-beta-10'), and follow its cleavage into the
apocarotenoids (the SBML model's species names: beta-carotin, cry, zea, beta-10, OH-beta-10, beta-io,
OH-beta-io). Amounts in arbitrary units, time in minutes, over 0-180 min.

Each reaction rate is multiplied by a per-condition factor ``<rate>_multiplier``: 0 for a reaction
switched off in that experiment, 1, or the estimated ``szea`` in the experiments run at a different
enzyme activity (``model1_data3``, ``model1_data6``). The initial amount of the substrate of each
experiment is estimated (``init_b10_1``, ``init_bcar1``, ...); the other states start at 0.
"""

from __future__ import annotations

import torch

import torchql

from .spec import ProblemSpec

__all__ = ["BrunoCarotenoids", "SPEC"]

RATES = ("k5", "kb1", "kb2", "kc1", "kc2", "kc4")
MULTIPLIERS = tuple(f"{k}_multiplier" for k in RATES)
_DEFAULT_RATES = (0.00305007086506138, 0.0164169857330715, 0.00537146249584483, 0.00162720870139293,
                  0.00673060855967958, 0.00617966905040397)


class BrunoCarotenoids(torchql.ODEModel):
    """First-order cleavage network of carotenoids and apocarotenoids.

    With the effective rates ``r_k = k * k_multiplier`` (1/min)::

        bcar  -kb1-> b10 + bio       bcry -kc1-> b10 + ohbio       bcry -kc2-> bio + ohb10
        b10   -kb2-> bio             zea  -k5->  ohb10 + ohbio     ohb10 -kc4-> ohbio

    (every reaction of a carotenoid yields two cleavage products, counted once each). States
    ``(bcar, bcry, b10, bio, ohb10, ohbio, zea)``.
    The multipliers switch reactions on and off per experiment; they are constants. The model's one
    compartment (``cyt = 1``) holds every species, so its volume does not enter. Defaults: the SBML
    model's values.
    """

    state_names = ("bcar", "bcry", "b10", "bio", "ohb10", "ohbio", "zea")
    constants = MULTIPLIERS

    def __init__(self, k5: float = _DEFAULT_RATES[0], kb1: float = _DEFAULT_RATES[1], kb2: float = _DEFAULT_RATES[2],
                 kc1: float = _DEFAULT_RATES[3], kc2: float = _DEFAULT_RATES[4], kc4: float = _DEFAULT_RATES[5],
                 k5_multiplier: float = 0.521817105884857, kb1_multiplier: float = 0.521817105884857,
                 kb2_multiplier: float = 0.521817105884857, kc1_multiplier: float = 0.521817105884857,
                 kc2_multiplier: float = 0.521817105884857, kc4_multiplier: float = 0.521817105884857) -> None:
        super().__init__()
        values = dict(k5=k5, kb1=kb1, kb2=kb2, kc1=kc1, kc2=kc2, kc4=kc4, k5_multiplier=k5_multiplier,
                      kb1_multiplier=kb1_multiplier, kb2_multiplier=kb2_multiplier, kc1_multiplier=kc1_multiplier,
                      kc2_multiplier=kc2_multiplier, kc4_multiplier=kc4_multiplier)
        for name, value in values.items():
            self.register_buffer(name, torch.as_tensor(value, dtype=torch.float64).clone())

    def forward(self, t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        bcar, bcry, b10, _bio, ohb10, _ohbio, zea = x.unbind(-1)
        v_b1 = self.kb1 * self.kb1_multiplier * bcar
        v_b2 = self.kb2 * self.kb2_multiplier * b10
        v_c1 = self.kc1 * self.kc1_multiplier * bcry
        v_c2 = self.kc2 * self.kc2_multiplier * bcry
        v_c4 = self.kc4 * self.kc4_multiplier * ohb10
        v_5 = self.k5 * self.k5_multiplier * zea
        return torch.stack((
            -v_b1,
            -v_c1 - v_c2,
            v_b1 + v_c1 - v_b2,
            v_b1 + v_b2 + v_c2,
            v_c2 + v_5 - v_c4,
            v_c1 + v_5 + v_c4,
            -v_5,
        ), dim=-1)


def initial_state(s):
    """``x(0)`` from the condition's initial amounts ``init_<state>``; ``bio`` and ``ohbio`` start at 0."""
    zero = torch.zeros_like(s["init_bcar"])
    return torch.stack((s["init_bcar"], s["init_bcry"], s["init_b10"], zero, s["init_ohb10"], zero, s["init_zea"]))


def _state(name):
    def observe(x, s, p):
        return x[name]
    observe.__doc__ = f"The amount of ``{name}`` itself."
    return observe


def first_noise_parameter(x, s, p):
    """``sigma = noiseParameter1``: each row carries its own measured standard deviation."""
    return p[0]


_OBSERVED = {"ob10": "b10", "obcar": "bcar", "obcry": "bcry", "obio": "bio", "oohb10": "ohb10", "ozea": "zea"}

SPEC = ProblemSpec(
    name="Bruno_JExpBot2016",
    model=BrunoCarotenoids,
    initial_state=initial_state,
    observables={obs: _state(state) for obs, state in _OBSERVED.items()},
    noise={obs: first_noise_parameter for obs in _OBSERVED},
    unused_symbols=("cyt",),
    solver="dopri5",
    rtol=1e-8,
    atol=1e-10,
)
