"""Shared helpers for the benchmark scripts: machine record, median timing, results I/O."""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "experiments" / "results"
FIGURES = ROOT / "docs" / "figures"
sys.path.insert(0, str(Path(__file__).resolve().parent))


def setup_jax():
    """float64 on, and return the jax module."""
    import jax

    jax.config.update("jax_enable_x64", True)
    return jax


def machine() -> dict:
    """Date and machine of a run: platform, CPU model, core count, library versions."""
    import jax

    cpu = platform.processor() or ""
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name"))
    except (OSError, StopIteration):
        pass
    vers = {"python": platform.python_version(), "jax": jax.__version__}
    for mod in ("diffrax", "equinox", "numpy", "scipy", "numba"):
        try:
            vers[mod] = __import__(mod).__version__
        except ImportError:
            vers[mod] = None
    return {
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "platform": platform.platform(), "cpu": cpu, "cores": os.cpu_count(),
        "devices": [str(d) for d in jax.devices()], "versions": vers,
        # e.g. crank_jax.with_cpu_flags's flags (the runs tagged _cpu_flags)
        "xla_flags": os.environ.get("XLA_FLAGS") or None,
        "note": "shared machine: other jobs ran at the same time; timings are medians",
    }


#: The clock `median_time` reads: "wall" (`time.perf_counter`), or "cpu"
#: (`time.process_time`, the CPU time of every thread of this process), which other jobs on
#: a shared machine disturb far less. Set by `use_clock` (the scripts' `--clock`).
CLOCK = {"name": "wall", "fn": time.perf_counter}


def use_clock(name: str) -> None:
    """Time with the "wall" or the "cpu" clock from now on."""
    CLOCK.update(name=name, fn={"wall": time.perf_counter, "cpu": time.process_time}[name])


def median_time(fn, repeats: int = 5, warmup: int = 1, budget_s: float = 20.0) -> float:
    """Median time of `fn()` in seconds (on [`CLOCK`][]) over `repeats` runs after `warmup`
    calls (fewer repeats, but at least 3, if a run is slow enough to exceed `budget_s`)."""
    for _ in range(warmup):
        fn()
    times = []
    start = time.perf_counter()
    clock = CLOCK["fn"]
    for i in range(repeats):
        t = clock()
        fn()
        times.append(clock() - t)
        if i >= 2 and time.perf_counter() - start > budget_s:
            break
    return float(np.median(times))


def wall(cmd, env) -> float:
    """Wall time, s, of the command `cmd` in a fresh process with environment `env`."""
    t = time.perf_counter()
    subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)
    return time.perf_counter() - t


def child_json(code: str, args, env) -> dict:
    """Run the Python source `code` in a fresh interpreter with arguments `args` and
    environment `env`; its last line of output, read as JSON."""
    out = subprocess.run([sys.executable, "-c", code, *map(str, args)], env=env,
                         check=True, capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def save(name: str, payload: dict, smoke: bool) -> Path:
    """Write `experiments/results/<name>.json` (or `<name>.smoke.json` in smoke mode)."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / (f"{name}.smoke.json" if smoke else f"{name}.json")
    payload = {"machine": machine(), "smoke": smoke, "clock": CLOCK["name"], **payload}
    path.write_text(json.dumps(payload, indent=1, default=float))
    print(f"wrote {path}")
    return path


def write_json(path: Path, payload: dict) -> None:
    """Write `payload` to `path` as indented JSON, atomically (a temporary file beside it,
    then renamed: an interrupted run leaves the previous results whole)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(payload, indent=1) + "\n")
    tmp.replace(path)


def interp_time(errors, times, target: float) -> float | None:
    """Time at error `target` by log-log interpolation along a work-precision curve
    (None if `target` is outside the measured range)."""
    e = np.log(np.asarray(errors, float))
    t = np.log(np.asarray(times, float))
    order = np.argsort(e)
    e, t = e[order], t[order]
    lt = np.log(target)
    if not (e[0] <= lt <= e[-1]):
        return None
    return float(np.exp(np.interp(lt, e, t)))


def write_section(page: Path, begin: str, end: str, text: str, what: str) -> None:
    """Replace the text between the markers `begin` and `end` on the docs page `page` with
    `text` (appended with its markers when the page has none)."""
    import re

    src = page.read_text()
    block = f"{begin}\n{text}\n{end}"
    pat = re.compile(re.escape(begin) + ".*?" + re.escape(end), re.S)
    page.write_text(pat.sub(lambda _: block, src) if pat.search(src)
                    else src.rstrip() + "\n\n" + block + "\n")
    print(f"rewrote the {what} table in {page.relative_to(ROOT)}")


def rk4(f, t: float, y, h: float, steps: int):
    """`steps` classical Runge-Kutta steps of `h` from `(t, y)` of `y' = f(t, y)` (numpy):
    the hand-written integrators of the peers and the stand-in records."""
    for s in range(steps):
        ts = t + s * h
        k1 = f(ts, y)
        k2 = f(ts + h / 2, y + h / 2 * k1)
        k3 = f(ts + h / 2, y + h / 2 * k2)
        k4 = f(ts + h, y + h * k3)
        y = y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return y


def tooth_edges(tf, phi, dphi, teeth: int, rng, jitter: float = 2e-5):
    """A toothed wheel's edge record of a dense motion `(tf, phi, dphi)` (rad, rad/s, with
    dphi > 0): the angles of the edges (a gap each turn: no edge at the last tooth) and
    their times, interpolated in the angle (Hermite, dt/dphi = 1/dphi) with `jitter` s of
    Gaussian noise from `rng`. Returns `(times, angles)`, s and rad."""
    from scipy.interpolate import CubicHermiteSpline

    step = 2 * np.pi / teeth
    k = np.arange(np.ceil(phi[0] / step), np.floor(phi[-1] / step) + 1)
    angle = k[k % teeth != teeth - 1] * step
    ts = CubicHermiteSpline(phi, tf, 1.0 / dphi)(angle) + rng.normal(0.0, jitter, angle.shape)
    return ts, angle
