"""Progress that fits a log: whole lines every few seconds when stderr is not a terminal,
never a carriage-return stream."""

import io

from crank_jax.runtime import progress


def _clock(monkeypatch, step: int) -> None:
    """The progress module's clock: each reading `step` s after the last."""
    clock = iter(float(t) for t in range(0, 1000, step))
    monkeypatch.setattr(progress.time, "monotonic", lambda: next(clock))


def _updates(bar, n: int, **postfix) -> None:
    for _ in range(n):
        bar.update()
    if postfix:
        bar.set_postfix(**postfix)


def test_progress_in_a_log_is_whole_lines_at_an_interval(capsys, monkeypatch):
    _clock(monkeypatch, 2)
    with progress.progress_bar(100, "fit", True, unit="it") as bar:
        _updates(bar, 10, rms=0.5)
    err = capsys.readouterr().err
    assert "\r" not in err
    lines = err.splitlines()
    # 2 s a reading, a line at most every LOG_INTERVAL = 5 s, and one at the end.
    assert 3 <= len(lines) <= 5, lines
    assert lines[0].startswith("fit: ") and "/100 it" in lines[0]
    assert lines[-1].startswith("fit: 10/100 it (rms=0.5), ")


def test_short_work_in_a_log_prints_nothing(capsys):
    with progress.progress_bar(3, "fit", True) as bar:
        bar.update(3)
    assert capsys.readouterr().err == ""


def test_a_terminal_gets_the_bar_and_no_progress_gets_nothing(monkeypatch):
    class Tty(io.StringIO):
        def isatty(self):
            return True

    monkeypatch.setattr(progress.sys, "stderr", Tty())
    bar = progress.progress_bar(5, "fit", True)
    assert type(bar).__name__ == "tqdm"
    bar.close()
    assert type(progress.progress_bar(5, "fit", False)).__name__ == "_NoBar"


def test_a_log_does_not_repeat_its_last_line(capsys, monkeypatch):
    # A line printed at the last update is the end's line too: close adds none, unless
    # something changed since (here the postfix).
    _clock(monkeypatch, 6)
    with progress.progress_bar(4, "sweep", True, unit="sample") as bar:
        _updates(bar, 4)
    lines = capsys.readouterr().err.splitlines()
    assert lines[-1].startswith("sweep: 4/4 sample") and len(lines) == len(set(lines)) == 4
    with progress.progress_bar(4, "fit", True) as bar:
        bar.update(4)
        bar.set_postfix(rms=0.5)
    lines = capsys.readouterr().err.splitlines()
    assert lines == [lines[0], lines[1]] and lines[1].startswith("fit: 4/4 it (rms=0.5)")
