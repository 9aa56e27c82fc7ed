"""`crank-jax sweep` (Monte Carlo sweeps).

    crank-jax sweep lab-rig --vary k=normal(2.0,0.1) --vary c=uniform(0.005,0.02) \\
        --n 100000 --out sweep.npz --summary
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from ..solve.names import SOLVERS
from .environment import check_cluster_env, env_int
from .errors import UserError
from .options import seed
from .scene_inputs import refuse_input_loads

_ENV_DISTRIBUTED = "CRANK_JAX_DISTRIBUTED"
#: Seconds to wait for the coordinator and every process when joining (default 60).
_ENV_TIMEOUT = "CRANK_JAX_DISTRIBUTED_TIMEOUT"


def _sweep_args(p: argparse.ArgumentParser) -> None:
    from ..sweep.plan import VARIABLES
    from ..sweep.reductions import DEFAULT_OUTPUTS, REDUCTIONS

    p.add_argument("scene", help="preset name (see `crank-jax scenes`) or a TOML scene file")
    p.add_argument("--vary", action="append", default=[], metavar="NAME=DIST",
                   help="vary NAME by DIST: normal(mu,sd), uniform(lo,hi), "
                        "lognormal(median,sigma), loguniform(lo,hi), const(x) or a number; "
                        f"NAME is one of {', '.join(VARIABLES)}. Repeat for several.")
    p.add_argument("--n", type=int, required=True, help="number of samples")
    p.add_argument("--seed", type=seed, default=0, help="random seed (default 0)")
    p.add_argument("--out", required=True, help="output .npz file")
    p.add_argument("--outputs", default=",".join(DEFAULT_OUTPUTS),
                   help=f"comma-separated reductions from {', '.join(REDUCTIONS)} "
                        f"(default {','.join(DEFAULT_OUTPUTS)}; phi/dphi store trajectories)")
    p.add_argument("--t1", type=float, help="end time, s (default: the scene's)")
    p.add_argument("--samples", type=int, help="number of save times on [0, t1]")
    p.add_argument("--solver", help=f"one of {', '.join(SOLVERS)} (default: the scene's; "
                                    "auto is decided per chunk)")
    p.add_argument("--max-steps", type=int, default=100_000, help="step budget per sample")
    p.add_argument("--chunk-size", type=int, default=1024,
                   help="samples per compiled call (bounds device memory; the samples drawn "
                        "do not depend on it)")
    p.add_argument("--checkpoint", metavar="DIR",
                   help="save each finished chunk in DIR; rerunning the same command after "
                        "an interruption computes only the missing chunks")
    p.add_argument("--save-trajectories", metavar="DIR",
                   help="stream every solved sample's phi and dphi to DIR, chunk by chunk "
                        "(.npy files and a manifest.json; read lazily with "
                        "crank_jax.load_trajectories or np.load(mmap_mode='r'))")
    p.add_argument("--save-every", type=int, metavar="K",
                   help="with --save-trajectories (refused without it): keep every K-th "
                        "save time (default 1)")
    p.add_argument("--summary", action="store_true",
                   help="print statistics of every output (JSON) on stdout")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--distributed", action="store_true",
                   help=f"join a multi-host run via jax.distributed (also: {_ENV_DISTRIBUTED}=1)"
                        "; the cluster comes from JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES, "
                        "JAX_PROCESS_ID or SLURM/MPI auto-detection")


def _parse_vary(items: list[str]) -> dict[str, object]:
    from ..sweep.distributions import parse_distribution
    from ..sweep.plan import VARIABLES

    spec: dict[str, object] = {}
    for item in items:
        name, sep, text = item.partition("=")
        name = name.strip()
        if not sep or not name or not text.strip():
            raise UserError(f"--vary {item!r}: expected NAME=DIST, e.g. k=normal(2.0,0.1)")
        if name not in VARIABLES:
            raise UserError(f"--vary {item!r}: cannot vary {name!r}; choose from "
                            f"{', '.join(VARIABLES)}")
        if name in spec:
            raise UserError(f"--vary {name} given twice")
        try:
            spec[name] = parse_distribution(text)
        except ValueError as e:
            raise UserError(f"--vary {item!r}: {e}") from None
    return spec


def _check_dirs(a: argparse.Namespace) -> None:
    """--checkpoint and --save-trajectories: not empty (the current directory), and no two
    of them and --out the same path (found only after the work)."""
    from ..runtime.io import same_file

    named = [(o, v) for o, v in (("--checkpoint", a.checkpoint),
                                 ("--save-trajectories", a.save_trajectories)) if v is not None]
    for option, value in named:
        if not value.strip():
            raise UserError(f"{option} is empty; name a directory for it (it would write into "
                            "the current directory)")
    paths = [("--out", a.out)] + named
    for i, (o1, p1) in enumerate(paths):
        for o2, p2 in paths[i + 1:]:
            if same_file(p1, p2):
                raise UserError(f"{o1} and {o2} name the same path {p1!r}; give each its own")


def _wait_for_coordinator(wait: int) -> None:
    """A process other than 0 first waits (at most `wait` s) until the coordinator accepts
    connections (the library's `wait_for_coordinator`: JAX aborts the whole process, with
    a C++ stack dump, when it cannot reach it); its error in the command's words."""
    from ..sweep.collective import wait_for_coordinator

    try:
        wait_for_coordinator({"initialization_timeout": wait})
    except RuntimeError as e:
        raise UserError(f"--distributed: {e}; or set {_ENV_TIMEOUT}") from None


