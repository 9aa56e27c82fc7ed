"""Many independent fits at once: [`fit_many`][] fits each of many records of one scene
and free set by itself, side by side in one compiled program.

Each record is planned as [`fit`][] plans it (its request checked, its start values and
noise level from the data, its start solve judged; the start solves of the records of one
shape side by side, in one compiled call per batch); the records whose plan is single
shooting are grouped by the shape of their problem (the bucket length of
[`segments`][crank_jax.identify.segments]) and fitted under one `jax.vmap` of a
Levenberg-Marquardt loop ([`batch_lm`][crank_jax.fleet.batch_lm]) with the fit's own
stop test. A fleet estimate is reported through the fit's own result
([`fit.finish`][crank_jax.identify.fit.finish]: the uncertainty, the channels, the
warnings), so it reads exactly as a single fit's.

The fleet makes one try from the start the fit plans, with the fit's shooting (a
multiple-shooting run, then a single-shooting polish from its estimate, both side by
side), but without the fit's escalation and its start from the motion. A record it
cannot settle (its plan holds a flat direction, its fleet run did not converge, ran off
the physical range or ended far above the noise, where the fit would escalate) is fitted
by [`fit`][] itself, and its result says so in its warnings and in `FleetResult.alone`.
A record whose fleet run fails is taken out and its batch run again without it, so that
no failing record changes another's result. The records are planned on the calling
thread while a worker thread fits the batches already planned (see `_pipeline`).
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np

from ..identify.attempt import in_range
from ..identify.fit import finish, fit
from ..identify.fit_plan import make_plan, plan_steps, recoordinate
from ..identify.fit_result import FitResult
from ..identify.outcome import Run, termination
from ..identify.request import normalize
from ..identify.stages import FitState
from ..identify.strategy import far_from_noise, noise_unit
from ..runtime.blas import one_blas_thread
from ..runtime.progress import progress_bar
from .batch_lm import STATUS, largest_batch, run_batch, shape_key, start_solves

__all__ = ["fit_many", "FleetResult", "SUMMARY_COLUMNS"]

#: The summary table's first columns; then each free name and its standard error.
SUMMARY_COLUMNS = ("record", "converged", "fleet", "iterations", "rms")


@dataclasses.dataclass(frozen=True)
class FleetResult:
    """The outcome of [`fit_many`][]: one [`FitResult`][] per record, in order, and how
    each was fitted (`alone[i]`: None when by the fleet, else why it was fitted by `fit`)."""

    results: list[FitResult]
    alone: list[str | None]
    seconds: float

    def __len__(self) -> int:
        return len(self.results)

    def __getitem__(self, i: int) -> FitResult:
        return self.results[i]

    def __iter__(self):
        return iter(self.results)

    def rows(self, labels: Sequence[str] | None = None) -> list[dict]:
        """One row per record: [`SUMMARY_COLUMNS`][], then each reported name and its
        standard error (`<name>_stderr`, None where undefined); `labels` name the records
        (default: their index)."""
        out = []
        for i, res in enumerate(self.results):
            row = {"record": labels[i] if labels else i, "converged": res.converged,
                   "fleet": self.alone[i] is None, "iterations": res.iterations,
                   "rms": res.rms_residual}
            for n in res.names:
                row[n], row[f"{n}_stderr"] = res.values[n], res.stderr[n]
            out.append(row)
        return out


class _Member(NamedTuple):
    req: object
    plan: object
    noise: float
    t_begin: float


def _plan(scene, data, free, kw) -> _Member | str:
    """A record's request and plan, as `fit` makes them; a string: why it is not for the
    fleet (it is then fitted by `fit`)."""
    t_begin = time.perf_counter()
    req = normalize(scene, data, free, **kw)
    return _member(req, make_plan(req), t_begin)


def _plan_all(reqs: dict, bar) -> dict:
    """Each request's plan (index -> Plan), as `make_plan` makes it, the start solves of
    the records of one shape side by side ([`start_solves`][crank_jax.fleet.batch_lm.
    start_solves]): each record's [`plan_steps`][crank_jax.identify.fit_plan.plan_steps]
    is stepped until it asks for a solve, then the asks are solved together."""
    steps, asks, plans = {i: plan_steps(r) for i, r in reqs.items()}, {}, {}

    def advance(i, solved):
        try:
            asks[i] = next(steps[i]) if solved is None else steps[i].send(solved)
        except StopIteration as done:
            plans[i] = done.value
            asks.pop(i, None)
            bar.update(1)

    for i in steps:
        advance(i, None)
    while asks:
        groups: dict = {}
        for i, (ss, _) in asks.items():
            groups.setdefault(shape_key(ss), []).append(i)
        for idx in groups.values():
            for i, solved in zip(idx, start_solves([asks[i] for i in idx])):
                advance(i, solved)
    return plans


def _member(req, plan, t_begin: float) -> _Member | str:
    """The fleet's member of a planned record; a string: why it is not for the fleet (it
    is then fitted by `fit`)."""
    if plan.abort:
        return "refused before any optimisation"
    if plan.Bg.shape[1] != plan.single.p:
        return "a flat direction is held fixed"
    return _Member(req, plan, noise_unit(req.noise), t_begin)


def _run(m: _Member, z, cost, iterations, status, dec, big, r, J) -> Run:
    """The fleet's outcome of one member as the fit's `Run` (single-shooting coordinates,
    with its residuals `r` and sensitivities `J` there), judged as the fit judges its try:
    in range, and near the noise level."""
    ok = STATUS[int(status)] == "converged" and math.isfinite(float(cost))
    words = (f"converged: the Gauss-Newton step predicts a cost decrease of {dec:.2g} "
             f"sigma^2 and moves no coordinate by more than {big:.2g} of its standard error")
    run = Run(np.asarray(z, float), float(cost), int(iterations), ok, "converged" if ok
              else f"ended {STATUS[int(status)]}", termination(
                  "converged" if ok else "failed", words, predicted_decrease=float(dec),
                  largest_step=float(big), noise=m.noise), (m.plan.single, r, J))
    run = in_range(m.plan, run)
    rms = math.sqrt(2 * run.cost / max(m.plan.single.n_residuals, 1))
    if run.converged and far_from_noise(rms, m.req.noise):
        run = run._replace(converged=False, message="ended far above the noise level")
    return run


def _fleet(items: dict, tol: float, max_steps: int) -> tuple[dict, dict]:
    """Fleet runs of `items` (index -> (problem, z0, noise)), by shape, in batches; a batch
    with a member that did not converge runs again without it. **Returns:** (index -> its
    row of [`FleetRun`][crank_jax.fleet.batch_lm.FleetRun] for the converged, index ->
    the status of each other one)."""
    groups: dict = {}
    for i, (problem, _, _) in items.items():
        groups.setdefault(shape_key(problem), []).append(i)
    done, left, size = {}, {}, largest_batch()
    for idx in groups.values():
        for k in range(0, len(idx), size):
            part = idx[k:k + size]
            while part:
                out = run_batch(*zip(*(items[i] for i in part)), tol, max_steps)
                rows = dict(zip(part, zip(*out)))
                bad = [i for i in part if STATUS[int(rows[i][3])] != "converged"
                       or not math.isfinite(float(rows[i][1]))]
                left.update({i: STATUS[int(rows[i][3])] for i in bad})
                if not bad:
                    done.update(rows)
                # Again without the failing members (their neighbours' solves step in
                # lockstep with theirs): each result is then that of a batch of
                # converging records.
                part = [i for i in part if i not in bad] if bad else []
    return done, left


def _fit_fleet(members: dict, tol: float, max_steps: int, bar) -> tuple[dict, dict]:
    """The fleet's tries: each member's planned problem from its planned start (multiple
    shooting where the fit plans it), then, for those, a single-shooting polish from that
    estimate (as `fit`'s). **Returns:** (index -> Run, index -> why left to `fit`)."""
    first, left = _fleet({i: (m.plan.shoot, m.plan.z0, m.noise) for i, m in members.items()},
                         tol, max_steps)
    left = {i: f"its fleet run ended {v}" for i, v in left.items()}
    multi = [i for i in first if members[i].plan.shoot is not members[i].plan.single]
    polish, more = _fleet({i: (members[i].plan.single, recoordinate(
        members[i].plan.shoot, members[i].plan.single, first[i][0]), members[i].noise)
        for i in multi}, tol, max_steps)
    left.update({i: f"its fleet polish ended {v}" for i, v in more.items()})
    runs = {}
    for i, row in first.items():
        if i in more:
            continue
        if i in polish:
            row = polish[i][:2] + (polish[i][2] + row[2],) + polish[i][3:]
        run = _run(members[i], *row)
        if run.converged:
            runs[i] = run
        else:
            left[i] = f"its fleet run {run.message}"
    bar.update(len(members))
    return runs, left


class _Locked:
    """A progress bar updated from the planning thread and the fleet's worker."""

    def __init__(self, bar):
        self.bar, self.lock = bar, threading.Lock()

    def update(self, n=1):
        with self.lock:
            self.bar.update(n)


def _pipeline(reqs: dict, tol: float, max_steps: int, bar, t0: float
              ) -> tuple[dict, dict]:
    """Each request planned and fitted: the plans on this thread, [`largest_batch`][]
    records at a time, while one worker thread runs the fleet's batches, each submitted
    as soon as its shape has a full batch of planned records (the rest at the end); then
    each batch's results are finished here. A shape's batches are its records in order,
    cut into full batches, whatever the timing: the overlap changes the time, never a
    result. Python plans the next records on one core while XLA fits a batch on the other
    (planning is host work: a quarter of the fleet's time on the lab rig); the two
    threads' compiled calls that could block each other take turns (see
    [`EXECUTION`][crank_jax.fleet.batch_lm.EXECUTION]). `t0`: when `fit_many` began (a
    result's time counts from it). **Returns:** (index -> its [`FitResult`][], index ->
    why it is left to `fit`)."""
    members, alone, pending, futures = {}, {}, {}, []
    order, size = sorted(reqs), largest_batch()
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="crank-jax-fleet") as worker:
        def submit(idx):
            futures.append(worker.submit(_fit_fleet, {i: members[i] for i in idx}, tol,
                                         max_steps, bar))

        try:
            for k in range(0, len(order), size):
                part = {i: reqs[i] for i in order[k:k + size]}
                for i, plan in sorted(_plan_all(part, bar).items()):
                    m = _member(reqs[i], plan, t0)
                    if isinstance(m, str):
                        alone[i] = m
                        continue
                    members[i] = m
                    key = shape_key(m.plan.shoot)
                    pending.setdefault(key, []).append(i)
                    if len(pending[key]) == size:
                        submit(pending.pop(key))
            for idx in pending.values():
                submit(idx)
            fitted = {}
            for fut in futures:
                runs, left = fut.result()
                alone.update(left)
                for i, run in runs.items():
                    m = members[i]
                    fitted[i] = finish(FitState(m.req, m.plan, run, run.iterations, (),
                                                m.plan.shooting), m.t_begin)
        except BaseException:
            for fut in futures:
                fut.cancel()
            raise
    return fitted, alone


