"""The text report, the condition number, and the plots (Agg backend)."""

import math
import re
import sys

import pytest
import torch

import torchql
from testmodels import Product
from torchql.models import CoastingCar
from torchql.report import information_criteria

DT = torch.float64
SUNBEAM = torch.tensor([117.3, 104.9, 95.3, 87.3, 79.2, 71.9, 65.7, 59.8, 54.0], dtype=DT)
CAR_TIMES = torch.arange(9, dtype=DT) * 5.0


@pytest.fixture(scope="module")
def car():
    # integrated from the guesses, so that the iteration table starts at them
    result = torchql.fit(CoastingCar(17.3, 80.43), torchql.Observations(CAR_TIMES, SUNBEAM, observe=["v"]), grid=100,
                         initial_trajectory="integrate")
    assert result.success
    return result


@pytest.fixture(scope="module")
def product():
    """``y' = -a b y``: a and b cannot be separated."""

    times = torch.linspace(0, 2, 11, dtype=DT)
    data = torchql.Observations(times, torch.exp(-0.6 * times), observe=["y"])
    result = torchql.fit(Product(1.0, 1.0), data, x0=torch.tensor([1.0], dtype=DT), grid=20)
    assert result.status is torchql.Status.NOT_IDENTIFIABLE
    return result


def test_car_report_lists_every_unknown_with_error_bar_and_interval(car):
    text = car.report()
    se = car.stderr
    cis = car.confidence_intervals(0.95)
    for name, value in zip(car.unknown_names, car.estimates.tolist()):
        line = next(line for line in text.splitlines() if line.strip().startswith(name + " "))
        assert f"= {value:.7g} +/- {se[name]:.4g} ({100 * se[name] / abs(value):.2f}%)" in line
        lo, hi = cis[name]
        assert f"95% CI [{lo:.7g}, {hi:.7g}]" in line
    for part in ("[[Fit]]", "kantorovich", "CONVERGED", car.message, f"iterations         = {car.iterations}",
                 f"function evals     = {car.nfev}", "data points        = 9", "unknowns           = 3",
                 "degrees of freedom = 6", f"SSE (chi-square)   = {car.sse:.7g}",
                 f"residual std       = {math.sqrt(car.sse / 6):.7g}"):
        assert part in text
    assert "reduced chi-square" not in text  # sigma not given: the residual std is the estimate
    assert "without error bars" not in text


def test_car_report_correlations_sorted_above_threshold(car):
    text = car.report()
    block = text.split("[[Correlations]] (|r| > 0.1)\n")[1].split("[[")[0]
    found = re.findall(r"C\((.+?), (.+?)\)\s+= ([+-]\d\.\d{4})", block)
    assert found[0][:2] == ("C_D", "mu")
    r = float(found[0][2])
    assert r == pytest.approx(car.correlation[1, 2].item(), abs=1e-4)
    assert -0.99 < r < -0.96
    magnitudes = [abs(float(x[2])) for x in found]
    assert magnitudes == sorted(magnitudes, reverse=True) and min(magnitudes) > 0.1
    assert len(found) == 3
    few = car.report(min_correlation=0.9).split("[[Correlations]]")[1].split("[[")[0]
    assert "C(C_D, mu)" in few and "v(t0)" not in few


def test_aic_bic_follow_lmfit(car):
    n, m = 9, 3
    aic, bic = information_criteria(car)
    assert aic == pytest.approx(n * math.log(car.sse / n) + 2 * m, rel=1e-14)
    assert bic == pytest.approx(n * math.log(car.sse / n) + math.log(n) * m, rel=1e-14)
    text = car.report()
    assert f"AIC                = {aic:.7g}" in text
    assert f"BIC                = {bic:.7g}" in text
    # beside the -log likelihood, the convention is named: these are not 2 NLL + 2 m
    assert f"AIC                = {aic:.7g} (lmfit's: N ln(SSE/N) + 2 m, from the SSE; not 2 NLL + 2 m)" in text


