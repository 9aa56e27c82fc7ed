"""A sweep sharded over several devices gives the one-device result, for every output,
every load kind, varied load parameters and every solver family.

XLA's host device count is fixed when JAX starts, so this runs in a fresh interpreter with
`XLA_FLAGS=--xla_force_host_platform_device_count=4` (more devices than this machine's
cores: a kernel that waits on XLA:CPU's intra-op threads, such as a batched LAPACK call,
deadlocks there; the subprocess's timeout turns that into a failure).
"""

import json
import os
import subprocess
import sys
import textwrap

import pytest

SCRIPT = textwrap.dedent("""
    import json
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    import crank_jax as cj

    lab = cj.load_scene("lab-rig")
    short = dict(t1=0.4, num_saves=17)
    ms = cj.MultiSineLoad([0.04, 0.03], [1.3, 2.9], [0.0, 1.0], X0=0.01)
    sampled = cj.SampledLoad(np.linspace(0, 0.5, 26), 0.03 * np.sin(np.arange(26.0)))
    every = tuple(cj.sweep.REDUCTIONS)
    cases = {
        # every output (peak_O solves for the reactions), invalid samples mixed in
        "all_outputs": (lab, {"k": "normal(2.0,0.3)", "L": "normal(0.1,0.05)",
                              "phi0": "uniform(-1,1)"}, every, {}),
        # none -> constant -> harmonic promotions of both loads by varied parameters
        "varied_loads": (lab, {"P0": "normal(1,0.2)", "tau1": "uniform(0,0.05)",
                               "tau_freq_hz": "uniform(0.5,2)", "tau_phase": "uniform(0,3)"},
                         ("peak_phi", "peak_O", "final_energy"), {}),
        "multisine": (cj.Scene(lab.mech, torque=ms, phi0=0.5),
                      {"k": "normal(2,0.1)", "tau0": "uniform(0,0.02)"},
                      ("final_phi", "peak_O"), {}),
        "sampled": (cj.Scene(lab.mech, torque=sampled, phi0=0.5), {"k": "normal(2,0.1)"},
                    ("final_phi", "peak_O", "phi"), {}),
        "implicit": (lab, {"k": "normal(2,0.1)", "c": "uniform(0.005,0.02)"},
                     ("peak_phi", "peak_O", "dphi"), {"solver": "kvaerno5"}),
    }
    report = {"devices": jax.device_count()}
    for name, (scene, spec, outs, extra) in cases.items():
        kw = dict(n=10, seed=5, chunk_size=4, **short, **extra)
        many = cj.run_sweep(scene, spec, outs, **kw)
        if name in ("sampled", "implicit"):
            # diffrax's vmap-ed steps (sampled load) and lineax's batched LU (implicit
            # solver) depend on the batch in their rounding: each device's part of a chunk
            # of 4 is one sample, so the one-device run it must equal has chunks of one.
            kw["chunk_size"] = 1
        one = cj.run_sweep(scene, spec, outs, devices=jax.devices()[:1], **kw)
        report[name] = {
            "status_equal": bool(np.array_equal(many.status, one.status)),
            "steps_equal": bool(np.array_equal(many.num_steps, one.num_steps)),
            "n_ok": int(many.ok.sum()),
            "max_diff": max(float(np.max(np.abs(many.outputs[k] - one.outputs[k])))
                            for k in outs),
        }
    print(json.dumps(report))
""")


def _run(devices: int) -> dict:
    env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}",
               JAX_PLATFORMS="cpu", CRANK_JAX_NO_CACHE="1")
    try:
        proc = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True,
                              text=True, timeout=1500)
    except subprocess.TimeoutExpired:
        pytest.fail(f"a sweep over {devices} devices hung (deadlock?)")
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.slow  # five configurations, each compiled for 1 and for 4 devices (minutes)
def test_four_host_devices_match_one_device_in_every_configuration():
    res = _run(4)
    assert res.pop("devices") == 4
    for name, r in res.items():
        assert r["status_equal"] and r["steps_equal"], name
        assert r["max_diff"] <= 1e-12, (name, r)
        assert r["n_ok"] > 0, name
    assert res["all_outputs"]["n_ok"] < 10  # some L samples fall below r: invalid
