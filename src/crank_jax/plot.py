"""Figures (matplotlib, Agg backend: works with no display)."""

from __future__ import annotations

import os

import numpy as np

from .io import atomic_write

__all__ = ["plot_trajectory", "save_figure"]


def pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | os.PathLike, dpi: int = 120) -> None:
    """Save a matplotlib figure atomically (format from the file suffix) and close it."""
    fmt = os.path.splitext(str(path))[1].lstrip(".") or "png"
    with atomic_write(path, "wb") as f:
        fig.savefig(f, format=fmt, dpi=dpi, bbox_inches="tight")
    pyplot().close(fig)


def plot_trajectory(traj, path: str | os.PathLike, title: str = "") -> None:
    """Draw phi(t) and dphi(t) of a [`Trajectory`][] to an image file."""
    plt = pyplot()
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    t = np.asarray(traj.ts)
    ax1.plot(t, np.asarray(traj.phi), lw=1.0)
    ax1.set_ylabel("phi [rad]")
    ax2.plot(t, np.asarray(traj.dphi), lw=1.0, color="C1")
    ax2.set_ylabel("dphi/dt [rad/s]")
    ax2.set_xlabel("t [s]")
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
    if title:
        ax1.set_title(title, fontsize=10)
    save_figure(fig, path)
