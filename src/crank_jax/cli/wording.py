"""The library's words in the command's: one table of argument names and their options.

A library message (an error, a warning, a note of a result) names an argument as the API
spells it, in backticks: `` `warmup=` `` alone, or with a value, `` `load_by='angle'` ``.
The command prints it with the argument replaced by its option (`--warmup`,
`--load-by angle`); an argument that no option sets stays as the library wrote it. The
marker is unambiguous: nothing else in a message is a backticked `name=`.
"""

from __future__ import annotations

import re

__all__ = ["FLAGS", "cli_message"]

#: API argument -> the command-line option that sets it (the same name in every command
#: that has it).
FLAGS: dict[str, str] = {
    # fit, validate, posterior
    "free": "--free", "per_record": "--per-record", "init": "--init",
    "init_free": "--init-free", "init_window": "--init-window", "horizon": "--horizon",
    "window": "--t-start/--t-end", "t_start": "--t-start", "t_end": "--t-end",
    "load_by": "--load-by", "max_steps": "--max-steps", "method": "--method",
    "shooting": "--shooting", "segments": "--segments", "multistart": "--multistart",
    "sigma": "--sigma", "profile": "--profile",
    "draws": "--draws", "chains": "--chains", "warmup": "--warmup", "seed": "--seed",
    # records read from files
    "channels": "--channel", "sensors": "--channel", "t_col": "--t-col",
    "phi_col": "--phi-col", "angle_unit": "--angle-unit",
    # synthesize, design
    "rate": "--rate", "t1": "--t1", "drop": "--drop", "quantization": "--quantization",
    "noise_std": "--noise-std", "jitter_std": "--jitter-std", "transient": "--transient",
    "transient_time": "--transient-time", "tones": "--tones", "iterations": "--iterations",
    "force_amplitude": "--force-amplitude", "release_speed": "--release-speed",
    "criterion": "--criterion", "target": "--target",
    # sweep (its `samples=`, the distributions, are the command's --vary), vibration
    "samples": "--vary", "n": "--n", "num_saves": "--samples", "chunk_size": "--chunk-size",
    "freq_hz": "--freq",
    # track
    "start": "--start", "start_seconds": "--start-seconds",
    "false_alarm_rate": "--false-alarm-rate", "change_ratio": "--change-ratio",
    "settle": "--settle", "every": "--every",
}

_MARK = re.compile(r"`([A-Za-z_][A-Za-z0-9_]*)=([^`]*)`")


def _option(m: re.Match) -> str:
    flag = FLAGS.get(m.group(1))
    if flag is None:
        return m.group(0)
    value = m.group(2).strip().strip("'\"")
    return f"{flag} {value}" if value else flag


def cli_message(text: str) -> str:
    """`text` with each backticked `` `name=` `` (or `` `name=value` ``) of `FLAGS`
    replaced by its option (`--name` or `--name value`)."""
    return _MARK.sub(_option, str(text))
