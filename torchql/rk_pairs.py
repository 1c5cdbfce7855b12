"""The embedded Runge–Kutta pairs of :func:`torchql.dopri.dopri_batch`, by solver name (:data:`PAIRS`).

* ``"dopri5"``, :class:`DormandPrince5`: Dormand and Prince's 5(4) pair with Shampine's dense
  output, as torchdiffeq's ``dopri5`` and scipy's ``RK45``;
* ``"dop853"``, :class:`DOP853`: Dormand and Prince's eighth-order pair with the error estimator
  and seventh-order dense output of Hairer's DOP853 (E. Hairer, S. P. Nørsett, G. Wanner,
  *Solving Ordinary Differential Equations I*, 2nd ed., Springer 1993, section II.10), as scipy's
  ``DOP853``. At the tight tolerances of a fit (``rtol=1e-10``) its steps are several times longer
  than the fifth-order pair's: on a damped oscillator over two periods, 37 steps of twelve slopes
  against 356 of six.

A pair gives :class:`~torchql.dopri._DopriRun` its trial step's slopes and solution, the local
error over its tolerance, the exponent of the step-size factor and a dense output; the loop, the
step-size control and the landing on nodes are the integrator's, the same for every pair.
"""

from __future__ import annotations

import torch

__all__ = ["PAIRS", "DormandPrince5", "DOP853", "combine"]

#: Dormand–Prince 5(4): nodes and rows (the dopri5 of torchdiffeq and scipy's RK45).
_DP_C = (0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0, 1.0)
_DP_A = (
    (),
    (1 / 5,),
    (3 / 40, 9 / 40),
    (44 / 45, -56 / 15, 32 / 9),
    (19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729),
    (9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656),
    (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84),
)
#: Weights of the dense output at the step's midpoint (Shampine's), over the seven slopes.
_DP_MID = (6025192743 / 30085553152 / 2, 0.0, 51252292925 / 65400821598 / 2, -2691868925 / 45128329728 / 2,
           187940372067 / 1594534317056 / 2, -1776094331 / 19743644256 / 2, 11237099 / 235043384 / 2)
#: Fifth-order weights minus the embedded fourth-order ones: the local error estimate.
_DP_E = (71 / 57600, 0.0, -71 / 16695, 71 / 1920, -17253 / 339200, 22 / 525, -1 / 40)


