"""Validation on a second record: fit on one run of the shaken rig, then predict another
run (a different shake) open-loop from an initial state estimated on its first period,
and score the prediction."""

import jax

jax.config.update("jax_enable_x64", True)

import crank_jax as cj  # noqa: E402
from crank_jax.identify import fitted_scene  # noqa: E402

rig = cj.load_scene("lab-rig")
run1 = cj.Scene(rig.mech, torque=cj.HarmonicLoad(0.0, 0.2, 3.0), phi0=0.5)
run2 = cj.Scene(rig.mech, torque=cj.HarmonicLoad(0.0, 0.15, 5.0), phi0=-0.2)
cj.save_data(cj.synthesize(run1, t1=4.0, rate=200.0, noise_std=1e-3, seed=1), "run1.csv")
cj.save_data(cj.synthesize(run2, t1=4.0, rate=200.0, noise_std=1e-3, seed=2), "run2.csv")

start = cj.Scene(rig.mech.replace(k=2.4, c=0.004), torque=run1.torque, phi0=0.5)
res = cj.fit(start, cj.load_data("run1.csv"), free=("k", "c", "phi0", "dphi0"),
             progress=False)
print(res.summary())
fitted = fitted_scene(start, res)  # the fitted mechanism as a scene
val = cj.validate(fitted, cj.load_data("run2.csv"))  # run2's own tau column drives it
print(val.summary())
val.report("validation-report.html", scene=fitted)
print("wrote validation-report.html")
