"""Progress for long work: a tqdm bar on stderr, or a silent stand-in."""

from __future__ import annotations

import sys

__all__ = ["progress_bar"]


class _NoBar:
    """What `progress_bar` returns when there is no progress to show."""

    n = 0

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def update(self, n=1):
        pass

    def set_postfix(self, *args, **kwargs):
        pass


def progress_bar(total: int, desc: str, progress: bool):
    """A tqdm bar on stderr, or a silent stand-in when not `progress` (tqdm is imported
    only for a bar that shows: 0.1-0.3 s of a warm CLI fit otherwise)."""
    if not progress:
        return _NoBar()
    from tqdm import tqdm  # the text bar: it works in terminals, logs and notebooks

    return tqdm(total=total, desc=desc, file=sys.stderr, leave=False, dynamic_ncols=True)