class DormandPrince5:
    """Dormand–Prince 5(4) (``"dopri5"``: torchdiffeq's ``dopri5``, scipy's ``RK45``): six new slopes
    per trial step, the last at the new solution (first same as last), error estimate of order 4,
    a quartic dense output through Shampine's midpoint value (fourth order: no further slope).

    The interface :class:`_DopriRun` steps by (also :class:`DOP853`): ``evals``
    (slopes per trial step), ``exponent`` (of the step-size factor), ``dense_evals`` (further slopes
    per dense output), :meth:`step`, :meth:`error_ratio`, :meth:`dense`."""

    name = "dopri5"
    evals, exponent, dense_evals = 6, -1 / 5, 0
    #: Hairer's stiffness test: the slopes of stage 5 and of the new solution (both at the step's
    #: end) and the bound of ``h lambda``, near the boundary of the pair's stability region.
    stiffness = (5, 6, 3.25)

    def __init__(self, dtype: torch.dtype, device: torch.device) -> None:
        # the tableau's rows as tensors: each stage's combination of the slopes is one contraction
        self.rows_a = [torch.tensor(_DP_A[i], dtype=dtype, device=device) for i in range(7)]
        self.nodes = _DP_C  # (the stages' times, as fractions of the step)
        self.row_e, self.row_mid = (torch.tensor(row, dtype=dtype, device=device) for row in (_DP_E, _DP_MID))

    def step(self, fv, xa: torch.Tensor, ta: torch.Tensor, ka: torch.Tensor,
             hc: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Slopes ``K (7, A, M)`` (``K[0] = ka``, ``K[6]`` at the new solution) and the new solution
        ``(A, M)`` of steps ``hc (A, 1)`` from ``xa (A, M)`` at ``ta (A,)``."""
        K = xa.new_empty(7, *xa.shape)
        K[0] = ka
        # the last stage is evaluated at the fifth-order solution (first same as last)
        return K, _stages(fv, self.rows_a, _DP_C, K, range(1, 7), xa, ta, hc)

    def error_ratio(self, K: torch.Tensor, hc: torch.Tensor, sc: torch.Tensor, norm) -> torch.Tensor:
        """The local error over its tolerance ``sc (A, n)`` in the ``norm`` of the states (``(A, n)
        -> (A,)``), ``(A,)``."""
        err = hc * combine(self.row_e, K)
        return norm(err[:, :sc.shape[1]] / sc)

    def dense(self, fv, xa, ta, x_new, K, hc):
        """The dense output of the steps ``hc (R, 1)`` from ``xa (R, M)`` to ``x_new`` with slopes
        ``K (7, R, M)``: a function of ``(theta (N, 1), which (N,))`` giving the values at the
        fractions ``theta`` of the steps ``which``, ``(N, M)``."""
        y_mid = torch.addcmul(xa, hc, combine(self.row_mid, K))
        quartic = _quartic(xa, x_new, y_mid, K[0], K[6], hc)

        def at(theta, which):
            value = quartic[4][which]
            for coefficient in quartic[3::-1]:
                value = value * theta + coefficient[which]
            return value
        return at


# DOP853: the nodes of its twelve stages, the new solution's slope and the dense output's three
# further stages; each stage's row of coefficients (the thirteenth: the eighth-order weights);
# the fifth- and third-order error estimators over the thirteen slopes; the dense output's
# coefficients of degrees 3 to 6 over all sixteen slopes.
_C8 = (0.0, 0.05260015195876773, 0.0789002279381516, 0.1183503419072274, 0.2816496580927726,
       0.3333333333333333, 0.25, 0.3076923076923077, 0.6512820512820513, 0.6, 0.8571428571428571, 1.0, 1.0,
       0.1, 0.2, 0.7777777777777778)
_A8 = (
    (),
    (0.05260015195876773,),
    (0.0197250569845379, 0.0591751709536137),
    (0.02958758547680685, 0.0, 0.08876275643042054),
    (0.2413651341592667, 0.0, -0.8845494793282861, 0.924834003261792),
    (0.037037037037037035, 0.0, 0.0, 0.17082860872947386, 0.12546768756682242),
    (0.037109375, 0.0, 0.0, 0.17025221101954405, 0.06021653898045596, -0.017578125),
    (0.03709200011850479, 0.0, 0.0, 0.17038392571223998, 0.10726203044637328, -0.015319437748624402,
     0.008273789163814023),
    (0.6241109587160757, 0.0, 0.0, -3.3608926294469414, -0.868219346841726, 27.59209969944671,
     20.154067550477894, -43.48988418106996),
    (0.47766253643826434, 0.0, 0.0, -2.4881146199716677, -0.590290826836843, 21.230051448181193,
     15.279233632882423, -33.28821096898486, -0.020331201708508627),
    (-0.9371424300859873, 0.0, 0.0, 5.186372428844064, 1.0914373489967295, -8.149787010746927,
     -18.52006565999696, 22.739487099350505, 2.4936055526796523, -3.0467644718982196),
    (2.273310147516538, 0.0, 0.0, -10.53449546673725, -2.0008720582248625, -17.9589318631188,
     27.94888452941996, -2.8589982771350235, -8.87285693353063, 12.360567175794303, 0.6433927460157636),
    (0.054293734116568765, 0.0, 0.0, 0.0, 0.0, 4.450312892752409, 1.8915178993145003, -5.801203960010585,
     0.3111643669578199, -0.1521609496625161, 0.20136540080403034, 0.04471061572777259),
    (0.056167502283047954, 0.0, 0.0, 0.0, 0.0, 0.0, 0.25350021021662483, -0.2462390374708025,
     -0.12419142326381637, 0.15329179827876568, 0.00820105229563469, 0.007567897660545699, -0.008298),
    (0.03183464816350214, 0.0, 0.0, 0.0, 0.0, 0.028300909672366776, 0.053541988307438566, -0.05492374857139099,
     0.0, 0.0, -0.00010834732869724932, 0.0003825710908356584, -0.00034046500868740456, 0.1413124436746325),
    (-0.42889630158379194, 0.0, 0.0, 0.0, 0.0, -4.697621415361164, 7.683421196062599, 4.06898981839711,
     0.3567271874552811, 0.0, 0.0, 0.0, -0.0013990241651590145, 2.9475147891527724, -9.15095847217987),
)
_E5 = (0.01312004499419488, 0.0, 0.0, 0.0, 0.0, -1.2251564463762044, -0.4957589496572502, 1.6643771824549864,
       -0.35032884874997366, 0.3341791187130175, 0.08192320648511571, -0.022355307863886294)
_E3 = (-0.18980075407240762, 0.0, 0.0, 0.0, 0.0, 4.450312892752409, 1.8915178993145003, -5.801203960010585,
       -0.4226823213237919, -0.1521609496625161, 0.20136540080403034, 0.02265179219836082)
_D8 = (
    (-8.428938276109013, 0.0, 0.0, 0.0, 0.0, 0.5667149535193777, -3.0689499459498917, 2.38466765651207,
     2.117034582445028, -0.871391583777973, 2.2404374302607883, 0.6315787787694688, -0.08899033645133331,
     18.148505520854727, -9.194632392478356, -4.436036387594894),
    (10.427508642579134, 0.0, 0.0, 0.0, 0.0, 242.28349177525817, 165.20045171727028, -374.5467547226902,
     -22.113666853125306, 7.733432668472264, -30.674084731089398, -9.332130526430229, 15.697238121770845,
     -31.139403219565178, -9.35292435884448, 35.81684148639408),
    (19.985053242002433, 0.0, 0.0, 0.0, 0.0, -387.0373087493518, -189.17813819516758, 527.8081592054236,
     -11.57390253995963, 6.8812326946963, -1.0006050966910838, 0.7777137798053443, -2.778205752353508,
     -60.19669523126412, 84.32040550667716, 11.99229113618279),
    (-25.69393346270375, 0.0, 0.0, 0.0, 0.0, -154.18974869023643, -231.5293791760455, 357.6391179106141,
     93.40532418362432, -37.45832313645163, 104.0996495089623, 29.8402934266605, -43.53345659001114,
     96.32455395918828, -39.17726167561544, -149.72683625798564),
)

class DOP853:
    """Hairer's DOP853 (``"dop853"``): twelve slopes per trial step (eleven stages and the new
    solution's, first same as last), the error of the fifth-order estimator damped by the
    third-order one (Hairer's ``err5^2 / sqrt(err5^2 + 0.01 err3^2)``), and a seventh-order dense
    output from three further slopes, evaluated only for steps that pass a node."""

    name = "dop853"
    evals, exponent, dense_evals = 12, -1 / 8, 3
    stiffness = (11, 12, 6.1)  # (as :class:`DormandPrince5`'s)

    def __init__(self, dtype: torch.dtype, device: torch.device) -> None:
        self.rows_a = [torch.tensor(row, dtype=dtype, device=device) for row in _A8]
        self.nodes = _C8
        self.row_e5, self.row_e3 = (torch.tensor(row, dtype=dtype, device=device) for row in (_E5, _E3))
        self.rows_d = torch.tensor([row + (0.0,) * (16 - len(row)) for row in _D8], dtype=dtype, device=device)

    def step(self, fv, xa: torch.Tensor, ta: torch.Tensor, ka: torch.Tensor,
             hc: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Slopes ``K (13, A, M)`` (``K[0] = ka``, ``K[12]`` at the new solution) and the new
        solution ``(A, M)`` of steps ``hc (A, 1)`` from ``xa (A, M)`` at ``ta (A,)``."""
        K = xa.new_empty(13, *xa.shape)
        K[0] = ka
        # the thirteenth row's combination is the eighth-order solution, where the last slope is taken
        return K, _stages(fv, self.rows_a, _C8, K, range(1, 13), xa, ta, hc)

    def error_ratio(self, K: torch.Tensor, hc: torch.Tensor, sc: torch.Tensor, norm) -> torch.Tensor:
        """The local error over its tolerance ``sc (A, n)``, ``(A,)``: Hairer's, ``|h| e5^2 / sqrt(e5^2
        + 0.01 e3^2)`` with ``e5``, ``e3`` the ``norm`` (``(A, n) -> (A,)``; his is the RMS norm) of
        the fifth- and third-order estimates: the fifth-order one, damped where the third-order one
        is much larger."""
        n = sc.shape[1]
        e5 = norm(combine(self.row_e5, K[:len(self.row_e5)])[:, :n] / sc).square()
        e3 = norm(combine(self.row_e3, K[:len(self.row_e3)])[:, :n] / sc).square()
        denominator = e5 + 0.01 * e3
        ratio = hc.squeeze(-1).abs() * e5 / denominator.clamp(min=torch.finfo(e5.dtype).tiny).sqrt()
        return torch.where(denominator > 0, ratio, torch.zeros_like(ratio))

    def dense(self, fv, xa, ta, x_new, K, hc):
        """The seventh-order dense output of the steps ``hc (R, 1)`` from ``xa (R, M)`` at ``ta (R,)``
        to ``x_new`` with slopes ``K (13, R, M)`` (three further slopes): a function of
        ``(theta (N, 1), which (N,))`` giving the values at the fractions ``theta`` of the steps
        ``which``, ``(N, M)``."""
        slopes = torch.cat([K, K.new_empty(3, *K.shape[1:])])
        _stages(fv, self.rows_a, _C8, slopes, range(13, 16), xa, ta, hc)
        delta = x_new - xa
        F = [delta, hc * K[0] - delta, 2 * delta - hc * (K[12] + K[0])]
        F += [hc * combine(row, slopes) for row in self.rows_d]  # one product per row: a sample's
        # values then do not depend on the other samples (a matrix-matrix product's blocking does)

        def at(theta, which):
            # y0 + theta (F0 + (1 - theta) (F1 + theta (F2 + (1 - theta) (F3 + ...)))), inside out
            value = F[6][which] * theta
            for k in range(5, -1, -1):
                value = (value + F[k][which]) * (theta if k % 2 == 0 else 1 - theta)
            return value + xa[which]
        return at


def _stages(fv, rows: list, nodes: tuple, K: torch.Tensor, which: range, xa: torch.Tensor, ta: torch.Tensor,
            hc: torch.Tensor) -> torch.Tensor:
    """The slopes ``K[i]`` of the stages ``which``, in place: each at ``ta + nodes[i] h`` and
    ``xa + h rows[i] . K`` (``rows[i]``: the tableau row, no longer than the slopes it combines),
    for steps ``hc (A, 1)`` from ``xa (A, M)``; returns the last stage's state."""
    he = hc.squeeze(-1)
    for i in which:
        xi = torch.addcmul(xa, hc, combine(rows[i], K[:rows[i].shape[0]]))
        K[i] = fv(ta + nodes[i] * he, xi)
    return xi


def combine(weights: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """``sum_i weights[i] K[i]``: ``(A, ...)`` from ``weights (i,)`` and slopes ``K (i, A, ...)``, one
    matrix-vector product (``torch.tensordot``'s Python wrapper cost a fifth of a step on one sample)."""
    return (weights @ K.reshape(K.shape[0], -1)).reshape(K.shape[1:])


def _quartic(y0, y1, y_mid, f0, f1, h):
    """Power-basis coefficients ``(c0, .., c4)`` in ``theta = (t - t0) / h`` of the quartic through
    ``y0``, ``y_mid`` and ``y1`` with slopes ``f0``, ``f1`` at the ends (the dense output of a step)."""
    return (y0, h * f0, h * (f1 - 4 * f0) - 11 * y0 - 5 * y1 + 16 * y_mid,
            h * (5 * f0 - 3 * f1) + 18 * y0 + 14 * y1 - 32 * y_mid,
            2 * h * (f1 - f0) - 8 * (y1 + y0) + 16 * y_mid)


#: The pairs by solver name.
PAIRS = {pair.name: pair for pair in (DormandPrince5, DOP853)}

