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
