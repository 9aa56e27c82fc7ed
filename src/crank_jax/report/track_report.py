"""The HTML report of a tracked record: the parameters' paths with their 95% bands and
the alarms, the normalised innovations and the change test's statistic, in the page the
fit's and the validation's reports use."""

from __future__ import annotations

import numpy as np

from ..model.params import UNITS
from .context import cell, fmt, verdicts
from .figures import embed
from .plotting import pyplot
from .provenance import provenance

__all__ = ["track_context", "track_figures"]


def _paths(res):
    plt = pyplot()
    names = list(res.values)
    fig, axes = plt.subplots(len(names), 1, figsize=(8, 2.4 * len(names)), sharex=True,
                             squeeze=False)
    for ax, n in zip(axes[:, 0], names):
        lo, hi = res.band(n)
        ax.fill_between(res.t, lo, hi, alpha=0.3, label="95% band")
        ax.plot(res.t, res.values[n], lw=1, label="estimate")
        for a in res.alarms:
            ax.axvline(a["t"], color="C3", lw=1, ls="--")
        ax.set_ylabel(f"{n} ({UNITS[n]})")
    axes[0, 0].legend(loc="best", fontsize="small")
    axes[-1, 0].set_xlabel("t (s)")
    return fig


def _innovations(res):
    plt = pyplot()
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 4.5), sharex=True)
    a1.plot(res.t, res.innovations, lw=0.5)
    a1.set_ylabel("normalised innovation")
    a2.plot(res.t, res.statistic, lw=1)
    a2.axhline(res.settings["threshold"], color="C3", ls="--", lw=1, label="threshold")
    a2.set_ylabel("CUSUM statistic")
    a2.set_xlabel("t (s)")
    a2.legend(loc="best", fontsize="small")
    return fig


def track_figures(res) -> list[dict]:
    """The report's figures (markup and caption)."""
    points = int(res.t.size * (len(res.values) + 2))
    return [{"title": "the free parameters with their 95% bands; dashed: alarms",
             "markup": embed(_paths(res), points)},
            {"title": "normalised innovations (white, unit variance when the model holds) "
                      "and the change test's statistic", "markup": embed(_innovations(res),
                                                                        points)}]


def track_context(res, *, scene=None, command=None, title: str = "") -> dict:
    """The template's values for a [`TrackResult`][crank_jax.online.tracked.TrackResult]."""
    scores = []
    for n, v in res.values.items():
        scores += [(f"{n} at the end", cell(float(v[-1])), UNITS[n]),
                   (f"{n}: standard error", cell(float(res.stderr[n][-1])), UNITS[n])]
    e = np.asarray(res.innovations)
    scores.append(("innovation variance", cell(float(np.mean(e**2))), ""))
    if res.alarms:
        words = "; ".join(f"at {fmt(a['t'])} s: " + ", ".join(
            f"{n} {fmt(a['before'][n])} -> {fmt(a['after'][n])}" for n in a["parameters"])
            for a in res.alarms)
        verdict = ("bad", f"{len(res.alarms)} change alarm(s): {words}.")
    else:
        verdict = ("ok", "No change alarm (at most "
                   f"{fmt(res.settings['false_alarm_rate_per_hour'])} false alarm per hour).")
    return {"kind": "track", "title": title or "crank-jax tracking report",
            "verdicts": verdicts([("Changes", verdict)]), "summary": [], "estimates": [],
            "correlation": None, "scores": scores, "warnings": [],
            "figures": track_figures(res), "start_from": res.settings.get("start", ""),
            "provenance": provenance(command=command, scene=scene, sources=[res.source])}


