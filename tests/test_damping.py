"""Damping strategies as objects: the registered names, a strategy passed as an object, and the
Levenberg–Marquardt schedule the engine follows."""

import pytest
import torch

import torchql
import torchql.damping as damping_module
from torchql.damping import DAMPINGS, Damping, LevenbergMarquardt, Undamped, damping_strategy, register_damping
from torchql.models import NonlinearOscillator

DT = torch.float64
GUESS = dict(A=0.5, B=2.0, C=0.5, D=2.0)  # the thesis' poor start: the first undamped step overshoots


def test_registered_names_and_errors():
    assert DAMPINGS == ("lm", None)
    assert isinstance(damping_strategy("lm"), LevenbergMarquardt)
    assert isinstance(damping_strategy(None), Undamped)
    custom = LevenbergMarquardt(start=1e-2)
    assert damping_strategy(custom) is custom
    with pytest.raises(ValueError, match=r"`damping` must be one of \('lm', None\) or a torchql.damping.Damping; "
                                         r"received 'trust'"):
        damping_strategy("trust")
    with pytest.raises(TypeError, match="must be a torchql.damping.Damping; received str"):
        register_damping("lm")
    with pytest.raises(ValueError, match="0 < minimum <= start <= maximum"):
        LevenbergMarquardt(start=0.0)


def test_levenberg_marquardt_schedule():
    """A first raise starts at ``start`` after an undamped iterate, else at a tenth of the last
    accepted damping (not below ``minimum``); later raises are tenfold; past ``maximum`` it stalls."""
    lm = LevenbergMarquardt()
    damping = torch.tensor([0.0, 0.0, 0.0, 1e-3], dtype=DT)
    last = torch.tensor([0.0, 1e-4, 1e-12, 0.0], dtype=DT)
    assert lm.raised(damping, last).tolist() == pytest.approx([1e-3, 1e-5, 1e-10, 1e-2], rel=1e-15)
    assert lm.stalled(torch.tensor([1e12, 1e13], dtype=DT)).tolist() == [False, True]
    undamped = Undamped()
    assert not undamped.filters and not bool(undamped.stalled(damping).any())


def test_a_retry_skips_the_raises_that_barely_shorten_the_step():
    """After a rejection the damping rises until it shortens the step by RETRY_SHORTENING (30 %)
    along some direction (damping ``lambda`` scales direction ``i`` by ``r_i / (r_i + lambda)``):
    on a well-conditioned problem (``r = 1, 0.5``) straight to 1, as 1e-3, 1e-2 and 1e-1 shorten
    it by 0.2 %, 2 % and 17 % at most; with a weak direction (``r = 1e-6``) the first raise
    shortens that one a thousandfold and stays; a problem with no direction left to judge (all
    NaN) takes the plain schedule; past the maximum the sample stalls as before."""
    lm = LevenbergMarquardt()
    nan = float("nan")
    damping = torch.tensor([0.0, 0.0, 0.0, 0.1, 1e12, 0.0], dtype=DT)
    last = torch.zeros(6, dtype=DT)
    spectrum = torch.tensor([[1.0, 0.5], [1.0, 1e-6], [nan, nan], [1.0, nan], [1.0, 1.0], [1.0, nan]], dtype=DT)
    retry = lm.retry(damping, last, spectrum)
    assert damping_module.RETRY_SHORTENING == 0.3
    assert retry.tolist() == pytest.approx([1.0, 1e-3, 1e-3, 1.0, 1e13, 1.0], rel=1e-12)
    assert lm.stalled(retry).tolist() == [False] * 4 + [True, False]
    shortened = ((spectrum[0] + 0.0) / (spectrum[0] + retry[0])).amin()
    assert shortened < 1 - damping_module.RETRY_SHORTENING < ((spectrum[0] + 0.0) / (spectrum[0] + 0.1)).amin()


def test_a_strategy_object_drives_the_fit(table_4_5_two_digit):
    """``damping=LevenbergMarquardt()`` is ``damping="lm"`` bit for bit; a subclass's schedule is
    the one the engine follows (here each raise a hundredfold), in fit and fit_many alike."""
    x0 = torch.tensor([0.5, 0.5], dtype=DT)

    class Steep(LevenbergMarquardt):
        name = "steep"

        def __init__(self):
            super().__init__()
            self.calls = []

        def raised(self, damping, last):
            self.calls.append(damping.clone())
            return torch.where(damping == 0, torch.full_like(damping, self.start), 100 * damping)

    by_name = torchql.fit(NonlinearOscillator(**GUESS), table_4_5_two_digit, x0=x0, max_steps=200)
    by_object = torchql.fit(NonlinearOscillator(**GUESS), table_4_5_two_digit, x0=x0, max_steps=200,
                            damping=LevenbergMarquardt())
    assert sum(rec.rejected for rec in by_name.history) > 0  # the damping works on this start
    assert torch.equal(by_name.estimates, by_object.estimates) and by_name.iterations == by_object.iterations
    steep = Steep()
    result = torchql.fit(NonlinearOscillator(**GUESS), table_4_5_two_digit, x0=x0, max_steps=200, damping=steep)
    assert result.success, result.message
    assert steep.calls, "the engine never asked the strategy to raise the damping"
    raised = [float(d) for rec in result.history for d in ([rec.damping] if rec.rejected else [])]
    assert all(d == steep.start or round(torch.log10(torch.tensor(d / steep.start)).item(), 9) % 2 == 0
               for d in raised if d > 0)  # start * 100^k: the subclass's schedule, not tenfold
    batch = torchql.fit_many(NonlinearOscillator(**GUESS), [table_4_5_two_digit] * 2, x0, max_steps=200,
                             damping=Steep())
    assert torch.allclose(batch.estimates, result.estimates.expand(2, -1), rtol=1e-10, atol=0)


def test_a_registered_strategy_is_taken_by_name(table_4_5_two_digit, monkeypatch):
    monkeypatch.setattr(damping_module._REGISTRY, "entries", dict(damping_module._REGISTRY.entries))  # leave the registry as found

    class Gentle(LevenbergMarquardt):
        name = "gentle"

    register_damping(Gentle(start=1e-1))
    result = torchql.fit(NonlinearOscillator(**GUESS), table_4_5_two_digit, x0=torch.tensor([0.5, 0.5], dtype=DT),
                         max_steps=200, damping="gentle")
    assert result.success, result.message
    assert isinstance(damping_strategy("gentle"), Damping)


def test_levenberg_marquardt_objects_with_equal_settings_are_equal_and_say_them():
    """A ``FitOptions`` field and a keyword giving the same settings agree (they were "given twice",
    with two printed values alike: equality was identity, and the repr hid the settings)."""
    a, b = LevenbergMarquardt(start=1e-2), LevenbergMarquardt(start=1e-2)
    assert a == b and hash(a) == hash(b) and a != LevenbergMarquardt(start=1e-1)
    assert repr(a) == "LevenbergMarquardt(start=0.01, minimum=1e-10, maximum=1e+12)"
    from torchql.options import FitOptions, with_options

    merged = with_options(FitOptions(damping=b), {"damping": a}, {"damping"})
    assert merged["damping"] == a
    import pickle

    options = FitOptions(method="shooting", damping=a)  # its scheme and strategy survive a round trip
    assert pickle.loads(pickle.dumps(options)) == options
