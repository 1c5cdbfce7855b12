"""Small models shared by the tests (tests/ is on the import path through its conftest)."""

import torch

import torchql


class Decay(torchql.ODEModel):
    """``y' = -k y``."""

    state_names = ("y",)

    def __init__(self, k=1.0, dtype=torch.float64):
        super().__init__()
        self.register_buffer("k", torch.tensor(k, dtype=dtype))

    def forward(self, t, x):
        return -self.k * x


class Product(torchql.ODEModel):
    """``y' = -a b y``: only the product ``a b`` is identifiable."""

    state_names = ("y",)

    def __init__(self, a=1.0, b=1.0):
        super().__init__()
        self.register_buffer("a", torch.tensor(a, dtype=torch.float64))
        self.register_buffer("b", torch.tensor(b, dtype=torch.float64))

    def forward(self, t, x):
        return -self.a * self.b * x


class SIR(torchql.ODEModel):
    """Susceptible-infected-recovered epidemic in a closed population of ``N`` (a constant)."""

    state_names = ("S", "I", "R")
    constants = ("N",)

    def __init__(self, beta=1.66, gamma=0.44, N=763.0):
        super().__init__()
        self.register_buffer("beta", torch.tensor(beta, dtype=torch.float64))
        self.register_buffer("gamma", torch.tensor(gamma, dtype=torch.float64))
        self.register_buffer("N", torch.tensor(N, dtype=torch.float64))

    def forward(self, t, x):
        S, I = x[..., 0], x[..., 1]
        infection = self.beta * S * I / self.N
        return torch.stack([-infection, infection - self.gamma * I, self.gamma * I], -1)


def sir_counts() -> torchql.Observations:
    """Infected counts of :class:`SIR` (``N = 1000``, ``beta = 0.6``, ``gamma = 0.25``, ``I(0) = 5``) at
    t = 0, 2, ..., 40 with noise of standard deviation 5 (``sigma=5``)."""
    t = torch.arange(0.0, 41.0, 2.0, dtype=torch.float64)
    x = torchql.simulate(SIR(0.6, 0.25, 1000.0), torch.tensor([995.0, 5.0, 0.0], dtype=torch.float64), t)
    y = x[:, 1:2] + 5.0 * torch.randn(21, 1, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    return torchql.Observations(t, y, observe=["I"], sigma=5.0)


#: Fitting :func:`sir_counts` from guesses three to four times off: I(0) and the rates bounded below
#: by 0, S(0) = N - I(0), R(0) = 0.
SIR_FAR = dict(x0=torch.tensor([990.0, 10.0, 0.0], dtype=torch.float64), params=["beta", "gamma"], fixed_x0=["R"],
               x0_expr={"S": lambda v: v["N"] - v["I"]}, bounds={"beta": (0, None), "gamma": (0, None), "I": (0, None)})
SIR_FAR_GUESSES = dict(beta=2.2969, gamma=0.6942, N=1000.0)


class Relaxation(torchql.ODEModel):
    """``x' = -k (x - A cos t)``: stiff for large ``k``, driven by the time-dependent ``cos t``; the
    amplitude ``A`` (1 by default) is a constant unless ``params`` names it."""

    state_names = ("x",)
    constants = ("A",)

    def __init__(self, k=1e3, A=1.0):
        super().__init__()
        self.register_buffer("k", torch.tensor(k, dtype=torch.float64))
        self.register_buffer("A", torch.tensor(A, dtype=torch.float64))

    def forward(self, t, x):
        return -self.k * (x - self.A * torch.cos(t))


def relaxation_solution(t, x0, k):
    """``x(t) = (x0 - x_p(0)) e^{-k t} + x_p(t)``, ``x_p = k (k cos t + sin t) / (k^2 + 1)``."""
    particular = k * (k * torch.cos(t) + torch.sin(t)) / (k**2 + 1)
    return (x0 - k**2 / (k**2 + 1)) * torch.exp(-k * t) + particular


class MichaelisMenten(torchql.ODEModel):
    """``S' = -V S / (Km + S)``: identifiable from its full decay, linear (``-(V/Km) S``) as ``Km -> inf``."""

    state_names = ("S",)

    def __init__(self, V=1.0, Km=0.5):
        super().__init__()
        self.register_buffer("V", torch.tensor(V, dtype=torch.float64))
        self.register_buffer("Km", torch.tensor(Km, dtype=torch.float64))

    def forward(self, t, x):
        return -self.V * x / (self.Km + x)


class LotkaVolterra(torchql.ODEModel):
    """Prey ``x`` and predators ``y``: ``x' = a x - b x y``, ``y' = -c y + d x y``."""

    state_names = ("x", "y")

    def __init__(self, a=1.0, b=0.5, c=1.0, d=0.3):
        super().__init__()
        for name, value in dict(a=a, b=b, c=c, d=d).items():
            self.register_buffer(name, torch.tensor(value, dtype=torch.float64))

    def forward(self, t, z):
        x, y = z.unbind(-1)
        return torch.stack((self.a * x - self.b * x * y, -self.c * y + self.d * x * y), dim=-1)


class Lag(torchql.ODEModel):
    """``x' = -k (x - y)``, ``y' = -a y``: ``x`` follows a decaying ``y`` with the lag ``1 / k``
    (stiff for a large ``k``, though not at a guess of ``k`` near 1)."""

    state_names = ("x", "y")

    def __init__(self, k=1.0, a=1.0):
        super().__init__()
        self.register_buffer("k", torch.tensor(k, dtype=torch.float64))
        self.register_buffer("a", torch.tensor(a, dtype=torch.float64))

    def forward(self, t, z):
        x, y = z.unbind(-1)
        return torch.stack((-self.k * (x - y), -self.a * y), dim=-1)


def lag_data(k: float, seed: int = 2) -> torchql.Observations:
    """:class:`Lag` with ``a = 1`` from ``x(0) = 0``, ``y(0) = 1``: both states at 20 times over (0, 2]
    (Rodas5P at ``rtol=1e-12``), plus noise of sigma 1e-4 (generator ``seed``)."""
    t = torch.linspace(0.0, 2.0, 21, dtype=torch.float64)[1:]
    x0 = torch.tensor([0.0, 1.0], dtype=torch.float64)
    x = torchql.simulate(Lag(k, 1.0), x0, torch.cat([torch.zeros(1, dtype=torch.float64), t]), solver="rodas5p",
                         rtol=1e-12, atol=1e-16)[1:]
    y = x + 1e-4 * torch.randn(x.shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return torchql.Observations(t, y, observe=["x", "y"], sigma=1e-4)


def counting(calls: dict, name: str, function):
    """``function`` wrapped to add one to ``calls[name]`` at every call (a test's spy on a solver or
    an entry point, set with ``monkeypatch.setattr``)."""
    def wrapper(*args, **kwargs):
        calls[name] += 1
        return function(*args, **kwargs)
    return wrapper
