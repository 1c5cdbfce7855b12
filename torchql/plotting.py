"""Plots of a fit, its convergence and a profile (matplotlib, an optional extra: ``pip install torchql[plot]``)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import torch

if TYPE_CHECKING:  # pragma: no cover
    from .compare import Comparison
    from .observations import Observations
    from .profile import ProfileResult
    from .result import FitResult

__all__ = ["plot_fit", "plot_convergence", "plot_profile", "plot_comparison"]


def _pyplot():
    try:
        import matplotlib.pyplot as plt
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(
            "torchql's plots need matplotlib, an optional dependency: pip install torchql[plot]"
        ) from exc
    return plt


def _two_axes(ax, sharex: bool, height_ratios=(3, 1)):
    """``(figure, (top, bottom))`` from ``ax``: None (a new figure), or a pair of Axes."""
    plt = _pyplot()
    if ax is None:
        fig, axes = plt.subplots(2, 1, sharex=sharex, figsize=(7, 6),
                                 gridspec_kw={"height_ratios": list(height_ratios)})
        return fig, (axes[0], axes[1])
    if hasattr(ax, "plot"):
        return ax.figure, (ax, None)
    try:
        top, bottom = ax
    except (TypeError, ValueError) as exc:
        raise TypeError("`ax` must be None, one matplotlib Axes, or a pair of Axes (top, bottom)") from exc
    return top.figure, (top, bottom)


def _output_labels(observe, state_names, K: int) -> list[str]:
    if isinstance(observe, (list, tuple)) and all(isinstance(n, str) for n in observe):
        return list(observe)
    return [f"y[{k}]" for k in range(K)]


def plot_fit(result: "FitResult", data: "Observations | None" = None, ax=None, n_points: int = 400,
             experiment: int | None = None):
    """The fitted model's observed quantities against the data, with a residual panel.

    Parameters
    ----------
    result : FitResult
    data : Observations, optional
        Default ``result.data`` (with several experiments, that of ``experiment``).
    ax : matplotlib Axes or pair of Axes, optional
        ``None``: a new figure with the fit above and the residuals ``y - h(x(t))`` below; a
        pair ``(ax_fit, ax_residuals)``: drawn there; one Axes: the fit only.
    n_points : int
        Points of the fitted curve.
    experiment : int, optional
        With a fit of several experiments, which one (its data, initial state and conditions).
        ``None`` there (with ``data`` and ``ax`` not given): every experiment, one column of the
        new figure each.

    Returns
    -------
    (Figure, (Axes, Axes or None)); for every experiment of a fit of ``E``: (Figure, list of the
    ``E`` pairs of Axes)
    """
    from .model import coefficients
    from .observations import ObservationOperator, Observations

    if experiment is None and result.experiment_t0 is not None and data is None and ax is None:
        return _plot_each_experiment(result, n_points)
    several = result._experiment_index(experiment, when=" when `data` or `ax` is given") is not None
    if several and data is None and isinstance(result.data, (list, tuple)):
        data = result.data[experiment]
    if data is None:
        data = result.data
    if data is None:
        raise ValueError("`data` is required: this FitResult does not hold the observations it was fitted to")
    if not isinstance(data, Observations):
        raise TypeError(f"`data` must be a torchql.Observations (one experiment's); received {type(data).__name__}")
    fig, (ax_fit, ax_res) = _two_axes(ax, sharex=True)
    dtype, device = result.x0.dtype, result.x0.device
    model = result.experiment_model(experiment) if several else result.model
    names = list(model.state_names)
    K = data.n_outputs
    operator = ObservationOperator(data.observe, names, K, dtype, device)
    t_obs = data.t.to(dtype=dtype, device=device)
    t0 = result.experiment_t0[experiment] if several else result.t0
    t_first = min(t0, float(t_obs[0]))
    t_last = float(t_obs[-1])
    if t_last > t_first:
        t_fine = torch.linspace(t_first, t_last, n_points, dtype=dtype, device=device)
    else:
        t_fine = t_obs.clone()
    with torch.no_grad():
        h_fine = operator.values(result.predict(t_fine, experiment=experiment), coefficients(model))
        h_obs = operator.values(result.predict(t_obs, experiment=experiment), coefficients(model))
    y = data.y.to(dtype=dtype, device=device)
    labels = _output_labels(data.observe, names, K)
    tf = t_fine.cpu().numpy()
    to = t_obs.cpu().numpy()
    sigma = data.sigma_at(coefficients(model))  # with a sigma(p) function, at the estimates
    for k in range(K):
        (line,) = ax_fit.plot(tf, h_fine[:, k].cpu().numpy(), label=f"{labels[k]} fitted")
        color = line.get_color()
        ok = ~torch.isnan(y[:, k])
        yk = y[ok, k].cpu().numpy()
        tk = to[ok.cpu().numpy()]
        if data.sigma_given:
            s = sigma[:, k][ok.cpu()].cpu().numpy()
            # log-normal noise: sigma is that of log y, the bars y e^(-/+ sigma)
            bars = [yk * (1 - np.exp(-s)), yk * (np.exp(s) - 1)] if data.noise == "lognormal" else s
            ax_fit.errorbar(tk, yk, yerr=bars, fmt="o", color=color, ms=4, label=f"{labels[k]} data")
        else:
            ax_fit.plot(tk, yk, "o", color=color, ms=4, label=f"{labels[k]} data")
        ex = (data.exact[:, k].to(ok.device) & ok)
        if bool(ex.any()):
            ax_fit.plot(to[ex.cpu().numpy()], y[ex, k].cpu().numpy(), "s", mfc="none", color=color, ms=9,
                        label=f"{labels[k]} exact")
        if ax_res is not None:
            ax_res.plot(tk, (y[ok, k] - h_obs[ok, k]).cpu().numpy(), "o-", color=color, ms=4, lw=0.8)
    ax_fit.set_ylabel("observed")
    # a likelihood fit's SSE is in units of its sigmas: the objective it minimized is its NLL
    objective = f"NLL {result.nll:.4g}" if result.likelihood else f"SSE {result.sse:.4g}"
    ax_fit.set_title(f"{result.method} fit: {result.status.name}, {objective}")
    ax_fit.legend(fontsize="small")
    if ax_res is not None:
        ax_res.axhline(0.0, color="0.5", lw=0.8)
        ax_res.set_ylabel("residual y - h(x)")
        ax_res.set_xlabel("t")
    else:
        ax_fit.set_xlabel("t")
    return fig, (ax_fit, ax_res)


def _plot_each_experiment(result: "FitResult", n_points: int):
    """:func:`plot_fit` of every experiment of ``result``, one column of a new figure each."""
    E = len(result.experiment_t0)
    fig, axes = _pyplot().subplots(2, E, sharex="col", figsize=(5 * E, 6), squeeze=False,
                                   gridspec_kw={"height_ratios": [3, 1]})
    pairs = [plot_fit(result, ax=(axes[0, e], axes[1, e]), n_points=n_points, experiment=e)[1] for e in range(E)]
    for e, (top, _) in enumerate(pairs):
        top.set_title(f"experiment {e}: " + top.get_title(), fontsize="small")
    return fig, pairs


def plot_convergence(result: "FitResult", ax=None, *, values: bool = False):
    """Each unknown and the SSE against iteration (with estimated sigmas or a ``sigma(p)`` function,
    the objective ``SSE + 2 sum log sigma`` instead, on a linear axis: it may be negative).

    Parameters
    ----------
    result : FitResult
    ax : matplotlib Axes or pair of Axes, optional
        ``None``: a new figure with the unknowns above and the SSE below; a pair: drawn
        there; one Axes: the unknowns only.
    values : bool
        ``False`` (default): each unknown's relative distance to its final value,
        ``|u_i - u_final| / max(|u_final|, tiny)``, on a log scale (quadratic convergence shows
        as a parabola; the final iterate, at distance 0, is not drawn). ``True``: the values.

    Returns
    -------
    (Figure, (Axes, Axes or None))
    """
    from .report import unknown_values

    fig, (ax_u, ax_sse) = _two_axes(ax, sharex=True, height_ratios=(2, 1))
    history = result.history
    iters = [rec.iteration for rec in history]
    table = torch.tensor([unknown_values(result, rec) for rec in history], dtype=torch.float64)
    if table.numel() == 0:
        table = table.reshape(0, len(result.unknown_names))
    final = table[-1] if table.shape[0] else torch.zeros(len(result.unknown_names), dtype=torch.float64)
    for i, name in enumerate(result.unknown_names):
        col = table[:, i]
        if values:
            ax_u.plot(iters, col.numpy(), "o-", label=name)
        else:
            ref = max(abs(float(final[i])), torch.finfo(torch.float64).tiny)
            dist = (col - final[i]).abs() / ref
            dist = torch.where(dist > 0, dist, torch.full_like(dist, math.nan))
            ax_u.semilogy(iters, dist.numpy(), "o-", label=name)
    ax_u.set_ylabel("value" if values else "|u - u_final| / |u_final|")
    ax_u.set_title(f"{result.method}: {result.status.name} after {result.iterations} iterations")
    ax_u.legend(fontsize="small")
    if ax_sse is not None:
        sse = torch.tensor([rec.sse for rec in history], dtype=torch.float64)
        if result.sigma_function or result.sigma is not None:  # SSE + 2 sum log sigma: of any sign
            ax_sse.plot(iters, sse.numpy(), "o-", color="k")
            ax_sse.set_ylabel("2 NLL - n log 2 pi")
        else:
            pos = torch.where(sse > 0, sse, torch.full_like(sse, math.nan))
            ax_sse.semilogy(iters, pos.numpy(), "o-", color="k")
            ax_sse.set_ylabel("SSE")
        ax_sse.set_xlabel("iteration")
    else:
        ax_u.set_xlabel("iteration")
    return fig, (ax_u, ax_sse)


def plot_profile(profile: "ProfileResult", ax=None):
    """The profile ``SSE(value)`` (a likelihood profile's ``2 NLL(value)``) with its threshold, the
    profile interval and the Wald interval.

    Returns
    -------
    (Figure, Axes)
    """
    plt = _pyplot()
    if ax is None:
        fig, ax = plt.subplots(figsize=(6, 4))
    else:
        fig = ax.figure
    what = "2 NLL" if profile.likelihood else "SSE"
    ax.plot(profile.values.numpy(), profile.sse.numpy(), "o-", ms=3, label=f"profile {what}")
    ax.axhline(profile.threshold, color="r", ls="--", lw=0.8, label=f"{100 * profile.level:g}% threshold")
    ax.axvline(profile.estimate, color="k", lw=0.8, label="estimate")
    for end, closed in zip(profile.interval, profile.closed):
        if closed:
            ax.axvline(end, color="r", lw=0.8)
    for end in profile.wald:
        if math.isfinite(end):
            ax.axvline(end, color="0.5", ls=":", lw=0.8)
    ax.plot([], [], color="r", lw=0.8, label="profile interval")
    ax.plot([], [], color="0.5", ls=":", lw=0.8, label="Wald interval")
    ax.set_xlabel(profile.name)
    ax.set_ylabel("optimal 2 x negative log-likelihood" if profile.likelihood else "optimal SSE")
    ax.legend(fontsize="small")
    return fig, ax


def plot_comparison(comparison: "Comparison", ax=None, n_points: int = 400):
    """Measured and simulated outputs of :func:`torchql.compare`, one panel per output, each
    labelled with its fit percentage (NRMSE).

    Parameters
    ----------
    comparison : Comparison
    ax : matplotlib Axes or sequence of ``K`` Axes, optional
        ``None``: a new figure with one panel per output.
    n_points : int
        Points of the simulated curve.

    Returns
    -------
    (Figure, list of Axes)
    """
    plt = _pyplot()
    K = comparison.y.shape[1]
    if ax is None:
        fig, axes = plt.subplots(K, 1, sharex=True, figsize=(7, 2.6 * K + 0.6), squeeze=False)
        axes = list(axes[:, 0])
    else:
        axes = [ax] if hasattr(ax, "plot") else list(ax)
        if len(axes) != K:
            raise ValueError(f"`ax` must be one Axes per output ({K}); received {len(axes)}")
        fig = axes[0].figure
    t = comparison.t.cpu().numpy()
    t_curve, curve = comparison.t, comparison.predicted
    if comparison.curve is not None and comparison.t.numel() > 1:  # the simulation between the samples too
        t_curve = torch.linspace(float(comparison.t[0]), float(comparison.t[-1]), n_points, dtype=comparison.t.dtype,
                                 device=comparison.t.device)
        with torch.no_grad():
            curve = comparison.curve(t_curve)
    for k, axis in enumerate(axes):
        name = comparison.output_names[k]
        axis.plot(t, comparison.y[:, k].cpu().numpy(), ".", color="0.35", label=f"{name} measured")
        axis.plot(t_curve.cpu().numpy(), curve[:, k].cpu().numpy(), "-",
                  label=f"{name} simulated: fit {comparison.fit_percent[k].item():.2f}%")
        axis.set_ylabel(name)
        axis.legend(loc="best", fontsize="small")
    axes[-1].set_xlabel("t")
    return fig, axes
