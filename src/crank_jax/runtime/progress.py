"""Progress for long work: a tqdm bar on a terminal, a line every few seconds in a log,
or a silent stand-in."""

from __future__ import annotations

import sys
import time

__all__ = ["progress_bar", "LOG_INTERVAL"]

#: Seconds between two progress lines when stderr is not a terminal (a log file, a pipe):
#: a bar's carriage-return updates there are hundreds of kilobytes for a long fit.
LOG_INTERVAL = 5.0


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

    def close(self):
        pass


class _LogBar(_NoBar):
    """Progress as whole lines on `file`: `desc: n/total unit (postfix), elapsed`, at most
    one every `interval` s, and a last one when the work ends (if any was printed or it
    took over `interval`)."""

    def __init__(self, total, desc: str, unit: str, file, interval: float | None = None):
        self.total, self.desc, self.unit, self.file = total, desc, unit, file
        # The module's LOG_INTERVAL as it is when the bar starts (a test may shorten it).
        self.interval = LOG_INTERVAL if interval is None else interval
        self.n, self.postfix = 0, ""
        self.t0 = self.last = time.monotonic()
        self.printed, self.closed, self.shown = False, False, None

    def update(self, n=1):
        self.n += n
        if time.monotonic() - self.last >= self.interval:
            self._line()

    def set_postfix(self, *args, **kwargs):
        items = dict(*args, **kwargs)
        self.postfix = ", ".join(f"{k}={v}" for k, v in items.items())

    def _line(self):
        self.last, self.shown = time.monotonic(), (self.n, self.postfix)
        total = f"/{self.total}" if self.total else ""
        extra = f" ({self.postfix})" if self.postfix else ""
        print(f"{self.desc}: {self.n}{total} {self.unit}{extra}, "
              f"{self.last - self.t0:.0f} s", file=self.file, flush=True)
        self.printed = True

    def close(self):
        # The last line, unless the last update's line already said it.
        long = self.printed or time.monotonic() - self.t0 >= self.interval
        if not self.closed and long and self.shown != (self.n, self.postfix):
            self._line()
        self.closed = True

    def __exit__(self, *exc):
        self.close()
        return False


def progress_bar(total: int | None, desc: str, progress: bool, unit: str = "it",
                 **tqdm_options):
    """A progress display on stderr for `total` units of work: a tqdm bar when stderr is a
    terminal, a whole line every [`LOG_INTERVAL`][] s when it is not (a log, a pipe), or a
    silent stand-in when not `progress` (tqdm is imported only for a bar that shows: 0.1-0.3
    s of a warm CLI fit otherwise). `tqdm_options` go to the bar (e.g. `unit_scale`)."""
    if not progress:
        return _NoBar()
    if not _terminal(sys.stderr):
        return _LogBar(total, desc, unit, sys.stderr)
    from tqdm import tqdm  # the text bar: it works in terminals and notebooks

    options = dict(leave=False, dynamic_ncols=True) | tqdm_options
    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, **options)


def _terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # a closed or stand-in stream
        return False
