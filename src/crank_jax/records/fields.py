"""The fields of a text table's lines: splitting a line (CSV quoting, or whitespace),
reading a number (decimal commas too), and labels for messages. A leaf module:
[`crank_jax.records.data`][] reads records with it and raises its `DataError`."""

from __future__ import annotations

import csv
from array import array

__all__ = ["split_fields", "to_float", "cut_names", "LineLabels"]


def _unquote(x: str) -> str:
    x = x.strip()
    return x[1:-1].strip() if len(x) >= 2 and x[0] == x[-1] == '"' else x


def split_fields(line: str, delim: str | None) -> list[str]:
    """Fields of one line: `csv` quoting rules for `,` and `;`, else whitespace
    (`csv.Error` for a malformed line)."""
    if delim is None:
        return [_unquote(x) for x in line.split()]
    if '"' not in line and "\r" not in line and "\0" not in line:
        # Nothing `csv` treats specially (a quote, a line break, NUL): its fields are the
        # line cut at each delimiter, without the cost of a reader a line.
        return [x.strip() for x in line.split(delim)]
    return [_unquote(x) for x in next(csv.reader([line], delimiter=delim))]


def to_float(x: str, delim: str | None) -> float:
    """A field as a number (`ValueError` when it is none); in a semicolon-separated file a
    decimal comma is read too."""
    try:
        return float(x)
    except ValueError:
        # Excel in many locales writes "1,5" in semicolon-separated files.
        if delim == ";" and x.count(",") == 1:
            return float(x.replace(",", "."))
        raise


def cut_names(names: list[str], limit: int = 8) -> str:
    """The first `limit` names of a header, as a short list for a message."""
    text = repr(names[:limit])[:-1] + (", ...]" if len(names) > limit else "]")
    return text if len(text) <= 200 else text[:197] + "..."


class LineLabels:
    """Row labels `line N` of a table's samples (`numbers[i]` is sample i's line), without
    a string per row in memory."""

    def __init__(self, numbers: array):
        self.numbers = numbers

    def __getitem__(self, i: int) -> str:
        return f"line {self.numbers[i]}"
