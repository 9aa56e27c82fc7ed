"""Per-sample predictions beside the measurements, for `fit.json`, `val.json` and the
`--predictions CSV` of `fit` and `validate`: what a user needs to plot or score a model
without the Python API.

One record's table is `{"t": [...], CHANNEL: {"measured": [...], "predicted": [...]}}`
(s, and each channel in its SI unit: rad, rad/s, m, m/s, m/s^2); a value that is not a
finite number (a prediction whose solve failed) is `null`. The CSV has one row per
sample: `record` (0-based), `t`, then `CHANNEL_measured`, `CHANNEL_predicted` for every
channel of any record (empty where a record lacks it).
"""

from __future__ import annotations

import csv
import os
from collections.abc import Mapping, Sequence

import numpy as np

from ..runtime.io import atomic_write
from .outcome import finite as _num

__all__ = ["prediction_table", "write_predictions_csv"]


def prediction_table(ts, measured: Mapping[str, np.ndarray],
                     predicted: Mapping[str, np.ndarray] | None) -> dict:
    """One record's table (see the module's docstring): the sample times `ts` (n,), s, and
    per channel its measured and predicted readings (n,), SI (`predicted` None: no
    prediction, every value null)."""
    ts = np.asarray(ts, dtype=float)
    out: dict = {"t": [float(t) for t in ts]}
    for name, y in measured.items():
        yhat = (np.full(ts.shape, np.nan) if predicted is None or name not in predicted
                else np.asarray(predicted[name], dtype=float))
        if yhat.shape != ts.shape or np.asarray(y).shape != ts.shape:
            raise ValueError(f"channel {name!r}: {np.asarray(y).shape[0]} measured and "
                             f"{yhat.shape[0]} predicted samples for {ts.shape[0]} times")
        out[name] = {"measured": [_num(v) for v in np.asarray(y, dtype=float)],
                     "predicted": [_num(v) for v in yhat]}
    return out


def write_predictions_csv(path: str | os.PathLike, tables: Sequence[dict]) -> None:
    """Write the tables of [`prediction_table`][] (one per record) as one CSV to `path`,
    atomically (an existing file is replaced only once the new one is complete)."""
    names: list[str] = []
    for table in tables:  # the channels: `t`, `source` and `scored` are not
        names += [n for n, v in table.items() if isinstance(v, dict) and n not in names]
    header = ["record", "t"] + [f"{n}_{kind}" for n in names
                                for kind in ("measured", "predicted")]

    def cell(v) -> str:
        return "" if v is None else repr(float(v))

    with atomic_write(path) as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(header)
        for i, table in enumerate(tables):
            for k, t in enumerate(table["t"]):
                row = [str(i), repr(float(t))]
                for n in names:
                    ch = table.get(n)
                    row += (["", ""] if ch is None
                            else [cell(ch["measured"][k]), cell(ch["predicted"][k])])
                w.writerow(row)
