"""Figures (matplotlib, Agg backend: works with no display)."""

from __future__ import annotations

import os

import numpy as np

from ..runtime.io import atomic_write, printable

__all__ = ["plot_trajectory", "save_figure", "printable_texts"]


def pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def printable_texts(fig) -> None:
    """Make every text of `fig` valid Unicode ([`printable`][crank_jax.runtime.io.printable]): a
    title naming a file whose name is not UTF-8 crashed matplotlib's font layout after
    the work."""
    from matplotlib.text import Text

    for t in fig.findobj(Text):
        text = t.get_text()
        if isinstance(text, str) and printable(text) != text:
            t.set_text(printable(text))


def save_figure(fig, path: str | os.PathLike, dpi: int = 120) -> None:
    """Save a matplotlib figure atomically (format from the file suffix) and close it."""
    printable_texts(fig)
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
        ax1.set_title(printable(title), fontsize=10)
    save_figure(fig, path)
