"""The stiff catalogue models, simulated by ``solver="rodas5p"`` against published reference solutions.

References: the Test Set for IVP Solvers, F. Mazzia and C. Magherini, release 2.4 (2008),
University of Bari, problems HIRES (solution at t = 321.8122) and ROBER (at t = 1e11), computed
there by RADAU5 in quadruple precision (rtol = atol = 1.1e-18). Where no published value exists
(Robertson at t = 1e5, van der Pol, the enzyme), scipy's Radau at a tolerance far below the one
tested serves.

Errors are measured in the mixed norm of the tolerances, ``|y - ref| / (atol + rtol |ref|)``: a
tolerance-controlled integration's global error is a small multiple of its tolerance.
"""

import math

import pytest
import torch

import torchql
from torchql.models import HIRES, MichaelisMentenEnzyme, Robertson, VanDerPol
from torchql.models.stiff import HIRES_REFERENCE, ROBERTSON_REFERENCE_1E11

DT = torch.float64
#: Robertson at t = 1e5 from (1, 0, 0): scipy Radau at rtol = 1e-13, atol = 1e-22 (agreeing with
#: rtol = 1e-12 to 3e-14 relative, and with rodas5p at rtol = 1e-12 to 4e-13).
ROBERTSON_1E5 = (1.7865921142100227e-02, 7.2747514684365823e-08, 9.8213400611039237e-01)


def mixed(y, ref, rtol, atol):
    ref = torch.as_tensor(ref, dtype=DT)
    return ((y - ref).abs() / (atol + rtol * ref.abs())).max().item()


def test_hires_matches_the_test_set_reference():
    rtol, atol = 1e-8, 1e-12
    t = torch.tensor([0.0, 321.8122], dtype=DT)
    y = torchql.simulate(HIRES(), [1, 0, 0, 0, 0, 0, 0, 0.0057], t, solver="rodas5p", rtol=rtol, atol=atol)
    assert mixed(y[-1], HIRES_REFERENCE, rtol, atol) < 2


@pytest.mark.parametrize("end, reference", [(1e5, ROBERTSON_1E5), (1e11, ROBERTSON_REFERENCE_1E11)])
def test_robertson_matches_the_reference(end, reference):
    # y2 falls to 8e-14 by t = 1e11: atol far below it so that every component is resolved
    rtol, atol = 1e-8, 1e-18
    y = torchql.simulate(Robertson(), [1.0, 0.0, 0.0], torch.tensor([0.0, end], dtype=DT), solver="rodas5p",
                         rtol=rtol, atol=atol)
    assert mixed(y[-1], reference, rtol, atol) < 2
    assert abs(y[-1].sum().item() - 1.0) < 1e-12  # the reactions conserve mass; the method preserves linear invariants


def test_van_der_pol_over_a_relaxation_matches_scipy_radau():
    solve_ivp = pytest.importorskip("scipy.integrate").solve_ivp
    # mu = 1000 from (2, 0): a slow drift down to y = 1, then the jump to y ~ -2 near t = 807
    mu, rtol, atol = 1000.0, 1e-8, 1e-8
    t = torch.linspace(0, 850, 18, dtype=DT)
    y = torchql.simulate(VanDerPol(mu), [2.0, 0.0], t, solver="rodas5p", rtol=rtol, atol=atol)
    ref = solve_ivp(lambda s, x: [x[1], mu * (1 - x[0] ** 2) * x[1] - x[0]], (0, 850), [2.0, 0.0], method="Radau",
                    rtol=1e-11, atol=1e-11, t_eval=t.numpy())
    assert ref.success and ref.y[0, -1] < -1.9  # the jump is inside the interval
    # the jump's timing amplifies the local errors (an error dt in it is an error dt * y' in y)
    assert mixed(y, torch.from_numpy(ref.y.T), rtol, atol) < 10


def test_enzyme_conserves_enzyme_and_mass_and_follows_michaelis_menten():
    model = MichaelisMentenEnzyme()
    t = torch.tensor([0.0, 1e-4, 1e-2, 1.0, 5.0, 20.0], dtype=DT)
    y = torchql.simulate(model, [10.0, 1.0, 0.0, 0.0], t, solver="rodas5p", rtol=1e-8, atol=1e-10)
    S, E, C, P = y.unbind(-1)
    # linear invariants: Rosenbrock steps keep them to roundoff, whatever the tolerance
    torch.testing.assert_close(E + C, torch.ones_like(E), rtol=0, atol=1e-12)
    torch.testing.assert_close(S + C + P, torch.full_like(S, 10.0), rtol=0, atol=1e-11)
    # after the fast binding, the complex sits at its quasi-steady state E_T S / (K_M + S)
    K_M = (model.kr + model.kcat) / model.kf
    quasi = S / (K_M + S)
    assert ((C[2:] - quasi[2:]).abs() / quasi[2:]).max() < 0.05


@pytest.mark.parametrize("model", [Robertson(), VanDerPol(), HIRES(), MichaelisMentenEnzyme()],
                         ids=lambda m: type(m).__name__)
def test_forward_broadcasts_over_leading_dimensions(model):
    n = len(model.state_names)
    x = torch.rand(4, 3, n, dtype=DT)
    out = model(torch.tensor(0.0, dtype=DT), x)
    assert out.shape == (4, 3, n) and out.dtype == DT
    torch.testing.assert_close(out[2, 1], model(torch.tensor(0.0, dtype=DT), x[2, 1]))


def test_dopri5_is_not_the_tool_here():
    # the stiff solver's accepted steps on Robertson to 1e3: tens; dopri5's stability bound
    # (|h lambda| < ~3.3 with lambda ~ -1e4 after the transient) would need ~1e6 steps
    from torchql.solvers import rodas5p_solve
    _, sol = rodas5p_solve(Robertson(), torch.tensor([1.0, 0.0, 0.0], dtype=DT), torch.tensor([0.0, 1e3], dtype=DT),
                           rtol=1e-6, atol=1e-12)
    assert sol.n_accepted.item() < 150 and math.isfinite(sol.t.item())