def test_condition_number_and_iteration_table(car):
    s = car.singular_values
    assert car.condition_number == pytest.approx((s.max() / s.min()).item())
    assert 1 < car.condition_number < 1e3
    text = car.report()
    assert f"condition number   = {car.condition_number:.4g}" in text
    table = text.split("[[Iterations]]")[1].splitlines()[1:]
    assert table[0].split()[:3] == ["iter", "SSE", "|alpha|"] and table[0].split()[3:] == car.unknown_names
    rows = [row.split() for row in table[1:]]
    assert [int(r[0]) for r in rows] == [rec.iteration for rec in car.history]
    assert float(rows[0][3]) == pytest.approx(117.3)  # the guesses: v(t0) from the data, C_D, mu from the model
    assert float(rows[0][4]) == pytest.approx(0.4) and float(rows[0][5]) == pytest.approx(0.02)
    for name, value in zip(car.unknown_names, rows[-1][3:]):
        assert float(value) == pytest.approx(car.estimates[car.unknown_names.index(name)].item(), rel=1e-9)
    assert float(rows[-1][1]) == pytest.approx(car.sse, rel=1e-5)
    assert rows[-1][2] == "-"  # no update computed from the final evaluation
    assert "[[Iterations]]" not in car.report(iterations=False)


def test_report_prints_and_validates(car, capsys):
    text = car.report(print=True)
    assert capsys.readouterr().out == text + "\n"
    assert car.report() == text and capsys.readouterr().out == ""
    with pytest.raises(ValueError, match="`level`"):
        car.report(level=95)
    with pytest.raises(ValueError, match="`min_correlation`"):
        car.report(min_correlation=2)


def test_known_sigma_report_shows_reduced_chi_square():
    result = torchql.fit(CoastingCar(17.3, 80.43), torchql.Observations(CAR_TIMES, SUNBEAM, observe=["v"], sigma=0.4),
                         grid=100)
    text = result.report(level=0.9)
    assert f"reduced chi-square = {result.sse / 6:.7g}" in text
    assert "sigma given" in text and "90% CI" in text


def test_not_identifiable_report_explains_missing_error_bars(product):
    assert product.condition_number == math.inf
    text = product.report()
    assert "NOT_IDENTIFIABLE" in text and "condition number   = inf" in text
    block = text.split("[[Unknowns without error bars]]\n")[1].splitlines()[0]
    # only the product a b is determined: a and b lack error bars, y(t0) keeps its own
    assert block.strip().startswith("a, b:") and "not identifiable" in block and "{a, b}" in block
    for name in ("a", "b"):
        assert re.search(rf"\n    {re.escape(name)} +=.*\+/- nan \(no error bar\)\n", text)
    assert not re.search(r"\n    y\(t0\) +=.*no error bar", text)
    assert "[[Correlations]]" not in text


def test_failed_fit_report_gives_the_reason_instead_of_error_bars_and_intervals():
    from testmodels import Decay

    times = torch.linspace(0, 2, 9, dtype=DT)
    data = torchql.Observations(times, torch.exp(-0.7 * times) + 0.01 * torch.cos(5 * times), observe=["y"])
    result = torchql.fit(Decay(30.0), data, x0=torch.tensor([5.0], dtype=DT), max_iter=1)
    assert result.status is torchql.Status.MAX_ITER
    text = result.report()
    assert "no standard errors or intervals: the fit did not converge (MAX_ITER)" in text
    assert "CI [" not in text and "+/-" not in text and "[[Correlations]]" not in text
    for name, value in zip(result.unknown_names, result.estimates.tolist()):  # the estimates are still shown
        assert re.search(rf"\n    {re.escape(name)} += {re.escape(f'{value:.7g}')}\n", text)


def test_bounded_report_says_which_intervals_are_in_the_internal_variable():
    from testmodels import Decay

    times = torch.linspace(0, 2, 9, dtype=DT)
    data = torchql.Observations(times, torch.exp(-0.7 * times) + 0.01 * torch.cos(5 * times), observe=["y"])
    result = torchql.fit(Decay(1.0), data, x0=torch.tensor([1.0], dtype=DT), bounds={"k": (0, None)})
    assert result.success
    text = result.report()
    header = next(line for line in text.splitlines() if line.startswith("[[Unknowns]]"))
    assert "of k in the bounds' internal variable" in header and "y(t0)" not in header
    lo, hi = result.confidence_intervals(0.95)["k"]
    assert f"95% CI [{lo:.7g}, {hi:.7g}]" in text
    assert "internal variable" not in torchql.fit(Decay(1.0), data, x0=torch.tensor([1.0], dtype=DT)).report()
    # an estimate on its bound gets the Wald interval clipped to the bounds, and the header says so
    # (it named the internal variable); bounds far from the estimate give the plain Wald interval
    on_bound = torchql.fit(Decay(1.0), data, x0=torch.tensor([1.0], dtype=DT), bounds={"k": (0.8, None)})
    assert on_bound.success and "['k'] lie at their bounds" in on_bound.message
    header = next(line for line in on_bound.report().splitlines() if line.startswith("[[Unknowns]]"))
    assert "of k (on or near a bound) clipped to the bounds" in header and "internal variable" not in header
    far = torchql.fit(Decay(1.0), data, x0=torch.tensor([1.0], dtype=DT), bounds={"k": (-1e9, None)})
    header = next(line for line in far.report().splitlines() if line.startswith("[[Unknowns]]"))
    assert header == "[[Unknowns]] (value +/- standard error (relative), 95% Wald interval)"


