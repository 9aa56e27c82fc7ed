"""Read a long record a chunk of rows at a time: a plain text table (a header naming the
columns, then numbers; comma-, semicolon- or whitespace-separated; `#`/`%` comment and
blank lines skipped) or a `.npy` array (read a block at a time), so that a record of 10^7 samples
never sits in memory whole. Each chunk is checked as [`load_data`][crank_jax.load_data]
checks a record: numbers, finite, times strictly increasing (across chunks too)."""

from __future__ import annotations

import csv
import itertools
import os
from collections.abc import Iterator, Sequence

import numpy as np

from .fields import split_fields, to_float
from .table import DataError, find_header, numbered_lines, open_text

__all__ = ["RecordChunks"]


class RecordChunks:
    """The columns `[t_col, *columns]` of the record at `path`, `rows` rows at a time.

    Iterating yields `(t (k,), values (k, C))`, float64, k <= `rows`; a new iteration
    reads the file again from its start. A `.npy` file holds a (n, 1 + C) array whose
    columns are `t` and `columns` in that order (read a block of rows at a time).
    Raises `DataError` (a `ValueError`) naming the line (or row) and
    column of a bad value, and the column missing from the header."""

    def __init__(self, path: str | os.PathLike, columns: Sequence[str], t_col: str = "t",
                 rows: int = 4096):
        self.path, self.columns, self.t_col = str(path), tuple(columns), t_col
        self.rows = int(rows)
        if not self.columns:
            raise DataError(f"{self.path}: name at least one channel column to read")
        self.npy = self.path.endswith(".npy")
        if self.npy:
            shape = self._npy_layout()[0]
            if len(shape) != 2 or shape[1] != 1 + len(self.columns):
                raise DataError(f"{self.path}: a .npy record is an (n, {1 + len(columns)}) "
                                f"array (columns {[t_col, *self.columns]}), got shape "
                                f"{shape}")
        else:
            with open_text(self.path) as f:
                self._layout(_body(numbered_lines(f, self.path)))

    def _npy_layout(self):
        """The .npy file's shape, dtype and the offset of its data."""
        try:
            with open(self.path, "rb") as f:
                fmt = np.lib.format
                read = (fmt.read_array_header_1_0 if fmt.read_magic(f) == (1, 0)
                        else fmt.read_array_header_2_0)
                shape, fortran, dtype = read(f)
                offset = f.tell()
        except (ValueError, OSError) as e:
            raise DataError(f"{self.path}: not a readable .npy array ({e})") from None
        if fortran or dtype.kind not in "fi" or dtype.hasobject:
            raise DataError(f"{self.path}: a .npy record is a C-ordered array of numbers, "
                            f"got dtype {dtype} ({'Fortran' if fortran else 'C'} order)")
        return shape, dtype, offset

    def _layout(self, body) -> None:
        _, self.delim, names = find_header(self.path, body, self.t_col, self.columns[0],
                                       (self.t_col, *self.columns),
                                       [(self.t_col, "t_col="),
                                        *((c, "channels=") for c in self.columns)])
        self.width = len(names)
        self.index = [names.index(c) for c in (self.t_col, *self.columns)]

    def __iter__(self) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        last = -np.inf
        for where, block in (self._npy_blocks() if self.npy else self._text_blocks()):
            _check_block(self.path, where, block, (self.t_col, *self.columns), last)
            last = float(block[-1, 0])
            yield np.ascontiguousarray(block[:, 0]), np.ascontiguousarray(block[:, 1:])

    def _npy_blocks(self):
        # Read with plain reads, not a memory map: a map's pages count in the process's
        # resident memory as they are touched, the whole file by the end.
        shape, dtype, offset = self._npy_layout()
        n, width = shape
        with open(self.path, "rb") as f:
            f.seek(offset)
            for lo in range(0, n, self.rows):
                k = min(self.rows, n - lo)
                block = np.fromfile(f, dtype=dtype, count=k * width)
                if block.size != k * width:
                    raise DataError(f"{self.path}: the file ends at row {lo + block.size // width}"
                                    f" of the {n} its header promises")
                yield np.arange(lo, lo + k), block.reshape(k, width).astype(np.float64)

    def _text_blocks(self):
        with open_text(self.path) as f:
            body = _body(numbered_lines(f, self.path))
            self._layout(body)
            while True:
                lines = list(itertools.islice(body, self.rows))
                if not lines:
                    return
                yield np.array([i for i, _ in lines]), self._parse(lines)

    def _parse(self, lines) -> np.ndarray:
        """The used columns of `lines` ((number, text) each), (k, 1 + C)."""
        try:
            if self.delim is None:
                rows = [ln.split() for _, ln in lines]
            else:
                rows = [ln.split(self.delim) for _, ln in lines]
            arr = np.array(rows, dtype=np.float64)
            if arr.ndim == 2 and arr.shape[1] == self.width:
                return arr[:, self.index]
        except ValueError:
            pass
        return self._parse_slowly(lines)

    def _parse_slowly(self, lines) -> np.ndarray:
        """As `_parse`, field by field (quotes, decimal commas), naming a bad line."""
        out = np.empty((len(lines), len(self.index)))
        for r, (ln, text) in enumerate(lines):
            try:
                fields = split_fields(text, self.delim)
            except csv.Error as e:
                raise DataError(f"{self.path}: line {ln}: {e}") from None
            if len(fields) != self.width:
                raise DataError(f"{self.path}: line {ln}: {len(fields)} values but the "
                                f"header has {self.width} columns")
            for j, col in enumerate(self.index):
                try:
                    out[r, j] = to_float(fields[col], self.delim)
                except ValueError:
                    name = (self.t_col, *self.columns)[j]
                    raise DataError(f"{self.path}: line {ln}: column {name!r}: "
                                    f"{fields[col][:40]!r} is not a number") from None
        return out


def _body(lines):
    return ((i, ln) for i, ln in lines if ln.strip() and not ln.lstrip().startswith(("#", "%")))


def _check_block(path: str, where: np.ndarray, block: np.ndarray, names, last: float) -> None:
    """Finite values and strictly increasing times, from `last` (the time before)."""
    label = "row" if path.endswith(".npy") else "line"
    bad = ~np.isfinite(block)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise DataError(f"{path}: {label} {int(where[r])}: column {names[c]!r} is not "
                        f"finite ({float(block[r, c])})")
    t = np.concatenate([[last], block[:, 0]])
    step = np.diff(t)
    if (step <= 0).any():
        r = int(np.flatnonzero(step <= 0)[0])
        raise DataError(f"{path}: {label} {int(where[r])}: time {float(block[r, 0])!r} does "
                        f"not increase (the sample before: {float(t[r])!r}); sort the record")
