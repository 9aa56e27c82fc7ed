"""What a report shows, as plain values for the template: the `to_json()` documents'
numbers formatted for reading, the verdicts in words, the figures and the provenance."""

from __future__ import annotations

import math
import re

from ..model.loads import LOAD_PARAMS
from ..model.params import UNITS
from .figures import fit_figures, validation_figures
from .provenance import provenance

__all__ = ["fit_context", "validation_context", "unit", "fmt", "cell", "verdicts",
           "VERDICT_CLASSES"]

_STATE_UNITS = {"phi0": "rad", "dphi0": "rad/s"}
_ROLE_UNITS = {"freq_hz": "Hz", "phase": "rad"}
_SIDE_UNITS = {"load": "N", "torque": "N*m"}
#: CSS class of a verdict: good, bad, not judged, or a plain statement.
VERDICT_CLASSES = ("ok", "bad", "none", "info")


def unit(name: str) -> str:
    """SI unit of a reported parameter name (`phi0[1]` is `phi0`'s), `""` if unknown."""
    base = re.sub(r"\[\d+\]$", "", name)
    if base in UNITS:
        return UNITS[base]
    if base in _STATE_UNITS:
        return _STATE_UNITS[base]
    if base in LOAD_PARAMS:
        side, role = LOAD_PARAMS[base]
        return _ROLE_UNITS.get(role, _SIDE_UNITS[side])
    return ""


def fmt(x) -> str:
    """6 significant digits; an en dash for a missing or non-finite value."""
    if x is None or not math.isfinite(x):
        return "\u2013"
    return f"{x:.6g}"


def cell(x) -> dict:
    return {"text": fmt(x), "full": "" if x is None else repr(float(x))}


def _estimates(doc: dict) -> list[dict]:
    rows = []
    for name, e in doc["estimates"].items():
        ci = e["ci95"] or [None, None]
        prof = e.get("profile", {}).get("ci95")
        rows.append({"name": name, "unit": unit(name), "start": cell(e["start"]),
                     "value": cell(e["value"]), "stderr": cell(e["stderr"]),
                     "lo": cell(ci[0]), "hi": cell(ci[1]),
                     "profile": None if prof is None else [cell(prof[0]), cell(prof[1])]})
    return rows


def _heat(r) -> dict:
    """A correlation cell: its text and its colour on matplotlib's RdBu_r (-1 blue, +1 red);
    grey where undefined."""
    if r is None:
        return {"text": "\u2013", "full": "", "bg": "#dddddd", "fg": "#000000"}
    import matplotlib

    rgba = matplotlib.colormaps["RdBu_r"]((r + 1.0) / 2.0)
    return {"text": f"{r:.2f}", "full": repr(float(r)), "bg": matplotlib.colors.to_hex(rgba),
            "fg": "#ffffff" if abs(r) > 0.6 else "#000000"}


def _correlation(doc: dict) -> dict:
    names = list(doc["estimates"])
    return {"names": names, "rows": [[_heat(doc["estimates"][a]["correlation"][b])
                                      for b in names] for a in names]}


def _convergence(res) -> tuple[str, str]:
    how = res.strategy or f"{res.shooting} shooting"
    if res.converged:
        return "ok", (f"The fit converged after {res.iterations} iterations in "
                      f"{res.seconds:.1f} s ({res.method}; {how}).")
    return "bad", (f"The fit did NOT converge ({res.message}) after {res.iterations} "
                   f"iterations ({res.method}; {how}): the values are its last iterate, "
                   "and no standard errors or intervals are given.")


def _identifiability(res) -> tuple[str, str]:
    cond = f"the scaled sensitivity matrix has condition number {res.condition_number:.3g}"
    if res.identifiable is None:
        return "none", "Identifiability was not judged: it is judged at a converged estimate."
    if res.identifiable:
        return "ok", (f"Identifiable: the data determine every free parameter ({cond}).")
    dirs = "; ".join(res.unidentifiable_directions) or "a direction of the free parameters"
    return "bad", (f"NOT identifiable ({cond}): {dirs}. The parameters involved have no "
                   "standard error or interval; fix one of them, or add a record that "
                   "excites the mechanism differently (for instance a known torque).")


def _whiteness(diag, what: str = "residuals") -> tuple[str, str]:
    if diag is None:
        return "none", f"The {what} were not tested for whiteness (the fit did not converge)."
    if diag.white:
        return "ok", (f"The {what} are white (Ljung-Box p = {diag.ljung_box_p:.2g} over "
                      f"{diag.n_lags} lags; lag-1 autocorrelation "
                      f"{diag.lag1_autocorrelation:.2f}; about {diag.effective_samples:.0f} "
                      f"independent samples of {diag.n_samples}): the model explains the "
                      "data to within the noise.")
    return "bad", diag.not_white_message().replace("the residuals", f"The {what}", 1)


