"""The summary report of many independent fits
([`fit_many`][crank_jax.fleet.many.fit_many], `crank-jax fit ... --each --report`): a
table of the records with their estimates, standard errors and verdicts, and a figure of
the estimates' spread over the records, in the page the single fit's report uses."""

from __future__ import annotations

import math

import numpy as np

from .context import cell, fmt, unit, verdicts
from .figures import embed
from .plotting import pyplot
from .provenance import provenance

__all__ = ["fleet_context", "fleet_figures"]


def _verdict(res, alone: str | None) -> tuple[str, str]:
    """(CSS class, words) of one record: converged or not, identifiable, by whom."""
    how = "side by side" if alone is None else "by fit itself"
    if not res.converged:
        return "bad", f"did NOT converge ({res.message}); {how}"
    if res.identifiable is False:
        return "bad", f"converged, NOT identifiable; {how}"
    return "ok", f"converged in {res.iterations} iterations; {how}"


def _records(fleet, labels, names) -> list[dict]:
    rows = []
    for label, res, alone in zip(labels, fleet.results, fleet.alone):
        cls, words = _verdict(res, alone)
        rows.append({"label": label, "cls": cls, "verdict": words,
                     "rms": cell(res.rms_residual),
                     "values": [(cell(res.values.get(n)), cell(res.stderr.get(n)))
                                for n in names]})
    return rows


def _spread(fleet, names, labels):
    """Each free name's estimate per record with its standard error (error bars), and the
    median across the records (dashed)."""
    plt = pyplot()
    fig, axes = plt.subplots(len(names), 1, figsize=(8, 1.9 * len(names) + 0.6),
                             sharex=True, squeeze=False)
    x = np.arange(len(fleet.results))
    for ax, n in zip(axes[:, 0], names):
        v = np.array([r.values.get(n, math.nan) for r in fleet.results], dtype=float)
        se = np.array([r.stderr.get(n) or math.nan for r in fleet.results], dtype=float)
        ax.errorbar(x, v, yerr=np.where(np.isfinite(se), se, 0.0), fmt="o", ms=2, lw=0.6)
        if np.any(np.isfinite(v)):
            ax.axhline(float(np.nanmedian(v)), color="C3", ls="--", lw=0.8)
        u = unit(n)
        ax.set_ylabel(f"{n} ({u})" if u else n)
    axes[-1, 0].set_xlabel("record (in the order given)")
    if len(labels) <= 30:
        axes[-1, 0].set_xticks(x, labels, rotation=60, ha="right", fontsize="small")
    return fig


def fleet_figures(fleet, names, labels) -> list[dict]:
    """The report's figure (markup and caption)."""
    return [{"title": "each record's estimate with its standard error; dashed: the median "
                      "over the records",
             "markup": embed(_spread(fleet, names, labels), 3 * len(names) * len(labels))}]


def _summary(fleet, names) -> list[tuple[str, str]]:
    """Over the converged records: each name's median and spread (standard deviation) of
    the estimates, beside its median standard error."""
    out = []
    ok = [r for r in fleet.results if r.converged]
    for n in names:
        v = np.array([r.values[n] for r in ok], dtype=float)
        se = np.array([r.stderr[n] for r in ok if r.stderr.get(n) is not None], dtype=float)
        if v.size:
            spread = float(np.std(v, ddof=1)) if v.size > 1 else math.nan
            med_se = float(np.median(se)) if se.size else math.nan
            out.append((f"{n} ({unit(n) or '-'})", f"median {fmt(float(np.median(v)))}, "
                        f"spread {fmt(spread)}, median standard error {fmt(med_se)}"))
    return out


def fleet_context(fleet, labels=None, *, scene=None, command=None, title: str = "") -> dict:
    """The template's values for a [`FleetResult`][crank_jax.fleet.many.FleetResult];
    `labels` name the records (default: their files' names, else their index)."""
    res = fleet.results
    labels = [str(x) for x in (labels or [r.data[0].source if r.data else i
                                          for i, r in enumerate(res)])]
    names = list(dict.fromkeys(n for r in res for n in r.names))
    n, ok = len(res), sum(r.converged for r in res)
    alone = sum(a is not None for a in fleet.alone)
    bad_id = sum(r.identifiable is False for r in res)
    judged = [("Convergence", ("ok" if ok == n else "bad",
                               f"{ok} of {n} records converged.")),
              ("Identifiability", ("ok" if bad_id == 0 else "bad",
                                   f"{bad_id} of {n} records not identifiable.")),
              ("Fleet", ("info", f"{n - alone} records fitted side by side, {alone} by fit "
                                 f"itself, in {fleet.seconds:.1f} s."))]
    warnings = [f"{label}: {w}" for label, r in zip(labels, res) if not r.converged
                for w in r.warnings[:1]]
    return {"kind": "fleet", "title": title or f"crank-jax fits of {n} records",
            "verdicts": verdicts(judged), "warnings": warnings, "names": names,
            "units": [unit(x) for x in names], "records": _records(fleet, labels, names),
            "summary": _summary(fleet, names), "estimates": [], "correlation": None,
            "scores": [], "figures": fleet_figures(fleet, names, labels), "start_from": "",
            "provenance": provenance(command=command, scene=scene, sources=labels)}