@one_blas_thread
def fit_many(
    scene,
    records: Sequence,
    free: Sequence[str] = ("k", "c", "phi0", "dphi0"),
    *,
    init: str | dict[str, float] = "scene",
    max_steps: int | None = None,
    tol: float = 1e-8,
    sigma: float | dict | None = None,
    window: tuple[float | None, float | None] | None = None,
    progress: bool = True,
    warn: bool = True,
    force=None,
    load_by: str = "time",
) -> FleetResult:
    """Fit each record by itself (many independent fits of one scene and free set), the
    records of one shape side by side in one compiled Levenberg-Marquardt program.

    **Arguments:** `scene`, a [`Scene`][] (or one per record); `records`, a sequence of
    [`Data`][]; the other options are [`fit`][]'s, applied to every record (one try from
    the planned start, with the planned shooting: `fit`'s escalation is for the records
    the fleet leaves to `fit`; no multistart, profile or joint records).

    **Returns:** a [`FleetResult`][]: per record, in order, the [`FitResult`][] a single
    `fit` gives (each estimate within a small fraction of its standard error of it: both
    stop at the same test), and None or why it was fitted by `fit` itself. A mistake in a
    record's request raises `ValueError` naming the record, before any fit.
    """
    t0 = time.perf_counter()
    records = list(records)
    scenes = list(scene) if isinstance(scene, (list, tuple)) else [scene] * len(records)
    if not records or len(scenes) != len(records):
        raise ValueError(f"fit_many needs at least one record and one scene per record; got "
                         f"{len(records)} records and {len(scenes)} scenes")
    kw = dict(init=init, method="lm", shooting="auto", segments=None, multistart=1, seed=0,
              max_steps=max_steps, tol=tol, sigma=sigma, profile=None, window=window,
              progress=False, warn=warn, force=force, load_by=load_by)
    reqs = {}
    for i, (sc, d) in enumerate(zip(scenes, records)):
        try:
            reqs[i] = normalize(sc, d, free, **kw)
        except ValueError as e:
            raise ValueError(f"record {i}: {e}") from None
    steps = 100 if max_steps is None else int(max_steps)
    # Two steps a record: its plan, then its fit in a batch.
    with progress_bar(2 * len(records), "fit_many (plans, fits)", progress, unit="step"
                      ) as bar:
        fitted, alone = _pipeline(reqs, tol, steps, _Locked(bar), t0)
    results = []
    for i, (sc, d) in enumerate(zip(scenes, records)):
        if i in fitted:
            results.append(fitted[i])
            continue
        res = fit(sc, d, free, **{**kw, "progress": progress})
        note = f"fitted by fit itself, not in fit_many's fleet: {alone[i]}"
        results.append(res._replace(warnings=[note] + list(res.warnings)))
    return FleetResult(results, [alone.get(i) for i in range(len(records))],
                       time.perf_counter() - t0)