def verdicts(pairs: list[tuple[str, tuple[str, str]]]) -> list[dict]:
    return [{"topic": topic, "cls": cls, "text": text} for topic, (cls, text) in pairs]


def _first_unit(channels: dict | None) -> str:
    """The SI unit of the first channel (the one overall scores are in); rad without any."""
    return next(iter((channels or {}).values()), {}).get("unit", "rad")


def fit_context(res, *, scene=None, command=None, title: str = "") -> dict:
    """The template's values for a [`FitResult`][crank_jax.FitResult]; every number comes
    from `res.to_json()` (the `fit.json` document) or the result's own fields."""
    doc = res.to_json()
    fitted = None
    if scene is not None:
        try:
            fitted = res.fitted_scene(scene)
        except ValueError:  # a load that cannot take the estimates: show the given scene
            fitted = None
    summary = [("parameters", str(len(res.names))), ("samples", str(doc["n_samples"])),
               ("records", str(len(res.data))),
               ("rms residual", f"{fmt(doc['rms_residual'])} {_first_unit(res.channels)}"),
               ("condition number", fmt(res.condition_number)),
               ("method", res.method), ("strategy", res.strategy or f"{res.shooting} shooting"),
               ("iterations", str(doc["iterations"])), ("time", f"{doc['seconds']:.1f} s")]
    return {
        "kind": "fit", "title": title or "crank-jax fit report",
        "verdicts": verdicts([("Convergence", _convergence(res)),
                               ("Identifiability", _identifiability(res)),
                               ("Whiteness", _whiteness(res.diagnostics))]),
        "summary": summary, "estimates": _estimates(doc), "correlation": _correlation(doc),
        "warnings": list(res.warnings), "figures": fit_figures(res),
        "start_from": "the start values in the table's start column (free phi0 and dphi0 "
                      "from a local fit to each record's first samples)",
        "provenance": provenance(command=command, scene=scene, fitted=fitted,
                                 sources=[d.source for d in res.data]),
        "scores": None,
    }


def validation_context(val, *, scene=None, command=None, title: str = "") -> dict:
    """The template's values for a [`Validation`][crank_jax.Validation] (its numbers from
    `val.to_json()`, the `VAL.json` document)."""
    doc = val.to_json()
    diag = val.error_diagnostics()
    u = _first_unit(val.channels)
    scores = [("fit", cell(doc["fit_percent"]), "%"), ("rms error", cell(doc["rms"]), u),
              ("max |error|", cell(doc["max_abs"]), u),
              ("scored samples", {"text": str(doc["n_samples"]), "full": ""}, ""),
              ("phi0 (estimated)", cell(doc["phi0"]), "rad"),
              ("dphi0 (estimated)", cell(doc["dphi0"]), "rad/s"),
              ("initial-state window", cell(doc["init_window"]), "s"),
              ("t start", cell(doc["t_start"]), "s"), ("t end", cell(doc["t_end"]), "s")]
    if len(doc["channels"]) > 1:  # the rows above are the first channel's: each in turn
        for n, c in doc["channels"].items():
            cu = val.channels[n]["unit"]
            scores += [(f"{n}: fit", cell(c["fit_percent"]), "%"),
                       (f"{n}: rms error", cell(c["rms"]), cu),
                       (f"{n}: max |error|", cell(c["max_abs"]), cu)]
    first = next(iter(doc["channels"]), "phi")
    # A score, not a pass/fail: what is good enough is the user's call.
    verdict = ("info",
               f"The open-loop prediction of {val.source} scores {fmt(val.fit_percent)}% "
               f"(100% is perfect, 0% no better than the record's mean), rms error "
               f"{fmt(val.rms)} {u} in {first} over {val.n_samples} samples not used for the "
               "estimate.")
    return {
        "kind": "validation", "title": title or "crank-jax validation report",
        "verdicts": verdicts([("Prediction", verdict),
                               ("Whiteness", _whiteness(diag, "prediction errors"))]),
        "summary": [], "estimates": [], "correlation": None, "scores": scores,
        "warnings": list(val.warnings), "figures": validation_figures(val, diag),
        "start_from": "",
        "provenance": provenance(command=command, scene=scene, sources=[val.source]),
    }
