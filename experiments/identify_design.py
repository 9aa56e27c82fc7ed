"""Experiment design: which of m_c, m_p, m_s, I_c, I_p, k, c does each experiment identify?

For free decay, a known crank torque and a known slider force, each at a small (0.05 rad)
and a large (1.5 rad) release, the scaled sensitivity matrix of 5 s of lab-rig data at
100 Hz is evaluated at the true parameters, with all seven free and with the coupler
weighed (m_p known, the other six free), plus phi0 and dphi0, and the
identifiability analysis of `crank_jax.fit` is applied with a known noise level of 1 mrad.
A parameter is identifiable when it lies outside every unidentifiable direction (exactly
flat, or with a standard error above 50% along it).

    python experiments/identify_design.py

Writes experiments/results/identify_design.{json,md}.
"""

from __future__ import annotations

import json
import platform
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

import crank_jax as cj  # noqa: E402
from crank_jax.identify.problem import build_problem  # noqa: E402
from crank_jax.identify.programs import jacobian_at  # noqa: E402
from crank_jax.identify.uncertainty import analyze  # noqa: E402
from crank_jax.runtime.io import atomic_write  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SEVEN = ("m_c", "m_p", "m_s", "I_c", "I_p", "k", "c")
SIGMA = 1e-3
EXPERIMENTS = {
    "free decay": {},
    "known crank torque": {"torque": cj.HarmonicLoad(0.0, 0.2, 3.0)},
    "known slider force": {"load": cj.HarmonicLoad(0.0, 5.0, 9.0)},
}
AMPLITUDES = {"small": 0.05, "large": 1.5}


FREE_SETS = {"all seven free": SEVEN,
             "m_p known": tuple(n for n in SEVEN if n != "m_p")}


def analyze_design(mech, kind: dict, phi0: float, params: tuple[str, ...]):
    scene = cj.Scene(mech, phi0=phi0, dphi0=0.0, **kind)
    data = cj.synthesize(scene, t1=5.0, rate=100.0)
    free = params + ("phi0", "dphi0")
    start = {n: float(getattr(mech, n)) for n in params}
    pr = build_problem(mech, [(data, scene.load, scene.torque, phi0, 0.0)], free, start, [1],
                       solver="dopri8", rtol=1e-9, atol=1e-11, max_steps=100_000)
    z = jnp.asarray(pr.to_z([start[n] for n in params] + [phi0, 0.0]))
    r, _, _, J = jacobian_at(pr, z)
    J = np.asarray(J)
    values = np.asarray(pr.values(z))
    unc = analyze(J, np.asarray(r), data.n, pr.names, values, pr.log, np.asarray(pr.ref),
                  sigma=SIGMA, geometry={k: float(getattr(mech, k)) for k in "rLbs"})
    rel = {n: (None if unc.affected[i] else float(unc.stderr[i] / abs(values[i])))
           for i, n in enumerate(pr.names) if n in SEVEN}
    return {"identified": [n for n in params if rel[n] is not None],
            "relative_stderr": rel, "directions": unc.directions,
            "condition_number": unc.condition_number,
            "max_abs_phi": float(np.max(np.abs(data.phi)))}


def main() -> None:
    mech = cj.load_scene("lab-rig").mech
    table = {}
    t0 = time.perf_counter()
    jobs = [(f, e, a) for f in FREE_SETS for e in EXPERIMENTS for a in AMPLITUDES]
    for fs, exp, amp in tqdm(jobs, desc="designs"):
        table[f"{fs}, {exp}, {amp}"] = analyze_design(mech, EXPERIMENTS[exp], AMPLITUDES[amp],
                                                      FREE_SETS[fs])
    doc = {"sigma": SIGMA, "record": "5 s at 100 Hz, lab rig", "table": table,
           "date": time.strftime("%Y-%m-%d"), "seconds": time.perf_counter() - t0,
           "machine": f"{platform.machine()} CPU, shared 2-core VM"}
    out = ROOT / "experiments" / "results"
    out.mkdir(parents=True, exist_ok=True)
    with atomic_write(out / "identify_design.json") as f:
        json.dump(doc, f, indent=1)
    lines = ["| free | experiment | amplitude | " + " | ".join(SEVEN) + " |",
             "|---|---|---|" + "---|" * len(SEVEN)]
    for key, row in table.items():
        fs, exp, amp = key.split(", ")
        cells = []
        for n in SEVEN:
            v = row["relative_stderr"].get(n, "known")
            cells.append(v if v == "known" else "no" if v is None else f"{100 * v:.2g}%")
        lines.append(f"| {fs} | {exp} | {amp} ({AMPLITUDES[amp]} rad) | " + " | ".join(cells)
                     + " |")
    lines.append("")
    lines.append("Cells: relative standard error at 1 mrad noise, or *no* (not identifiable).")
    lines.append("")
    for key, row in table.items():
        for d in row["directions"]:
            lines.append(f"- {key}: {d}")
    with atomic_write(out / "identify_design.md") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
