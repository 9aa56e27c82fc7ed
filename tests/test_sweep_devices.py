"""A sweep sharded over several devices gives the one-device result.

XLA's host device count is fixed when JAX starts, so this runs in a fresh interpreter with
`XLA_FLAGS=--xla_force_host_platform_device_count=4`.
"""

import json
import os
import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent("""
    import json
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    import crank_jax as cj

    scene = cj.load_scene("lab-rig")
    spec = {"k": "normal(2.0,0.3)", "c": "uniform(0.005,0.02)", "L": "normal(0.1,0.05)",
            "phi0": "uniform(-1,1)"}
    outs = ("peak_phi", "final_energy", "settling_time", "phi")
    kw = dict(n=10, seed=5, t1=0.5, num_saves=21, chunk_size=4)
    many = cj.sweep(scene, spec, outs, **kw)
    one = cj.sweep(scene, spec, outs, devices=jax.devices()[:1], **kw)
    print(json.dumps({
        "devices": jax.device_count(),
        "status_equal": bool(np.array_equal(many.status, one.status)),
        "n_ok": int(many.ok.sum()),
        "max_diff": max(float(np.max(np.abs(many.outputs[k] - one.outputs[k])))
                        for k in outs),
        "steps_equal": bool(np.array_equal(many.num_steps, one.num_steps)),
    }))
""")


def test_four_host_devices_match_one_device():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4",
               JAX_PLATFORMS="cpu", CRANK_JAX_NO_CACHE="1")
    proc = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    assert res["devices"] == 4
    assert res["status_equal"] and res["steps_equal"]
    assert 0 < res["n_ok"] < 10  # some L samples fall below r and are marked invalid
    assert res["max_diff"] <= 1e-12
