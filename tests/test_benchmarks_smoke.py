"""Smoke runs of the benchmark scripts (tiny sizes): they run, and write their results.

The full benchmarks run by command (`python experiments/bench_*.py`), not in CI.
"""

import json
import subprocess
import sys
from pathlib import Path

import pytest

EXP = Path(__file__).resolve().parent.parent / "experiments"


@pytest.mark.parametrize("script,result", [
    ("bench_work_precision.py", "work_precision"),
    ("bench_throughput.py", "throughput"),
    ("bench_gradients.py", "gradients"),
    ("bench_startup.py", "startup"),
    ("bench_structure.py", "structure"),
    ("bench_fusion.py", "fusion"),
    ("bench_sweep_devices.py", "sweep_devices"),
    ("misfit_bench.py", "misfit_bench"),
    ("bench_track.py", "bench_track"),
    ("bench_fit_many.py", "bench_fit_many"),
    # Both settings, and with the flags the backward program of before 2026-11-28 from
    # `_reverse_programs.py`, whose signature had drifted from `adjoint._deferred`'s: the
    # script failed and nothing ran it (found 2026-11-28). About 100 s.
    ("bench_reverse.py", "gradients_reverse_cpu_flags"),
])
def test_benchmark_smoke(script, result):
    subprocess.run([sys.executable, str(EXP / script), "--smoke"], check=True, cwd=EXP,
                   capture_output=True, timeout=300)
    data = json.loads((EXP / "results" / f"{result}.smoke.json").read_text())
    assert data["smoke"] is True
    assert data["machine"]["cores"] >= 1 and data["machine"]["versions"]["jax"]


def test_numba_peer_matches_crank_jax():
    sys.path.insert(0, str(EXP))
    import numpy as np
    import peers

    import crank_jax as cj

    if not peers.HAVE_NUMBA:
        pytest.skip("numba is not installed")
    mech = cj.load_scene("lab-rig").mech
    ts = np.linspace(0.0, 2.0, 201)
    ref = np.asarray(cj.simulate(mech, 1.0, 0.0, ts, solver="dopri8", rtol=1e-13,
                                 atol=1e-15).phi)
    ys, _ = peers.dp5_numba(peers.params_of(mech), (1.0, 0.0), ts, 1e-12, 1e-14)
    assert np.max(np.abs(ys[:, 0] - ref)) < 1e-9
    phi, _ = peers.scipy_solve("DOP853", peers.params_of(mech), (1.0, 0.0), ts, 1e-12, 1e-14)
    assert np.max(np.abs(phi - ref)) < 1e-9
    ys, _ = peers.dop853_numba(peers.params_of(mech), (1.0, 0.0), ts, 1e-12, 1e-14)
    assert np.max(np.abs(ys[:, 0] - ref)) < 1e-9


def test_numba_dop853_is_scipys_dop853():
    # The compiled DOP853 transcribes scipy's (coefficients, controller, dense output): at a
    # loose tolerance, where the two would differ visibly if the steps differed, they agree
    # to rounding.
    sys.path.insert(0, str(EXP))
    import numpy as np
    import peers

    import crank_jax as cj

    if not peers.HAVE_NUMBA:
        pytest.skip("numba is not installed")
    p = peers.params_of(cj.load_scene("lab-rig").mech)
    ts = np.linspace(0.0, 2.0, 201)
    ys, _ = peers.dop853_numba(p, (1.0, 0.0), ts, 1e-5, 1e-7)
    phi, _ = peers.scipy_solve("DOP853", p, (1.0, 0.0), ts, 1e-5, 1e-7)
    assert np.max(np.abs(ys[:, 0] - phi)) < 1e-11


def test_rotating_fleet_peer_matches_crank_jax():
    # The fleet bench's rotating-rig peer (offset slider line, tilted mount, constant
    # torque) has its own right-hand side and slide kinematics: both must be crank_jax's
    # model, or the peer fits another rig and the bench compares nothing.
    sys.path.insert(0, str(EXP))
    import fleet_rot as fr
    import numpy as np
    from scipy.integrate import solve_ivp

    from crank_jax.model.outputs import output

    sc = fr.scene(0.21, 0.0095, 1.2, 4.0)
    ts = np.linspace(0.0, 2.0, 201)
    tr = sc.simulate(ts, solver="dopri8", rtol=1e-13, atol=1e-15)
    d = sc.mech.as_dict()
    p = tuple(float(d[k]) for k in fr.PARAM_ORDER)
    sol = solve_ivp(fr.numba_rhs(), (0.0, 2.0), [1.2, 4.0], method="DOP853", t_eval=ts,
                    rtol=1e-12, atol=1e-14, args=(0.21, p))
    assert np.max(np.abs(sol.y[0] - np.asarray(tr.phi))) < 1e-8
    x_s = np.asarray(output("x_s", sc.mech, ts, tr.phi, tr.dphi))
    assert np.max(np.abs(fr.slide(sol.y[0], p) - x_s)) < 1e-9


@pytest.mark.full
def test_fleet_bench_rotating_smoke():
    # About 60 s on the shared 2-core machine (the fleet's compile and the peer's fits).
    subprocess.run([sys.executable, str(EXP / "bench_fit_many.py"), "--smoke", "--rig",
                    "rotating"], check=True, cwd=EXP, capture_output=True, timeout=300)
    data = json.loads((EXP / "results" / "bench_fit_many_rot.smoke.json").read_text())
    assert data["smoke"] is True and data["rig"] == "rotating"
    assert data["channels"] == ["phi", "x_s"]