# ----------------------------------------------------------------------------------------- plots
@pytest.fixture()
def agg():
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    yield plt
    plt.close("all")


def test_plot_fit_writes_a_figure(car, agg, tmp_path):
    fig, (ax_fit, ax_res) = car.plot_fit()
    assert ax_res is not None and len(ax_fit.lines) >= 2
    path = tmp_path / "fit.png"
    fig.savefig(path)
    assert path.stat().st_size > 1000
    fig2, axes = agg.subplots(1, 2)
    out_fig, (a, b) = car.plot_fit(car.data, ax=axes)  # into given axes, data explicit
    assert out_fig is fig2 and a is axes[0] and b is axes[1] and len(b.lines) >= 1
    _, (_, none) = car.plot_fit(ax=axes[0])
    assert none is None


def test_plot_fit_bars_of_log_normal_data_span_y_times_e_to_the_sigma(agg):
    """With ``noise="lognormal"`` a value's sigma is that of ``log y``: its bar runs from
    ``y e^-sigma`` to ``y e^sigma`` (it was +/- sigma in y's units)."""
    from testmodels import Decay

    t = torch.linspace(0.0, 5.0, 12, dtype=torch.float64)
    noise = torch.randn(12, 1, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    y = 100.0 * torch.exp(-0.6 * t).unsqueeze(-1) * torch.exp(0.2 * noise)
    result = torchql.fit(Decay(0.5), torchql.Observations(t, y, observe=["y"], sigma=0.2, noise="lognormal"),
                         x0=torch.tensor([90.0], dtype=torch.float64))
    assert result.success, result.message
    _, (ax_fit, _) = result.plot_fit()
    segments = ax_fit.containers[0].lines[2][0].get_segments()
    low, high = (torch.tensor([seg[i][1] for seg in segments], dtype=torch.float64) for i in (0, 1))
    torch.testing.assert_close(low, y[:, 0] * math.exp(-0.2), rtol=1e-12, atol=0)
    torch.testing.assert_close(high, y[:, 0] * math.exp(0.2), rtol=1e-12, atol=0)


def test_plot_fit_of_several_experiments_draws_the_one_named(agg):
    """A fit of two experiments: each drawn with its own data, initial state and curve; without
    ``experiment`` every one, a column each, as each alone; into a given ``ax`` without
    ``experiment`` a clear error (it was an AttributeError of the list of datasets)."""
    from torchql.models import LinearOscillator

    t = torch.arange(14, dtype=torch.float64) * 0.5
    starts = (torch.tensor([0.0, 1.0], dtype=torch.float64), torch.tensor([1.0, 0.0], dtype=torch.float64))
    sets = [torchql.Observations(t, torchql.simulate(LinearOscillator(0.1, 3.0), x0, t)[:, :1], observe=["y"])
            for x0 in starts]
    result = torchql.fit(LinearOscillator(0.5, 2.0), sets, x0=torch.stack(starts))
    assert result.success, result.message
    for k in (0, 1):
        _, (ax_fit, ax_res) = result.plot_fit(experiment=k)
        fitted, measured = ax_fit.lines[0].get_ydata(), ax_fit.lines[1].get_ydata()
        assert measured == pytest.approx(sets[k].y[:, 0].tolist())
        assert fitted[0] == pytest.approx(float(starts[k][0]), abs=1e-6)  # the curve from that experiment's start
        assert max(abs(v) for v in ax_res.lines[0].get_ydata()) < 1e-6
    fig, pairs = result.plot_fit()
    assert len(pairs) == 2 and len(fig.axes) == 4
    for k, (ax_fit, ax_res) in enumerate(pairs):
        _, (alone, _) = result.plot_fit(experiment=k)
        assert ax_fit.lines[1].get_ydata() == pytest.approx(sets[k].y[:, 0].tolist())
        assert ax_fit.lines[0].get_ydata() == pytest.approx(alone.lines[0].get_ydata(), rel=0, abs=0)
        assert ax_fit.get_title().startswith(f"experiment {k}: ")
    with pytest.raises(ValueError, match=r"`experiment` must be an index 0..1 \(the fit has 2 experiments\) when "
                                         r"`data` or `ax` is given"):
        result.plot_fit(ax=pairs[0][0])
    with pytest.raises(ValueError, match="`experiment` applies only to fits of several experiments"):
        torchql.fit(LinearOscillator(0.5, 2.0), sets[0], x0=starts[0]).plot_fit(experiment=0)


def test_plot_convergence_writes_a_figure(car, agg, tmp_path):
    fig, (ax_u, ax_sse) = car.plot_convergence()
    assert ax_u.get_yscale() == "log" and ax_sse.get_yscale() == "log"
    assert len(ax_u.lines) == 3
    path = tmp_path / "convergence.png"
    fig.savefig(path)
    assert path.stat().st_size > 1000
    fig, (ax_u, _) = car.plot_convergence(values=True)
    assert ax_u.get_yscale() == "linear"


def test_plot_profile_writes_a_figure(car, agg, tmp_path):
    prof = torchql.profile(car, "mu", max_points=2)
    fig, ax = prof.plot()
    path = tmp_path / "profile.png"
    fig.savefig(path)
    assert path.stat().st_size > 1000
    assert not prof.likelihood and ax.get_ylabel() == "optimal SSE"
    assert ax.lines[0].get_label() == "profile SSE"
    assert torch.equal(torch.as_tensor(ax.lines[0].get_ydata()), prof.sse)


def test_a_likelihood_fit_is_plotted_with_its_negative_log_likelihood(agg):
    """With estimated sigmas the SSE is in units of the sigmas (the number of values, near enough):
    the fit's title names its NLL, the profile's axis twice the NLL it holds."""
    data = torchql.Observations(CAR_TIMES, SUNBEAM, observe=["v"], sigma="estimate")
    fit = torchql.fit(CoastingCar(17.3, 80.43), data)
    assert fit.success and fit.likelihood
    fig, axes = fit.plot_fit()
    assert f"NLL {fit.nll:.4g}" in axes[0].get_title() and "SSE" not in axes[0].get_title()
    prof = torchql.profile(fit, "mu", max_points=2)
    assert prof.likelihood
    fig, ax = prof.plot()
    assert ax.get_ylabel() == "optimal 2 x negative log-likelihood"
    assert ax.lines[0].get_label() == "profile 2 NLL"
    assert torch.equal(torch.as_tensor(ax.lines[0].get_ydata()), prof.sse)
    assert prof.sse_min == pytest.approx(2 * fit.nll, rel=1e-9, abs=1e-9)
    # the iterates' objective, SSE + 2 sum log sigma, is negative here: drawn on a linear axis
    fig, (_, ax_objective) = fit.plot_convergence()
    objective = torch.tensor([rec.sse for rec in fit.history], dtype=DT)
    assert float(objective[-1]) < 0 and ax_objective.get_yscale() == "linear"
    assert torch.equal(torch.as_tensor(ax_objective.lines[0].get_ydata()), objective)
    n = fit.residuals.numel()
    assert float(objective[-1]) == pytest.approx(2 * fit.nll - n * math.log(2 * math.pi), rel=1e-9)
    assert "with estimated sigmas, SSE + 2 sum log sigma" in fit.report()


def test_missing_matplotlib_names_the_extra(car, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    monkeypatch.setitem(sys.modules, "matplotlib.pyplot", None)
    with pytest.raises(ImportError, match=r"pip install torchql\[plot\]"):
        car.plot_fit()
    with pytest.raises(ImportError, match=r"pip install torchql\[plot\]"):
        car.plot_convergence()


class _Logistic(torchql.ODEModel):
    """``y' = r y (1 - y / K)``."""

    state_names = ("y",)

    def __init__(self, r, K):
        super().__init__()
        self.register_buffer("r", torch.tensor(r, dtype=DT))
        self.register_buffer("K", torch.tensor(K, dtype=DT))

    def forward(self, t, x):
        return self.r * x * (1 - x / self.K)


def test_iteration_sse_is_the_stored_trajectory_and_acceptance_lowers_a_recorded_merit():
    """From far guesses the Kantorovich SSE column (of the predicted linear trajectories) dips
    below the optimum and rises back; every accepted step lowered the merit it was judged by."""
    times = torch.linspace(0, 10, 21, dtype=DT)
    truth = torchql.simulate(_Logistic(0.9, 10.0), torch.tensor([0.5], dtype=DT), times)[:, 0]
    y = truth + 0.1 * torch.randn(21, generator=torch.Generator().manual_seed(1), dtype=DT)
    result = torchql.fit(_Logistic(2.0, 2.0), torchql.Observations(times, y, observe=["y"]),
                         x0=torch.tensor([0.5], dtype=DT))
    assert result.success
    sse = [rec.sse for rec in result.history]
    assert min(sse) < result.sse * (1 - 1e-3)  # a predicted trajectory fits better than the optimum model
    assert any(b > a * (1 + 1e-3) for a, b in zip(sse, sse[1:]))  # the column rises somewhere
    assert sse[-1] == result.sse and math.isnan(result.history[-1].merit)
    steps = result.history[:-1]
    assert all(math.isfinite(rec.merit) for rec in steps)
    for a, b in zip(steps, steps[1:]):  # the acceptance test, as recorded
        assert b.merit <= a.merit * (1 + 1e-10) or b.model_merit <= a.model_merit * (1 + 1e-10)
    assert "not the model's solution: it need not fall" in result.report()


def test_iteration_table_of_several_experiments_shows_each_experiments_initial_state():
    """A fit of two experiments names its initial states ``"y[e](t0)"``: the iteration table showed
    NaN for them in every row (only ``"y(t0)"`` was looked up); it shows each iterate's values."""
    from testmodels import Decay
    from torchql.report import unknown_values

    t = torch.linspace(0, 3, 10, dtype=torch.float64)
    experiments = [torchql.Observations(t, torchql.simulate(Decay(0.7), torch.tensor([y0], dtype=torch.float64), t),
                                        observe=["y"]) for y0 in (2.0, 1.0)]
    result = torchql.fit(Decay(0.3), experiments, x0=torch.tensor([[1.5], [0.5]], dtype=torch.float64))
    assert result.success and result.unknown_names == ["y[0](t0)", "y[1](t0)", "k"]
    assert unknown_values(result, result.history[0])[:2] == [1.5, 0.5]
    assert unknown_values(result, result.history[-1]) == pytest.approx(result.estimates.tolist(), rel=1e-12)
    table = result.report().split("[[Iterations]]")[1]
    assert "nan" not in table


def test_aic_bic_count_the_unknowns_the_exact_values_leave_free():
    """A value marked exact fixes one unknown: the information criteria count ``m - 1`` free
    unknowns over the ``N`` least-squares values, as the degrees of freedom do (they counted all
    ``m``)."""
    t = torch.linspace(0, 6, 25, dtype=torch.float64)
    y = (torch.exp(-0.7 * t) + 0.01 * torch.randn(25, generator=torch.Generator().manual_seed(1),
                                                   dtype=torch.float64)).unsqueeze(-1)
    exact = torch.zeros(25, 1, dtype=torch.bool)
    exact[0] = True
    from testmodels import Decay

    result = torchql.fit(Decay(k=0.5), torchql.Observations(t, y, observe=["y"], exact=exact),
                         x0=torch.tensor([1.0], dtype=torch.float64))
    assert result.success and result.dof == 23
    n, m = 24, 1
    aic, bic = information_criteria(result)
    assert aic == pytest.approx(n * math.log(result.sse / n) + 2 * m, rel=1e-14)
    assert bic == pytest.approx(n * math.log(result.sse / n) + math.log(n) * m, rel=1e-14)


def test_lognormal_values_without_sigma_count_their_variance_in_aic():
    """Log-normal values without ``sigma``: the likelihood takes their variance at its maximum, SSE / n,
    as ``sigma="estimate"`` does for the same data (the same NLL); AIC and BIC counted the model's
    unknowns alone, 2 (and ln n) below the estimated sigma's. Both now count the variance:
    ``2 NLL + 2 (m + 1)``, written out here from the log residuals."""
    from testmodels import Decay

    g = torch.Generator().manual_seed(4)
    t = torch.linspace(0, 5, 15, dtype=DT)
    y = (3.0 * torch.exp(-0.7 * t) * torch.exp(0.1 * torch.randn(15, generator=g, dtype=DT))).unsqueeze(-1)
    fits = [torchql.fit(Decay(0.5), torchql.Observations(t, y, observe=["y"], sigma=sigma, noise="lognormal"),
                        x0=torch.tensor([2.0], dtype=DT)) for sigma in (None, "estimate")]
    log_residuals = y[:, 0].log() - (fits[0].x0[0] * torch.exp(-fits[0].params["k"] * t)).log()
    variance = float(log_residuals.square().mean())
    nll = 0.5 * 15 * math.log(2 * math.pi * variance) + 0.5 * 15 + float(y.log().sum())
    assert fits[0].nll == pytest.approx(nll, rel=1e-9) and fits[1].nll == pytest.approx(nll, rel=1e-9)
    for fit in fits:
        assert information_criteria(fit) == pytest.approx((2 * nll + 2 * 3, 2 * nll + math.log(15) * 3), rel=1e-9)
