"""Reading a record's text table: the header found, the used columns parsed as numbers,
with each refusal naming the file, the line and the fix (a CSV, a semicolon- or
whitespace-separated table, a UTF-8 or UTF-16 file, as pandas reads them).

[`load_data`][crank_jax.records.data.load_data] turns the columns into a
[`Data`][crank_jax.records.data.Data]."""

from __future__ import annotations

import csv
import os
from array import array
from collections.abc import Sequence

import numpy as np

from ..runtime.io import check_input
from .columns import role_conflict
from .fields import cut_names, split_fields, to_float

__all__ = ["read_table", "header_columns", "open_text", "numbered_lines", "find_header",
           "DataError", "MAX_RECORD_SAMPLES", "MAX_LINE_CHARS"]


class DataError(ValueError):
    """A data file or array is malformed; the message names the row or column."""


#: The most samples `load_data` reads: a longer record is refused as soon as it is
#: seen, before it fills memory (each used column takes 8 bytes per sample).
MAX_RECORD_SAMPLES = 10**7


def open_text(path: str | os.PathLike):
    """Open a text file as pandas would read it: a UTF-8 byte-order mark (as Excel writes)
    is dropped, a UTF-16 one selects UTF-16, and CRLF or CR line ends read as LF. Anything
    but a regular file (a FIFO would wait for a writer forever) is refused unopened."""
    try:
        check_input(path, "data file")
    except ValueError as e:
        raise DataError(str(e)) from None
    with open(path, "rb") as f:
        head = f.read(2)
    enc = "utf-16" if head in (b"\xff\xfe", b"\xfe\xff") else "utf-8-sig"
    return open(path, encoding=enc, errors="replace", newline=None)


def find_header(where: str, lines, t_col: str, phi_col: str, used: tuple[str, ...],
            required: Sequence[tuple[str, str]] | None = None):
    """Find the header line; return (its line number, delimiter, column names).
    `required`: (column, the argument that names it) of every column that must be there
    (default: `t_col` and `phi_col`)."""
    if required is None:
        required = ((t_col, "`t_col=`"), (phi_col, "`phi_col=`"))
    for lineno, text in lines:
        delim = "," if "," in text else (";" if ";" in text else None)
        names = split_fields(text, delim)
        dup = sorted({n for n in names if n in used and names.count(n) > 1})
        if dup:
            raise DataError(f"{where}: line {lineno}: column {dup[0]!r} appears more than "
                            "once in the header; rename one")
        for want, opt in required:
            if want in names:
                continue
            try:
                [to_float(x, delim) for x in names]
            except ValueError:
                raise DataError(f"{where}: missing column {want!r}; the header (line "
                                f"{lineno}) has {cut_names(names)}; choose the column with "
                                f"{opt}") from None
            raise DataError(f"{where}: line {lineno} is data, not a header: add a header "
                            f"line naming the columns, e.g. '{t_col},{phi_col}'")
        return lineno, delim, names
    raise DataError(f"{where}: no header line and no data (the file is empty or all "
                    "comments)")


#: The longest line `load_data` reads, in characters: a binary file or a device such
#: as /dev/zero has no line ends, and reading its "line" would fill memory.
MAX_LINE_CHARS = 1 << 16


def numbered_lines(f, where: str):
    """(line number, line without its end) for each line, refusing overlong lines."""
    for i, ln in enumerate(iter(lambda: f.readline(MAX_LINE_CHARS + 1), ""), start=1):
        if len(ln) > MAX_LINE_CHARS:
            raise DataError(f"{where}: line {i} is longer than {MAX_LINE_CHARS} characters; "
                            "this is not a text table")
        yield i, ln.rstrip("\n")


def read_table(path, t_col: str, phi_col: str, used: tuple[str, ...],
                required: Sequence[tuple[str, str]] | None = None,
                roles: Sequence[tuple[str, str]] = (),
                optional: Sequence[tuple[str, str]] = ()):
    """Read the used columns of a text table: (names, {name: array}, line numbers).

    `roles`: (column, role) of every column read; `optional`: those read only when the
    header has them (the load columns). A column with two roles is refused once the header
    is read (see [`role_conflict`][crank_jax.records.columns.role_conflict])."""
    where = str(path)
    with open_text(path) as f:
        lines = numbered_lines(f, where)
        body = ((i, ln) for i, ln in lines
                if ln.strip() and not ln.lstrip().startswith(("#", "%")))
        lineno, delim, names = find_header(where, body, t_col, phi_col, used, required)
        problem = role_conflict(list(roles) + [(c, r) for c, r in optional if c in names])
        if problem:
            raise DataError(f"{where}: {problem}")
        want = [(j, n) for j, n in enumerate(names) if n in used]
        cols = {n: array("d") for _, n in want}
        numbers = array("q")
        for ln, text in body:
            try:
                fields = split_fields(text, delim)
            except csv.Error as e:
                raise DataError(f"{where}: line {ln}: {e}") from None
            if len(fields) != len(names):
                raise DataError(f"{where}: line {ln}: {len(fields)} values but the header "
                                f"has {len(names)} columns")
            if len(numbers) >= MAX_RECORD_SAMPLES:
                raise DataError(f"{where}: more than {MAX_RECORD_SAMPLES} samples; split the "
                                "record or decimate it")
            for j, name in want:
                try:
                    cols[name].append(to_float(fields[j], delim))
                except ValueError:
                    raise DataError(f"{where}: line {ln}: column {name!r}: "
                                    f"{fields[j][:40]!r} is not a number") from None
            numbers.append(ln)
    return names, {n: np.array(c, dtype=np.float64) for n, c in cols.items()}, numbers


def header_columns(path: str | os.PathLike) -> list[str]:
    """The column names in a record's header line (the first line that is not blank or a
    comment); [`DataError`][] when there is none."""
    where = str(path)
    with open_text(path) as f:
        for _, text in numbered_lines(f, where):
            if text.strip() and not text.lstrip().startswith(("#", "%")):
                return split_fields(text, "," if "," in text else (";" if ";" in text else None))
    raise DataError(f"{where}: no header line (the file is empty or all comments)")
