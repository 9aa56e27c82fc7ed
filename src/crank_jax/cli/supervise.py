"""Run a `--distributed` sweep in a child process and turn JAX's fatal aborts into one line.

Why a child: when the coordinator or a peer process goes away (killed, crashed, never
started), JAX's distributed client does not raise; its C++ code aborts the whole process
(SIGABRT, a glog `F...` line and a stack dump on stderr). No Python handler can catch that,
and the callback JAX's client accepts for it cannot be called from Python in JAX 0.10
(`std::bad_cast`). So the command runs itself again as a child, relays the child's stderr
line by line, and, if the child aborts, prints one `crank-jax: error:` line and exits 2
when the run never formed (a process did not join in time) or 1 when it broke in the
middle (a process died). stdout is the child's own (inherited).
"""

from __future__ import annotations

import codecs
import os
import re
import signal
import subprocess
import sys

__all__ = ["ENV_CHILD", "JOINED", "supervise", "die_with_parent"]

#: Set in the child's environment: it is the one that runs the sweep.
ENV_CHILD = "CRANK_JAX_SUPERVISED_CHILD"
#: The line a child prints on stderr once every process has joined (not relayed).
JOINED = "crank-jax: joined the distributed run"
# glog's line prefix: severity letter, MMDD, time, thread, file:line].
_GLOG = re.compile(r"^([FEWI])\d{4} \d\d:\d\d:\d\d\.\d+\s+\d+ [^\]]+\] ?(.*)")


def supervise(argv: list[str], address: str, wait: int) -> int:
    """Run `crank-jax argv` as a child with `ENV_CHILD` set; return its exit status, or
    print one line and return 2 (never joined) / 1 (a process died in the run) when it
    aborted. `address` and `wait` (s) only word the message."""
    env = dict(os.environ, **{ENV_CHILD: "1"})
    child = subprocess.Popen([sys.executable, "-m", "crank_jax", *argv], env=env,
                             stderr=subprocess.PIPE)
    joined, fatal, aborted, buf = False, None, False, ""
    text = codecs.getincrementaldecoder("utf-8")("replace")
    try:
        while data := os.read(child.stderr.fileno(), 65536):
            # Relay as it comes, a progress bar's '\r' updates included.
            parts = re.split(r"(?<=[\r\n])", buf + text.decode(data))
            buf = parts.pop()
            for line in parts:
                if line.rstrip("\r\n") == JOINED:
                    joined = True
                    continue
                m = _GLOG.match(line)
                if m or aborted or line.startswith("[Gloo] "):
                    # XLA's C++ log lines, Gloo's "connected" notes and, after a fatal
                    # line, its stack dump: kept off the user's stderr (the one line
                    # below says what happened).
                    if m and m.group(1) == "F":
                        fatal, aborted = m.group(2), True
                    continue
                sys.stderr.write(line)
                sys.stderr.flush()
        if buf and not aborted:
            sys.stderr.write(buf)
        code = child.wait()
    except BaseException:
        # Ctrl-C, SIGTERM, SIGHUP: the child gets the same signal (it cleans up its
        # temporary files), then the parent reports as usual.
        if child.poll() is None:
            child.send_signal(signal.SIGTERM)
            child.wait()
        raise
    if code >= 0 and fatal is None:
        return code
    if fatal is None:
        # Killed from outside (the OOM killer, a user's SIGKILL), not a JAX abort.
        print(f"crank-jax: error: --distributed: the sweep's process was ended by "
              f"{signal.Signals(-code).name}; --out was not written", file=sys.stderr)
        return 1
    status = re.search(r"absl::Status: ([^\n]*)", fatal or "")
    why = (status.group(1) if status else fatal).split(". ")[0][:200]
    if not joined:
        print(f"crank-jax: error: --distributed: the run did not form: not every process "
              f"joined the coordinator {address} within {wait} s ({why}); start all "
              "JAX_NUM_PROCESSES processes with the same JAX_COORDINATOR_ADDRESS, or set "
              "CRANK_JAX_DISTRIBUTED_TIMEOUT", file=sys.stderr)
        return 2
    print(f"crank-jax: error: --distributed: another process of the run, or its "
          f"coordinator {address}, went away ({why}); --out was not written. Rerun every "
          "process (with --checkpoint only the missing chunks are computed)",
          file=sys.stderr)
    return 1


def die_with_parent() -> None:
    """In the child: end (as if SIGKILLed, status 137) within a second of the supervising
    parent's death, so that killing the command kills the run (and its peers learn of it),
    not only the parent."""
    import threading
    import time

    parent = os.getppid()

    def watch():
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(128 + signal.SIGKILL)

    threading.Thread(target=watch, name="crank-jax-parent-watch", daemon=True).start()
