"""The figure of a validation: each channel's data and prediction, and the error below."""

from __future__ import annotations

import os

from ..runtime.io import printable
from .plotting import pyplot, save_figure

__all__ = ["plot_validation"]


def _how(val) -> str:
    return ("prediction (open loop)" if val.horizon is None
            else f"prediction ({val.horizon:g} s ahead, windows)")


def plot_validation(val, path: str | os.PathLike, title: str = "") -> None:
    """Draw, for each channel, data and prediction and below them the error; the
    initial-state window is shaded.

    `val`: a [`Validation`][crank_jax.validation.kstep.Validation] (read through its
    fields, so the report does not import the fit); `path`: the figure file (its suffix
    picks the format), written atomically."""
    plt = pyplot()
    chans = val.channels or {"phi": {"unit": "rad"}}
    preds = val.predicted_channels or {"phi": val.predicted}
    data = val.data_channels or {"phi": val.phi}
    fig, axes = plt.subplots(2 * len(chans), 1, figsize=(9, 1 + 5 * len(chans)), sharex=True,
                             gridspec_kw={"height_ratios": [2, 1] * len(chans)})
    t0 = float(val.ts[0])
    for ax in axes:
        ax.axvspan(t0, t0 + val.init_window, color="0.9", zorder=0)
        ax.grid(alpha=0.3)
    for c, (name, info) in enumerate(chans.items()):
        ax1, ax2 = axes[2 * c], axes[2 * c + 1]
        y = data[name]
        ax1.plot(val.ts, y, ".", ms=2, color="C0", label="data")
        ax1.plot(val.ts, preds[name], "-", lw=1, color="C1", label=_how(val))
        ax1.set_ylabel(f"{name} [{info['unit']}]")
        ax1.legend(loc="upper right", fontsize=8)
        ax2.plot(val.ts, y - preds[name], "-", lw=0.8, color="C3")
        ax2.set_ylabel(f"data - prediction [{info['unit']}]")
    axes[-1].set_xlabel("t [s] (shaded: initial-state window)")
    unit = next(iter(chans.values()))["unit"]
    head = printable(title) + "\n" if title else ""  # a file name that is not UTF-8
    axes[0].set_title(head + f"fit {val.fit_percent:.2f}%, rms "
                      f"{val.rms:.3g} {unit}, max |error| {val.max_abs:.3g} {unit} over "
                      f"{val.n_samples} samples", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)