def _join(a: argparse.Namespace) -> int | None:
    """Join the distributed run (`--distributed`). The command first runs itself as a
    child under `supervise` (JAX aborts a process whose peer or coordinator goes away);
    returns the child's exit status, or `None` in the child, once every process joined."""
    from .supervise import ENV_CHILD, JOINED, die_with_parent, supervise

    # Bounded: JAX waits 300 s for a missing coordinator or peer by default, and 100 s
    # for a silent peer's heartbeat.
    wait = env_int(_ENV_TIMEOUT, 60, 1, "the seconds to wait for the other processes")
    check_cluster_env()
    address = os.environ.get("JAX_COORDINATOR_ADDRESS", "auto-detected")
    if not os.environ.get(ENV_CHILD):
        return supervise(a._argv[1:], address, wait)
    from ..sweep.run import initialize_distributed

    die_with_parent()
    _wait_for_coordinator(wait)
    try:
        initialize_distributed(initialization_timeout=wait,
                               heartbeat_timeout_seconds=max(wait, 10))
    except (RuntimeError, ValueError) as e:
        first = (str(e).strip().splitlines() or [type(e).__name__])[0][:300]
        raise UserError(f"--distributed: could not join the run (coordinator {address}) "
                        f"within {wait} s ({_ENV_TIMEOUT} sets the wait): {first}") from None
    print(JOINED, file=sys.stderr, flush=True)
    return None


def _sweep_run(a: argparse.Namespace) -> int:
    if a.distributed or os.environ.get(_ENV_DISTRIBUTED, "") not in ("", "0"):
        code = _join(a)
        if code is not None:
            return code
    import jax
    import numpy as np

    from ..runtime.io import check_output
    from ..scene import load_scene
    from ..sweep.reductions import REDUCTIONS
    from ..sweep.run import sweep

    spec = _parse_vary(a.vary)
    outputs = [o.strip() for o in a.outputs.split(",") if o.strip()]
    for o in outputs:
        if o not in REDUCTIONS:
            raise UserError(f"--outputs: unknown output {o!r}; choose from "
                            f"{', '.join(REDUCTIONS)}")
    if a.n < 1:
        raise UserError(f"--n must be >= 1, got {a.n}")
    if a.solver is not None and a.solver not in SOLVERS:
        raise UserError(f"--solver {a.solver!r} is unknown; choose from {', '.join(SOLVERS)}")
    if a.t1 is not None and not (np.isfinite(a.t1) and a.t1 > 0):
        raise UserError(f"--t1 must be a finite time > 0 s, got {a.t1}")
    if a.samples is not None and a.samples < 2:
        raise UserError(f"--samples must be >= 2, got {a.samples}")
    if a.max_steps < 1 or a.chunk_size < 1:
        raise UserError("--max-steps and --chunk-size must be >= 1")
    if a.save_every is not None and a.save_trajectories is None:
        raise UserError("--save-every thins the saved trajectories: give --save-trajectories "
                        "DIR with it, or leave it out")
    if a.save_every is not None and a.save_every < 1:
        raise UserError(f"--save-every must be >= 1, got {a.save_every}")
    _check_dirs(a)
    if not a.out.endswith(".npz"):
        # np.savez would silently append ".npz" to another name; say so instead.
        raise UserError(f"--out must end in .npz, got {a.out!r}")
    check_output(a.out, [a.scene], "--out")
    scene = load_scene(a.scene)
    refuse_input_loads(scene, a.scene, "sweep")
    result = sweep(scene, spec, outputs, n=a.n, seed=a.seed, t1=a.t1, num_saves=a.samples,
                   solver=a.solver, max_steps=a.max_steps, chunk_size=a.chunk_size,
                   progress=not a.quiet, checkpoint=a.checkpoint,
                   save_trajectories=a.save_trajectories, trajectory_every=a.save_every or 1)
    if jax.process_index() == 0:
        result.save(a.out)
        counts = result.counts()
        failed = ", ".join(f"{v} {k}" for k, v in counts.items() if k != "ok" and v)
        print(f"wrote {a.out}: {result.n} samples of {', '.join(outputs)} "
              f"({counts['ok']} ok{'; ' + failed if failed else ''}; "
              f"{jax.device_count()} device(s), {jax.process_count()} process(es))",
              file=sys.stderr)
        if a.summary:
            print(json.dumps({"n": result.n, "status": counts, "seed": a.seed,
                              "varied": {k: str(v) for k, v in spec.items()},
                              "outputs": result.summary()}, indent=2))
    return 0


#: Subcommands added to `crank-jax` (see `cli.COMMANDS` for the tuple layout).
COMMANDS: list = [
    ("sweep", "Monte Carlo sweep of a scene over sampled values; writes an .npz",
     _sweep_args, _sweep_run),
]
