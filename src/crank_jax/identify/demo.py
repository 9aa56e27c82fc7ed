"""The demo experiment of `crank-jax demo`: its settings (`DEMO`) and its scene and
synthetic record (`demo_record`), for a script or a test that fits what the demo fits."""

from __future__ import annotations

from types import MappingProxyType

import numpy as np

from ..records.data import Data
from ..scene import Scene, load_scene
from ..sweep.distributions import MAX_SEED

__all__ = ["DEMO", "demo_record"]

DEMO = MappingProxyType(dict(
    scene="lab-rig", tau1=0.2, freq_hz=3.0, phi0=0.5, t1=5.0, rate=200.0, noise_std=1e-3,
    start=MappingProxyType({"k": 2.4, "c": 0.004}), shooting="single"))
"""The demo experiment (read-only): the lab rig (`scene`, a preset) driven by a known
harmonic crank torque `tau1 sin(2 pi freq_hz t)` (a shaker; `tau1` in N*m, `freq_hz` in
Hz), which fixes the common scale of the inertial parameters; released from rest at
`phi0` rad; `t1` = 5 s sampled at `rate` = 200 Hz with `noise_std` = 1 mrad of noise.
The fit starts 20% off in k and 2x off in c (`start`, in N*m/rad and N*m*s/rad; pass
`init=dict(DEMO["start"])` to `fit`). Single shooting (`shooting`): the record holds 16.6
periods, which single shooting fits from that start (9 LM iterations); under
`shooting="auto"` the fit would warn of its choice on every run, a warning about the
demo's own setup."""


def demo_record(seed: int = 1) -> tuple[Scene, Data]:
    """The demo's scene and its synthetic record (what `crank-jax demo` fits).

    **Arguments:**

    - `seed`: seed of the record's noise (`crank-jax demo --noise-seed`; default 1).

    **Returns:** `(scene, data)`: the lab rig driven by the known harmonic torque of
    `DEMO` (`name="lab-rig+shaker"`, its true parameters the preset's), and a [`Data`][]
    record of the crank angle `phi` (rad) at `DEMO["rate"]` Hz over `DEMO["t1"]` s with
    Gaussian noise of standard deviation `DEMO["noise_std"]` rad. The same seed gives the
    same record.
    """
    from ..model.loads import HarmonicLoad
    from ..records.synth import synthesize

    # Checked here, in this function's words (synthesize names its own seed).
    if (isinstance(seed, bool) or not isinstance(seed, (int, np.integer))
            or not 0 <= seed <= MAX_SEED):
        raise ValueError(f"demo_record: seed must be an integer from 0 to {MAX_SEED}, got "
                         f"{seed!r}")
    base = load_scene(DEMO["scene"])
    scene = Scene(base.mech, torque=HarmonicLoad(0.0, DEMO["tau1"], DEMO["freq_hz"]),
                  phi0=DEMO["phi0"], dphi0=0.0, rtol=base.rtol, atol=base.atol,
                  t1=DEMO["t1"], name="lab-rig+shaker",
                  description="lab rig driven by a known harmonic crank torque")
    data = synthesize(scene, rate=DEMO["rate"], noise_std=DEMO["noise_std"], seed=seed)
    return scene, data
