"""Figure of a fit: data against model, residuals, and the parameter correlations."""

from __future__ import annotations

import math
import os

import numpy as np

from ..runtime.io import printable
from .plotting import pyplot, save_figure

__all__ = ["plot_fit", "plot_channel", "plot_acf"]


def plot_fit(result, path: str | os.PathLike, title: str = "") -> None:
    """Draw a [`FitResult`][]: for each channel its data and fit, then its residuals; the
    correlation matrix of the estimates (bottom left; blank where undefined) and the
    residuals' autocorrelation with its white-noise band (bottom right)."""
    plt = pyplot()
    names_ch = list(result.channels or {"phi": None})
    rows = 2 * len(names_ch)
    fig = plt.figure(figsize=(10, 5 + 4 * len(names_ch)))
    gs = fig.add_gridspec(rows + 1, 2, height_ratios=[2, 1] * len(names_ch) + [2])
    first = None
    for c, name in enumerate(names_ch):
        ax1 = fig.add_subplot(gs[2 * c, :], sharex=first)
        ax2 = fig.add_subplot(gs[2 * c + 1, :], sharex=ax1)
        first = first or ax1
        plot_channel(ax1, ax2, result, name)
    state = "converged" if result.converged else "NOT converged"
    ident = ", NOT identifiable" if result.identifiable is False else ""
    unit = (result.channels or {}).get(names_ch[0], {}) or {}
    first.set_title((printable(title) + "\n" if title else "") + f"{state}{ident}; rms residual "
                    f"{result.rms_residual:.3g} {unit.get('unit', 'rad')}; condition number "
                    f"{result.condition_number:.3g}", fontsize=9)
    gs_last = rows
    ax3 = fig.add_subplot(gs[gs_last, 0])
    corr = np.ma.masked_invalid(np.asarray(result.correlation, dtype=float))
    im = ax3.imshow(corr, vmin=-1, vmax=1, cmap="RdBu_r")
    names = list(result.names)
    ax3.set_xticks(range(len(names)), names, rotation=45, fontsize=8)
    ax3.set_yticks(range(len(names)), names, fontsize=8)
    for i in range(len(names)):
        for j in range(len(names)):
            if not np.ma.is_masked(corr[i, j]):
                ax3.text(j, i, f"{corr[i, j]:.2f}", ha="center", va="center", fontsize=7)
    ax3.set_title("correlation of the estimates", fontsize=9)
    fig.colorbar(im, ax=ax3, shrink=0.8)
    ax4 = fig.add_subplot(gs[gs_last, 1])
    if result.diagnostics is not None:
        plot_acf(ax4, result.diagnostics)
    else:
        ax4.text(0.5, 0.5, "no residual diagnostics\n(the fit did not converge)",
                 ha="center", va="center", fontsize=9, transform=ax4.transAxes)
        ax4.set_axis_off()
    fig.tight_layout()
    save_figure(fig, path)


def plot_channel(ax1, ax2, result, name: str) -> None:
    """One channel's data against the fit (ax1) and its residuals (ax2), SI."""
    fitted = result.fitted_channels or [{"phi": f} for f in result.fitted]
    unit = ((result.channels or {}).get(name) or {}).get("unit", "rad")
    for i, (d, f) in enumerate(zip(result.data, fitted)):
        y = dict((s.name, v) for s, v in d.outputs()).get(name)
        if y is None or name not in f:
            continue
        label = f" (record {i})" if len(result.data) > 1 else ""
        ax1.plot(d.ts, y, ".", ms=2, color=f"C{2 * i}", label="data" + label)
        ax1.plot(d.ts, f[name], "-", lw=1, color=f"C{2 * i + 1}", label="fit" + label)
        ax2.plot(d.ts, y - f[name], ".", ms=2, color=f"C{2 * i}")
    ax1.set_ylabel(f"{name} [{unit}]")
    ax1.legend(loc="upper right", fontsize=8)
    ax2.set_ylabel(f"data - fit [{unit}]")
    ax2.set_xlabel("t [s]")
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)


def plot_acf(ax, diag) -> None:
    """Draw the residual autocorrelation on a matplotlib axis, with the +-1.96/sqrt(n) band
    that white residuals stay inside 95% of the time, and the test result in the title.
    `diag`: a fit's [`Diagnostics`][crank_jax.stats.diagnostics.Diagnostics]."""
    lags = np.arange(diag.acf.shape[0])
    ax.vlines(lags, 0.0, diag.acf, color="C0", lw=1.5)
    ax.plot(lags, diag.acf, "o", ms=3, color="C0")
    band = 1.959963984540054 / math.sqrt(diag.n_samples)
    ax.axhspan(-band, band, color="0.85", zorder=0)
    ax.axhline(0.0, color="k", lw=0.5)
    ax.set_xlabel("lag [samples]")
    ax.set_ylabel("residual autocorrelation")
    verdict = "white" if diag.white else "NOT white"
    ax.set_title(f"residuals {verdict}: Ljung-Box p = {diag.ljung_box_p:.2g}, "
                 f"rho_1 = {diag.lag1_autocorrelation:.2f}, n_eff = "
                 f"{diag.effective_samples:.0f} of {diag.n_samples}", fontsize=9)
