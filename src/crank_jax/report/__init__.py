"""Self-contained HTML reports of a fit ([`write_fit_report`][]) and of a validation
([`write_validation_report`][]): one file a person can send to a colleague.

The page makes no network request (its Content-Security-Policy forbids any), embeds its
figures as inline SVG (or base64 PNG for very long records), and prints. The numbers it
shows are those of `fit.json` / `VAL.json` (`to_json()`), formatted to 6 significant
digits, with the full value in each cell's `title`. Rendering uses jinja2 (imported only
when a report is written) and the template `crank_jax/templates/report.html.j2`.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

from .context import fit_context, validation_context
from .fleet_report import fleet_context
from .track_report import track_context

__all__ = ["write_fit_report", "write_validation_report", "write_track_report",
           "write_fleet_report", "render"]


def render(context: dict) -> str:
    """The report page for a context from `fit_context` or `validation_context`."""
    import jinja2

    env = jinja2.Environment(loader=jinja2.PackageLoader("crank_jax", "templates"),
                             autoescape=True, undefined=jinja2.StrictUndefined,
                             trim_blocks=True, lstrip_blocks=True)
    return env.get_template("report.html.j2").render(**context)


def _write(path: str | os.PathLike, html: str) -> None:
    from ..runtime.io import atomic_write, printable

    # A file name that is not UTF-8 (in the command line, a record's source) is shown by
    # its bytes: its surrogates failed the UTF-8 write after the work.
    with atomic_write(path, "w") as f:
        f.write(printable(html))


def write_fit_report(result, path: str | os.PathLike, *, scene=None,
                     command: Sequence[str] | str | None = None, title: str = "") -> None:
    """Write the HTML report of a [`FitResult`][crank_jax.FitResult] to `path`, atomically.

    **Arguments:** `scene`: the [`Scene`][crank_jax.Scene] the fit started from (shown as
    TOML with the fitted scene; `None`: not shown); `command`: the command line (default:
    this process's); `title`: a heading.
    """
    _write(path, render(fit_context(result, scene=scene, command=command, title=title)))


def write_validation_report(val, path: str | os.PathLike, *, scene=None,
                            command: Sequence[str] | str | None = None,
                            title: str = "") -> None:
    """Write the HTML report of a [`Validation`][crank_jax.Validation] to `path`,
    atomically (arguments as [`write_fit_report`][])."""
    _write(path, render(validation_context(val, scene=scene, command=command, title=title)))


def write_track_report(res, path: str | os.PathLike, *, scene=None,
                       command: Sequence[str] | str | None = None, title: str = "") -> None:
    """Write the HTML report of a [`TrackResult`][crank_jax.online.tracked.TrackResult] to
    `path`, atomically (arguments as [`write_fit_report`][])."""
    _write(path, render(track_context(res, scene=scene, command=command, title=title)))


def write_fleet_report(fleet, path: str | os.PathLike, *, labels: Sequence[str] | None = None,
                       scene=None, command: Sequence[str] | str | None = None,
                       title: str = "") -> None:
    """Write the summary report of many independent fits (a
    [`FleetResult`][crank_jax.fleet.many.FleetResult]) to `path`, atomically: a row
    per record (`labels`, default its file's name) with its estimates, standard errors and
    verdict, and the estimates' spread (other arguments as [`write_fit_report`][])."""
    _write(path, render(fleet_context(fleet, labels, scene=scene, command=command,
                                      title=title)))
