"""The coefficients of Rodas5P, a stiffly accurate, L-stable Rosenbrock method of order 5(4).

G. Steinebach, "Construction of Rosenbrock–Wanner method Rodas5P and numerical benchmarks within
the Julia Differential Equations package", BIT Numerical Mathematics 63 (2023), article 27. Eight
stages, one LU factorisation per step; the solution is of order 5, the embedded one (the seventh
stage's) of order 4, and the dense output of order 4. The coefficients are in the "transformed"
form of E. Hairer and G. Wanner, *Solving Ordinary Differential Equations II*, Section IV.7
(eq. 7.25): with ``W = I / (h gamma) - J``, ``J = df/dy(t0, y0)``, ``f_t = df/dt(t0, y0)``,

    W k_i = f(t0 + c_i h, y0 + sum_{j<i} a_ij k_j) + sum_{j<i} (C_ij / h) k_j + h d_i f_t,

``y1 = y0 + sum_i m_i k_i`` and the local error estimate ``k_8`` (the solution less the embedded
one). The method is stiffly accurate: the last three stages are evaluated at ``t0 + h`` on the
running solution, so ``m`` is the last row of ``a`` followed by ones.
"""

from __future__ import annotations

import torch

__all__ = ["GAMMA", "A", "C", "NODES", "D", "M", "DENSE", "STAGES", "Tensors", "stage_sums"]

#: The diagonal ``gamma`` of the method.
GAMMA = 0.21193756319429014

_A6 = (-7.502846399306121, 2.561846144803919, -11.627539656261098, -0.18268767659942256, 0.030198172008377946)

#: ``a[i] = (a_i1, ..., a_i,i-1)``: the stage arguments, ``y0 + sum_j a_ij k_j``.
A = (
    (),
    (3.0,),
    (2.849394379747939, 0.45842242204463923),
    (-6.954028509809101, 2.489845061869568, -10.358996098473584),
    (2.8029986275628964, 0.5072464736228206, -0.3988312541770524, -0.04721187230404641),
    _A6,
    _A6 + (1.0,),
    _A6 + (1.0, 1.0),
)

#: ``C[i] = (C_i1, ..., C_i,i-1)``: the stage increments' contributions to the right-hand sides.
C = (
    (),
    (-14.155112264123755,),
    (-17.97296035885952, -2.859693295451294),
    (147.12150275711716, -1.41221402718213, 71.68940251302358),
    (165.43517024871676, -0.4592823456491126, 42.90938336958603, -5.961986721573306),
    (24.854864614690072, -3.0009227002832186, 47.4931110020768, 5.5814197821558125, -0.6610691825249471),
    (30.91273214028599, -3.1208243349937974, 77.79954646070892, 34.28646028294783, -19.097331116725623,
     -28.087943162872662),
    (37.80277123390563, -3.2571969029072276, 112.26918849496327, 66.9347231244047, -40.06618937091002,
     -54.66780262877968, -9.48861652309627),
)

#: The stages' times, ``t0 + c_i h``.
NODES = (0.0, 0.6358126895828704, 0.4095798393397535, 0.9769306725060716, 0.4288403609558664, 1.0, 1.0, 1.0)

#: The coefficients ``d_i`` of the time derivative ``h f_t`` (zero in the stiffly accurate stages).
D = (0.21193756319429014, -0.42387512638858027, -0.3384627126235924, 1.8046452872882734, 2.325825639765069,
     0.0, 0.0, 0.0)

#: The solution's weights: ``y1 = y0 + sum_i m_i k_i``.
M = _A6 + (1.0, 1.0, 1.0)

#: Three rows of weights of the dense output's vectors ``q_r = sum_i DENSE[r][i] k_i``, with
#: ``y(t0 + theta h) = (1 - theta) y0 + theta (y1 + (1 - theta) (q_1 + theta (q_2 + theta q_3)))``.
DENSE = (
    (25.948786856663858, -2.5579724845846235, 10.433815404888879, -2.3679251022685204, 0.524948541321073,
     1.1241088310450404, 0.4272876194431874, -0.17202221070155493),
    (-9.91568850695171, -0.9689944594115154, 3.0438037242978453, -24.495224566215796, 20.176138334709044,
     15.98066361424651, -6.789040303419874, -6.710236069923372),
    (11.419903575922262, 2.8879645146136994, 72.92137995996029, 80.12511834622643, -52.072871366152654,
     -59.78993625266729, -0.15582684282751913, 4.883087185713722),
)

#: Number of stages.
STAGES = 8


class Tensors:
    """The coefficients as tensors of one dtype and device: ``a[i]``, ``c[i]`` (rows of :data:`A`
    and :data:`C`), ``ac[i]`` (the two stacked, ``(2, i)``), ``nodes``, ``m`` (the solution's
    weights) and ``dense`` ``(3, 8)``."""

    def __init__(self, dtype: torch.dtype, device: torch.device) -> None:
        def tensor(values):
            return torch.tensor(values, dtype=dtype, device=device)
        self.a = [tensor(row) for row in A]
        self.c = [tensor(row) for row in C]
        self.ac = [torch.stack((a, c)) for a, c in zip(self.a, self.c)]
        self.nodes, self.m, self.dense = tensor(NODES), tensor(M), tensor(DENSE)


def stage_sums(weights: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """``sum_i weights[..., i] K[i]`` of stage increments ``K (8, ...)``: ``(*weights.shape[:-1], ...)``
    (the step's change with :attr:`Tensors.m`, the dense output's vectors with :attr:`Tensors.dense`)."""
    return (weights @ K.reshape(K.shape[0], -1)).view(*weights.shape[:-1], *K.shape[1:])
