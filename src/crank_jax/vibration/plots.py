"""Figures of the vibration analyses: a forced response curve (stable orbits solid,
unstable dashed, with the linear response and the backbone) and a stability chart."""

from __future__ import annotations

import os

import numpy as np

from ..report.plotting import pyplot, save_figure

__all__ = ["plot_response", "plot_chart"]


def _runs(mask: np.ndarray):
    """(start, stop) index pairs of the runs of equal values in `mask`, each run extended
    by one point so that consecutive runs meet."""
    edges = np.flatnonzero(np.diff(mask.astype(int)) != 0) + 1
    starts = np.concatenate([[0], edges])
    stops = np.concatenate([edges, [mask.size]])
    return [(a, min(b + 1, mask.size)) for a, b in zip(starts, stops)]


def plot_response(resp, path: str | os.PathLike, title: str = "") -> None:
    """Amplitude (rad) against forcing frequency (Hz) of a [`ForcedResponse`][
    crank_jax.vibration.ForcedResponse], saved to `path`."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    lin = resp.linear
    ax.plot(lin["freq_hz"], lin["amplitude"], color="0.6", lw=1, label="linear response")
    if "backbone_freq_hz" in lin:
        ax.plot(lin["backbone_freq_hz"], lin["backbone_amplitude"], color="tab:green", lw=1,
                ls=":", label="backbone")
    for b in resp.branches:
        stable = np.asarray(b.stable)
        labels = {True: "stable", False: "unstable"}
        for a, z in _runs(stable):
            s = bool(stable[a])
            ax.plot(b.freq_hz[a:z], b.amplitude[a:z], color="tab:blue",
                    ls="-" if s else "--", lw=1.6, label=labels.pop(s, None))
    for fo in resp.folds:
        ax.plot(fo["freq_hz"], fo["amplitude"], "o", color="tab:red", ms=4)
    top = max(float(np.nanmax(b.amplitude)) for b in resp.branches)
    ax.set_ylim(0, 1.15 * top)
    ax.set_xlim(min(lin["freq_hz"]), max(lin["freq_hz"]))
    ax.set_xlabel("forcing frequency (Hz)")
    ax.set_ylabel("amplitude (phi_max - phi_min)/2 (rad)")
    ax.set_title(title or f"forced response ({resp.drive} drive); folds: red dots")
    ax.legend(loc="upper right", fontsize=8)
    save_figure(fig, path)


def plot_chart(chart, path: str | os.PathLike, title: str = "") -> None:
    """A [`Chart`][crank_jax.vibration.Chart]: the largest Floquet multiplier modulus over
    (frequency, amplitude), the unstable region (> 1) outlined, saved to `path`."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    fm = np.asarray(chart.floquet_max)
    im = ax.pcolormesh(chart.freq_hz, chart.amplitude, np.log10(fm), shading="nearest",
                       cmap="RdBu_r", vmin=-0.3, vmax=0.3)
    if (fm > 1).any() and (fm < 1).any():
        ax.contour(chart.freq_hz, chart.amplitude, fm, levels=[1.0], colors="k",
                   linewidths=1)
    fig.colorbar(im, ax=ax, label="log10 max |Floquet multiplier|")
    ax.set_xlabel("slider-force frequency (Hz)")
    ax.set_ylabel("slider-force amplitude P1 (N)")
    ax.set_title(title or "stability of the rest position (unstable inside the black line)")
    save_figure(fig, path)
