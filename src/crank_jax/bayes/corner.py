"""Corner plot of a posterior, with the fit's Laplace (linearised) 95% ellipses."""

from __future__ import annotations

import os

import numpy as np

from ..report.plotting import pyplot, save_figure
from ..runtime.io import printable

__all__ = ["plot_corner", "plot_design", "CHI2_2_95"]

#: sqrt of the 95% quantile of chi-square with 2 degrees of freedom: the radius, in
#: standard deviations, of a 2-d Gaussian's 95% ellipse.
CHI2_2_95 = float(np.sqrt(-2 * np.log(0.05)))


def _ellipse(mean: np.ndarray, cov: np.ndarray, n: int = 100) -> np.ndarray:
    """(n, 2) points of the 95% ellipse of N(mean, cov) (2-d)."""
    t = np.linspace(0, 2 * np.pi, n)
    w, V = np.linalg.eigh(cov)
    circle = np.stack([np.cos(t), np.sin(t)], axis=1) * np.sqrt(np.maximum(w, 0)) * CHI2_2_95
    return mean + circle @ V.T


def plot_corner(post, path: str | os.PathLike, title: str = "") -> None:
    """Draw a [`Posterior`][crank_jax.Posterior]: histograms of each parameter's draws on
    the diagonal, scatter of each pair below it, and the fit's Laplace 95% interval (lines)
    and ellipse (red) where the fit gives standard errors."""
    plt = pyplot()
    names = list(post.names)
    p = len(names)
    fig, axes = plt.subplots(p, p, figsize=(2.2 * p + 1, 2.2 * p + 1), squeeze=False)
    x = {n: np.asarray(post.draws[n]).reshape(-1) for n in names}
    se = post.fit.stderr
    corr = np.asarray(post.fit.correlation)
    for i, ni in enumerate(names):
        for j, nj in enumerate(names):
            ax = axes[i, j]
            if j > i:
                ax.axis("off")
                continue
            if i == j:
                ax.hist(x[ni], bins=40, density=True, color="C0", alpha=0.7)
                if se[ni] is not None:
                    m = post.fit.values[ni]
                    for v in (m - 1.96 * se[ni], m + 1.96 * se[ni]):
                        ax.axvline(v, color="C3", lw=1)
                ax.set_yticks([])
            else:
                ax.plot(x[nj], x[ni], ".", ms=1, alpha=0.3, color="C0")
                if se[ni] is not None and se[nj] is not None:
                    s = np.array([se[nj], se[ni]])
                    cov = np.outer(s, s) * np.array([[1, corr[j, i]], [corr[i, j], 1]])
                    e = _ellipse(np.array([post.fit.values[nj], post.fit.values[ni]]), cov)
                    ax.plot(e[:, 0], e[:, 1], color="C3", lw=1)
            if i == p - 1:
                ax.set_xlabel(nj)
            if j == 0 and i > 0:
                ax.set_ylabel(ni)
            ax.tick_params(labelsize=6)
    fig.suptitle((printable(title) + "\n" if title else "") + f"posterior: {post.chains} chains x "
                 f"{post.n_draws} draws, {post.divergences} divergences; red: Laplace 95%",
                 fontsize=9)
    save_figure(fig, path)


def plot_design(d, path: str | os.PathLike) -> None:
    """Draw a [`Design`][crank_jax.Design]: the designed torque over the record (top) and
    each parameter's predicted 95% interval, relative to its value, designed against
    baseline (bottom, log scale)."""
    plt = pyplot()
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 6))
    ts = np.linspace(0.0, d.scene.t1, 4000)
    ax1.plot(ts, np.asarray(d.torque(ts)), lw=0.8)
    ax1.set_xlabel("t [s]")
    ax1.set_ylabel("tau [N*m]")
    ax1.set_title(f"designed torque ({d.criterion}-optimal), peak {d.peak:.3g} N*m", fontsize=9)
    names = list(d.names)
    mech = d.scene.mech.as_dict()
    for k, (label, color) in enumerate((("baseline", "C7"), ("designed", "C0"))):
        rel = [1.96 * d.predicted_stderr[n][label] / abs(mech.get(n, 1.0) or 1.0)
               for n in names]
        ax2.bar(np.arange(len(names)) + 0.4 * k - 0.2, rel, 0.4, color=color, label=label)
    ax2.set_yscale("log")
    ax2.set_xticks(np.arange(len(names)), names)
    ax2.set_ylabel("predicted 95% half-width / value")
    ax2.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)
