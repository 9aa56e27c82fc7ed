"""A fit request is complete when made: `normalize` resolves each record's crank angle,
each channel's noise level and the options (as enums) before it returns, so no stage
ever sees a request half built."""

import dataclasses

import numpy as np
import pytest

import crank_jax as cj
from crank_jax.identify.fit_options import Init, Method, ShootingMode
from crank_jax.identify.request import FitRequest, normalize
from crank_jax.records.sensors import Sensor

_OPTIONS = dict(init="scene", method="lm", shooting="auto", segments=None, multistart=1,
                seed=0, max_steps=None, tol=1e-8, profile=None, window=None,
                progress=False, warn=False)


@pytest.fixture(scope="module")
def two_channels():
    scene = dataclasses.replace(cj.load_scene("lab-rig"),
                                sensors=(Sensor("phi"), Sensor("x_s")))
    return scene, cj.synthesize(scene, t1=0.5, rate=60, noise_std={"phi": 1e-3,
                                                                     "x_s": 1e-4}, seed=2)


def test_normalize_resolves_angles_levels_and_options(two_channels):
    scene, data = two_channels
    req = normalize(scene, data, ("k", "c"), sigma=None, **_OPTIONS)
    assert len(req.angles) == 1 and req.angles[0].shape == (data.n,)
    assert np.all(np.isfinite(req.angles[0]))
    assert set(req.sigmas) == {"phi", "x_s"} and all(v > 0 for v in req.sigmas.values())
    assert req.estimated == ("phi", "x_s") and req.known_sigma is None
    assert req.method is Method.LM and req.shooting is ShootingMode.AUTO
    assert req.init is Init.SCENE and req.names == ("k", "c")


def test_given_levels_are_kept_and_only_the_others_estimated(two_channels):
    scene, data = two_channels
    req = normalize(scene, data, ("k", "c"), sigma={"x_s": 2e-4}, **_OPTIONS)
    assert req.sigmas["x_s"] == 2e-4 and req.estimated == ("phi",)
    assert req.known_sigma is None  # phi's level is not given
    both = normalize(scene, data, ("k", "c"), sigma={"x_s": 2e-4, "phi": 3e-3}, **_OPTIONS)
    assert both.estimated == () and both.known_sigma == 3e-3  # the first channel's
    # A number is the first channel's level: the other is still estimated.
    num = normalize(scene, data, ("k", "c"), sigma=3e-3, **_OPTIONS)
    assert num.sigmas["phi"] == 3e-3 and num.estimated == ("x_s",)
    assert num.known_sigma is None


def test_a_request_cannot_be_made_without_its_channels():
    # The angles and the levels are fields without defaults: no request lacks them.
    missing = [f.name for f in dataclasses.fields(FitRequest)
               if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
    assert {"angles", "sigmas"} <= set(missing)


def test_a_level_for_a_channel_no_record_has_is_refused_by_name(two_channels):
    scene, data = two_channels
    with pytest.raises(ValueError, match=r"sigma names channel 'v_s', which no record has; "
                                         r"the channels are \['phi', 'x_s'\]"):
        normalize(scene, data, ("k", "c"), sigma={"v_s": 1e-3}, **_OPTIONS)


def test_a_record_without_an_angle_channel_starts_from_its_own_scenes_state():
    # Only a slider speed: the angle is the scene's motion simulated over the record, from
    # that record's own initial state (one scene per record), not the first scene's.
    lab = cj.load_scene("lab-rig")
    other = dataclasses.replace(lab, phi0=np.asarray(0.4), dphi0=np.asarray(0.0))
    ts = np.linspace(0.0, 0.5, 26)
    records = [cj.Data(ts, None, channels={"v_s": 0.01 * np.sin(k * ts)}) for k in (1, 2)]
    req = normalize([lab, other], records, ("k", "c"), sigma=None, **_OPTIONS)
    for scene, angle in zip((lab, other), req.angles):
        expected = np.asarray(scene.simulate(ts, throw=False).phi)
        np.testing.assert_array_equal(angle, expected)
