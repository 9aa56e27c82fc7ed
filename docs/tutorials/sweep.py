"""A Monte Carlo sweep: how the lab rig's response spreads when its shaft stiffness and
damping are uncertain (2,000 samples, each a full nonlinear simulation)."""

import jax

jax.config.update("jax_enable_x64", True)

import crank_jax as cj  # noqa: E402
from crank_jax.sweep import Normal  # noqa: E402

scene = cj.load_scene("lab-rig")
res = cj.run_sweep(scene, {"k": Normal(2.0, 0.1), "c": "uniform(0.005,0.02)", "phi0": 0.5},
               outputs=("dominant_freq", "settling_time", "peak_O"),
               n=2000, seed=0, t1=2.0, num_saves=201)
print("status counts:", res.counts())
for name, stats in res.summary().items():
    print(f"{name:>14}: " + ", ".join(f"{k} {v:.4g}" for k, v in stats.items()))
