"""The thesis' coast-down data (Table 4.6): least-squares optimum and the thesis' coefficients.

The optimum is checked against scipy's `least_squares` over `solve_ivp` (a test extra): both
estimates are evaluated with one accurate integrator (DOP853 at rtol 1e-13, so the SSE is
known to about 1e-11 relative) and torchql's SSE must be no larger than scipy's, up to that
evaluation error.
"""

import numpy as np
import pytest
import torch

import torchql
from torchql.models import AIR_DENSITY, GRAVITY, CoastingCar

scipy_optimize = pytest.importorskip("scipy.optimize")
scipy_integrate = pytest.importorskip("scipy.integrate")

TIMES = np.arange(0.0, 41.0, 5.0)
CARS = {
    # name: (frontal area ft^2, mass slug, measured velocity ft/s, thesis C_D, thesis mu)
    "Sunbeam Alpine": (17.3, 80.43, [117.3, 104.9, 95.3, 87.3, 79.2, 71.9, 65.7, 59.8, 54.0], 0.51, 0.0207),
    "Porsche 911": (18.4, 76.39, [117.3, 108.4, 100.9, 93.9, 88.0, 82.1, 76.3, 70.5, 65.4], 0.27, 0.0201),
    "XKE Jaguar": (18.2, 105.59, [117.3, 108.5, 101.2, 94.6, 88.6, 82.1, 76.4, 71.6, 66.0], 0.37, 0.0198),
}


def _velocity(area, mass, cd, mu, v0):
    rhs = lambda t, v: -0.5 * AIR_DENSITY * area * cd / mass * v**2 - mu * GRAVITY
    sol = scipy_integrate.solve_ivp(rhs, (0.0, 40.0), [v0], t_eval=TIMES, method="DOP853", rtol=1e-13, atol=1e-13)
    return sol.y[0]


@pytest.mark.parametrize("method", torchql.METHODS)
@pytest.mark.parametrize("name", list(CARS))
def test_each_car_is_the_least_squares_optimum(name, method):
    area, mass, v, cd_thesis, mu_thesis = CARS[name]
    v = np.array(v)
    data = torchql.Observations(torch.tensor(TIMES), torch.tensor(v), observe=["v"])
    result = torchql.fit(CoastingCar(area, mass), data, method=method)
    assert result.success, result.message
    v0, cd, mu = result.estimates.tolist()

    peer = scipy_optimize.least_squares(lambda p: _velocity(area, mass, *p) - v, [0.4, 0.02, v[0]],
                                        xtol=1e-15, ftol=1e-15, gtol=1e-15)
    sse_ours = float(((_velocity(area, mass, cd, mu, v0) - v) ** 2).sum())
    sse_peer = float(((_velocity(area, mass, *peer.x) - v) ** 2).sum())
    assert sse_ours <= sse_peer * (1 + 1e-9)
    # within one unit of the last digit the thesis prints
    assert abs(cd - cd_thesis) <= 0.01
    assert abs(mu - mu_thesis) <= 0.0001
