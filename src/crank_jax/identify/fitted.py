"""The scene a fit gives: the scene it started from with its estimates, which
`crank-jax fit --scene-out` writes and a report shows."""

from __future__ import annotations

import dataclasses
import json

import equinox as eqx

from ..model.loads import LOAD_PARAMS, set_param
from ..model.params import as_float_array
from ..records.sensors import DEFAULT_SENSOR, OFFSET_NAMES, Sensor
from ..runtime.io import atomic_write
from ..scene import PRESETS, Scene, SceneError, read_scene_doc, scene_to_toml

__all__ = ["fitted_scene", "save_fitted_scene", "fit_mark", "marked_unconverged"]


def _fitted_sensors(scene: Scene, result, record: int, values: dict,
                    sensors: tuple[Sensor, ...] | None) -> tuple[Sensor, ...]:
    """The scene's sensors joined by those record `record` was read through (they win by
    channel; default: its `Data`'s), each fitted offset put into its channel's sensor, so
    that the scene reads the record as the fit did. A plain angle read (`phi` in rad, no
    calibration, nothing else) joins only with a fitted offset: a plain fit's scene stays
    as it was (its sensors, if any, were not in the record, which reads plain again)."""
    records = getattr(result, "data", None)
    data = records[record] if records else None
    if sensors is None:
        sensors = tuple(s for s, _ in data.outputs()) if data is not None else ()
    merged = {s.name: s for s in scene.sensors}
    if tuple(sensors) != (DEFAULT_SENSOR,) or "phi_offset" in values:
        merged.update({s.name: s for s in sensors})
    for name, value in values.items():
        if name in OFFSET_NAMES:
            channel = OFFSET_NAMES[name]
            if channel not in merged:
                raise SceneError(f"the fitted {name} has no {channel} sensor to go into; "
                                 "give fitted_scene the sensors the record was read through")
            merged[channel] = dataclasses.replace(merged[channel], offset=float(value))
    return tuple(merged.values())


def fitted_scene(scene: Scene, result, record: int = 0,
                 sensors: tuple[Sensor, ...] | None = None, *, anyway: bool = False) -> Scene:
    """`scene` with a fit's estimates: the fitted mechanism, the fitted load amplitudes
    (`P0`, `P1`, `tau0`, `tau1`, the gains) and, where they were free, record `record`'s
    fitted initial state (the state at that record's first sample). A record's own sampled
    loads are data, not scene, so the scene's loads are kept for them.

    **Arguments:** `scene`, the scene the fit started from; `result`, its
    [`FitResult`][crank_jax.FitResult]; `record`, which record's values to take for
    names fitted per record (`name[i]`); `sensors`, those that record was read through
    (default: its `Data`'s), joined to the scene's (see `_fitted_sensors`); `anyway`:
    take the last iterate of a fit that did not converge (default: `ValueError` naming
    `anyway`). **Returns:** a [`Scene`][]; fitted channel offsets become its sensors'.
    """
    _check_converged(result, anyway)
    values = {n: v for n, v in result.values.items() if "[" not in n}
    suffix = f"[{record}]"
    values.update({n[:-len(suffix)]: v for n, v in result.values.items() if n.endswith(suffix)})
    loads = {"load": scene.load, "torque": scene.torque}
    for name, value in values.items():
        if name in LOAD_PARAMS:
            side, role = LOAD_PARAMS[name]
            loads[side] = set_param(loads[side], role, as_float_array(value), side)
    state = {n: values.get(n) for n in ("phi0", "dphi0")}
    # The record's sensors, with the fitted offsets, become the scene's calibration.
    sensors = _fitted_sensors(scene, result, record, values, sensors)
    scene = dataclasses.replace(scene, sensors=sensors) if sensors != scene.sensors else scene
    # A mechanism field fitted per record: the shared mechanism holds its start value.
    own = {n: float(values[n]) for n in result.mech.as_dict() if f"{n}{suffix}" in
           result.values}
    mech = result.mech.replace(**own) if own else result.mech
    return eqx.tree_at(
        lambda s: (s.mech, s.load, s.torque, s.phi0, s.dphi0), scene,
        (mech, loads["load"], loads["torque"],
         as_float_array(scene.phi0 if state["phi0"] is None else state["phi0"]),
         as_float_array(scene.dphi0 if state["dphi0"] is None else state["dphi0"])))


def _check_converged(result, anyway: bool) -> None:
    if not (result.converged or anyway):
        why = " ".join(str(result.message).split())  # one line
        raise ValueError(f"the fit did not converge ({why}): its last iterate is "
                         "no fitted scene; fix the fit, or pass anyway=True for a scene "
                         "marked unconverged")


def marked_unconverged(text: str, result) -> str:
    """Scene TOML `text` marked as the last iterate of a fit that did not converge: a
    comment at its head and a `[fit]` table at its end (last: a table takes every key
    after it), which [`fit_mark`][] reads back."""
    # A JSON string of ASCII is a TOML basic string (the messages are ours: no lone
    # surrogate, which neither could hold).
    why = json.dumps(" ".join(str(result.message).split()), ensure_ascii=True)
    return ("# NOT CONVERGED: the last iterate of a fit that did not converge, not a fitted\n"
            "# scene; `crank-jax validate` refuses it without --allow-unconverged.\n"
            + text.rstrip("\n") + "\n\n"
            f"[fit]\nconverged = false\nmessage = {why}\n")


def save_fitted_scene(scene: Scene, result, path, record: int = 0,
                      sensors: tuple[Sensor, ...] | None = None, *,
                      anyway: bool = False) -> None:
    """Write [`fitted_scene`][]`(scene, result, record, sensors)` as a scene file,
    atomically. A fit that did not converge is refused (`ValueError` naming `anyway`);
    with `anyway=True` its last iterate is written, marked in a comment and a
    `[fit] converged = false` table that [`fit_mark`][] reads and `validate` refuses."""
    fitted = fitted_scene(scene, result, record, sensors, anyway=anyway)
    text = scene_to_toml(fitted)
    if not result.converged:
        text = marked_unconverged(text, result)
    with atomic_write(path, "wb") as f:
        f.write(text.encode("utf-8"))


def fit_mark(source) -> dict | None:
    """The `[fit]` table of a scene file (None for a preset or a file without one), checked:
    `converged` a boolean, `message` a string. Raises `SceneError` naming the file."""
    if str(source) in PRESETS:
        return None
    mark = read_scene_doc(source).get("fit")
    if mark is None:
        return None
    if not isinstance(mark, dict) or not isinstance(mark.get("converged"), bool) or not (
            isinstance(mark.get("message", ""), str)) or set(mark) - {"converged", "message"}:
        raise SceneError(f"{source}: [fit] must hold converged = true or false (and "
                         "optionally message = \"...\"), as a fitted scene writes it")
    return mark
