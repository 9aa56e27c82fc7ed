"""The report's figures, drawn with matplotlib and embedded in the page: inline SVG
(sharp when printed), or a base64 PNG above [`SVG_MAX_POINTS`][] plotted points, where
an SVG would grow to megabytes."""

from __future__ import annotations

import base64
import io

import numpy as np

from .fit_plot import plot_acf
from .plotting import printable_texts, pyplot

__all__ = ["embed", "fit_figures", "validation_figures", "SVG_MAX_POINTS"]

#: Plotted points above which a figure is embedded as PNG rather than SVG.
SVG_MAX_POINTS = 20_000


def embed(fig, points: int = 0) -> str:
    """The figure as HTML markup (an `<svg>` element or a `data:` PNG `<img>`); closes it."""
    buf = io.BytesIO()
    printable_texts(fig)
    try:
        if points <= SVG_MAX_POINTS:
            # No date: the same result gives the same page.
            fig.savefig(buf, format="svg", bbox_inches="tight", metadata={"Date": None})
            text = buf.getvalue().decode("utf-8")
            return text[text.index("<svg"):]  # drop the XML prolog and DOCTYPE
        fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
        data = base64.b64encode(buf.getvalue()).decode("ascii")
        return f'<img alt="figure" src="data:image/png;base64,{data}">'
    finally:
        pyplot().close(fig)


def _data_and_residuals(result):
    """Per channel, its data against the fit (tall panel) and its residuals, each in the
    channel's own SI unit (a slide-only record has no angle to draw)."""
    from .fit_plot import plot_channel

    plt = pyplot()
    names = list(result.channels or {"phi": None})
    fig, axes = plt.subplots(2 * len(names), 1, figsize=(9, 0.5 + 5 * len(names)),
                             sharex=True, gridspec_kw={"height_ratios": [2, 1] * len(names)})
    for c, name in enumerate(names):
        plot_channel(axes[2 * c], axes[2 * c + 1], result, name)
    fig.tight_layout()
    return fig, 2 * len(names) * sum(d.n for d in result.data)


def _acf(diag):
    fig, ax = pyplot().subplots(figsize=(7, 3.2))
    plot_acf(ax, diag)
    fig.tight_layout()
    return fig


def fit_figures(result) -> list[dict]:
    """Data against fit with the residuals, and the residuals' autocorrelation (when the
    fit has residual diagnostics), as `{"title", "markup"}` dicts."""
    fig, points = _data_and_residuals(result)
    out = [{"title": "Data against fit, and the residuals", "markup": embed(fig, points)}]
    if result.diagnostics is not None:
        out.append({"title": "Autocorrelation of the residuals",
                    "markup": embed(_acf(result.diagnostics))})
    return out


def _prediction(val):
    """Per channel, its data against the open-loop prediction and the error, each in the
    channel's own SI unit; the initial-state window shaded."""
    plt = pyplot()
    chans = val.channels or {"phi": {"unit": "rad"}}
    preds = val.predicted_channels or {"phi": val.predicted}
    data = val.data_channels or {"phi": val.phi}
    fig, axes = plt.subplots(2 * len(chans), 1, figsize=(9, 0.5 + 5 * len(chans)),
                             sharex=True, gridspec_kw={"height_ratios": [2, 1] * len(chans)})
    t0 = float(val.ts[0])
    for ax in axes:
        ax.axvspan(t0, t0 + val.init_window, color="0.9", zorder=0)
        ax.grid(alpha=0.3)
    how = ("open loop" if getattr(val, "horizon", None) is None
           else f"{val.horizon:g} s ahead")
    for c, (name, info) in enumerate(chans.items()):
        ax1, ax2 = axes[2 * c], axes[2 * c + 1]
        y, yhat = np.asarray(data[name]), np.asarray(preds[name])
        ax1.plot(val.ts, y, ".", ms=2, color="C0", label="data")
        ax1.plot(val.ts, yhat, "-", lw=1, color="C1", label=f"prediction ({how})")
        ax1.set_ylabel(f"{name} [{info['unit']}]")
        ax1.legend(loc="upper right", fontsize=8)
        ax2.plot(val.ts, y - yhat, "-", lw=0.8, color="C3")
        ax2.set_ylabel(f"data - prediction [{info['unit']}]")
    axes[-1].set_xlabel("t [s] (shaded: initial-state window)")
    fig.tight_layout()
    return fig, 3 * len(chans) * len(val.ts)


def validation_figures(val, diag) -> list[dict]:
    """Data against the open-loop prediction with its error, and the error's
    autocorrelation over the scored samples (`diag`, or `None`)."""
    fig, points = _prediction(val)
    out = [{"title": "Data against the open-loop prediction, and the error",
            "markup": embed(fig, points)}]
    if diag is not None:
        out.append({"title": "Autocorrelation of the prediction error (scored samples)",
                    "markup": embed(_acf(diag))})
    return out
