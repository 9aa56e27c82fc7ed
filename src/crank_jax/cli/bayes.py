"""`crank-jax posterior` (NUTS over a fit's parameters) and `crank-jax design` (an
excitation chosen for the Fisher information)."""

from __future__ import annotations

import argparse
import json
import sys

from .channel_options import add_angle_options, add_channel_options, read_records
from .errors import UserError
from .load_by_option import add_load_by_option, load_by_words
from .options import free_list, seed
from .scene_inputs import refuse_input_loads
from .wording import cli_message

# --- posterior --------------------------------------------------------------------------


def _posterior_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", help="CSV record (t,phi[,P][,tau])")
    p.add_argument("scene", help="preset name or TOML scene file (its [priors] table gives "
                                 'priors, e.g. k = "lognormal(2, 0.5)"; default flat)')
    p.add_argument("--more-data", action="append", default=[], metavar="CSV",
                   help="another record of the same mechanism (repeatable)")
    add_channel_options(p)  # records are read as fit reads them (the scene's [sensors])
    add_angle_options(p)
    add_load_by_option(p)
    # The record options `fit` and `validate` take (read alike by `read_records`).
    p.add_argument("--t-col", default="t", help="name of the time column (t)")
    p.add_argument("--load-interp", default="cubic", choices=("cubic", "linear", "zoh"),
                   help="interpolation of the record's P/tau columns: cubic (default), "
                        "linear, or zoh (a held digital command)")
    p.add_argument("--free", default="k,c,phi0,dphi0",
                   help="comma-separated free parameters (default k,c,phi0,dphi0)")
    p.add_argument("--draws", type=int, default=1000, help="draws per chain (1000)")
    p.add_argument("--chains", type=int, default=4, help="chains (4)")
    p.add_argument("--warmup", type=int, default=500, help="warm-up steps per chain (500)")
    p.add_argument("--seed", type=seed, default=0, help="seed of the sampler (0)")
    p.add_argument("--t-start", type=float, dest="fit_t_start",
                   help="use only samples at or after this time, s")
    p.add_argument("--t-end", type=float, dest="fit_t_end",
                   help="use only samples at or before this time, s")
    p.add_argument("--out", required=True, help="posterior summary and draws (JSON)")
    p.add_argument("--plot", help="corner plot with the Laplace ellipses (PNG)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def _posterior_check(a: argparse.Namespace) -> tuple[str, ...]:
    from ..bayes.posterior import check_posterior_memory
    from ..runtime.io import check_distinct_outputs, check_figure_format, check_output

    free = free_list(a.free)
    for option, value, lo in (("--draws", a.draws, 1), ("--chains", a.chains, 1),
                              ("--warmup", a.warmup, 0)):
        if value < lo:
            raise UserError(f"{option} must be >= {lo}, got {value}")
    if a.chains > 1 and a.draws < 4:
        raise UserError(f"--draws must be >= 4 with several chains, got {a.draws}")
    # Each further record adds its own phi0 and dphi0 (when free): the most parameters.
    p = len(free) + 2 * len(a.more_data)
    check_posterior_memory(a.draws, a.chains, a.warmup, p)
    inputs = [a.data, *a.more_data, a.scene]
    check_output(a.out, inputs, "--out")
    if a.plot:
        check_output(a.plot, inputs, "--plot")
        check_figure_format(a.plot, "--plot")
    check_distinct_outputs([(a.out, "--out"), (a.plot, "--plot")])
    return free


def _posterior_run(a: argparse.Namespace) -> int:
    from ..bayes.posterior import posterior
    from ..bayes.priors import load_priors, parse_priors
    from ..runtime.io import atomic_write
    from ..scene import load_scene

    free = _posterior_check(a)
    scene = load_scene(a.scene)
    priors = parse_priors(load_priors(a.scene), free, where=f"{a.scene}: [priors]")
    files = [a.data, *a.more_data]
    records = read_records(a, scene, files)
    lo, hi = a.fit_t_start, a.fit_t_end
    window = None if lo is None and hi is None else (lo, hi)
    with load_by_words():
        post = posterior(scene, records if len(records) > 1 else records[0], free, priors,
                         draws=a.draws, chains=a.chains, seed=a.seed, warmup=a.warmup,
                         window=window, progress=not a.quiet, load_by=a.load_by)
    print(f"{'name':>10} {'mean':>12} {'sd':>10} {'q2.5':>12} {'q97.5':>12} {'rhat':>6} "
          f"{'ess':>6}")
    for n, s in post.summary().items():
        print(f"{n:>10} {s['mean']:12.6g} {s['sd']:10.3g} {s['q2.5']:12.6g} "
              f"{s['q97.5']:12.6g} {s['rhat']:6.3f} {s['ess_bulk']:6.0f}")
    print(f"{post.chains} chain{'s' if post.chains != 1 else ''} x {post.n_draws} draws "
          f"after {post.warmup} warm-up steps in {post.seconds:.1f} s; {post.divergences} "
          "divergences" + ("" if post.reliable else "; UNRELIABLE: a chain never moved"))
    for w in post.warnings:
        print(f"crank-jax: warning: {cli_message(w)}", file=sys.stderr)
    if post.divergences:
        print(f"crank-jax: warning: {post.divergences} divergent transitions: the posterior "
              "may be under-explored; try a longer --warmup or priors", file=sys.stderr)
    bad = [n for n, r in post.rhat.items() if r > 1.01]
    if bad:
        print(f"crank-jax: warning: R-hat above 1.01 for {', '.join(bad)}: the chains "
              "disagree; run more --draws or --warmup", file=sys.stderr)
    with atomic_write(a.out) as f:
        json.dump(post.to_json(), f, indent=1, allow_nan=True)
        f.write("\n")
    print(f"wrote {a.out}", file=sys.stderr)
    if not post.reliable:
        # A stuck chain's draws repeat its start: sd 0 would read as certainty. The JSON
        # says so (reliable: false); no corner plot draws it, and the run fails.
        raise RuntimeError(f"the posterior is unreliable: chain(s) "
                           f"{', '.join(map(str, post.stuck))} never moved (see the warning); "
                           f"{a.out} is marked reliable = false" +
                           (f" and {a.plot} was not drawn" if a.plot else ""))
    if a.plot:
        from ..bayes.corner import plot_corner

        plot_corner(post, a.plot, title=f"{', '.join(files)} with {a.scene}")
        print(f"wrote {a.plot}", file=sys.stderr)
    return 0


# --- design -----------------------------------------------------------------------------


def _design_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", help="preset name or TOML scene file (the design point)")
    p.add_argument("--free", required=True,
                   help="comma-separated parameters to identify, e.g. m_s,I_p,k,c")
    p.add_argument("--t1", type=float, required=True, help="record duration, s")
    p.add_argument("--rate", type=float, required=True, help="sample rate, Hz")
    p.add_argument("--torque-amplitude", type=float, required=True,
                   help="bound on the crank torque's magnitude, N*m")
    p.add_argument("--force-amplitude", type=float,
                   help="also design a multisine slider force of this peak, N (the scene "
                        "must have no slider load)")
    p.add_argument("--release", action="store_true",
                   help="also design the release angle phi0")
    p.add_argument("--release-speed", type=float,
                   help="also design the release speed dphi0, within +-this, rad/s")
    p.add_argument("--tones", type=int, default=6, help="sines in the multisine (6)")
    p.add_argument("--criterion", default="D", choices=("D", "c"),
                   help="D: max log det Fisher (default); c: min the variance of --target")
    p.add_argument("--target", help="the parameter whose variance criterion c minimizes")
    p.add_argument("--noise-std", type=float, default=1e-3,
                   help="angle noise, rad (1e-3; scales the predicted standard errors)")
    p.add_argument("--iterations", type=int, default=60, help="Adam iterations (60)")
    p.add_argument("--seed", type=seed, default=0, help="seed of the start phases (0)")
    p.add_argument("--scene-out", required=True,
                   help="the designed scene (TOML, its [torque] the multisine)")
    p.add_argument("--out", required=True, help="the design report (JSON)")
    p.add_argument("--plot", help="the torque and the before/after intervals (PNG)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _design_outputs(a: argparse.Namespace) -> None:
    """--out, --scene-out and --plot: each a writable file, not the scene, none another."""
    from ..runtime.io import check_distinct_outputs, check_figure_format, check_output

    outs = [(a.out, "--out"), (a.scene_out, "--scene-out")] + (
        [(a.plot, "--plot")] if a.plot else [])
    for path, option in outs:
        check_output(path, [a.scene], option)
    check_distinct_outputs(outs)
    if a.plot:
        check_figure_format(a.plot, "--plot")


def _design_run(a: argparse.Namespace) -> int:
    from ..bayes.design import design
    from ..runtime.io import atomic_write
    from ..scene import load_scene, save_scene

    free = free_list(a.free)
    if not a.torque_amplitude > 0:
        raise UserError(f"--torque-amplitude must be > 0 N*m, got {a.torque_amplitude:g}")
    for opt, v, unit in (("--force-amplitude", a.force_amplitude, "N"),
                         ("--release-speed", a.release_speed, "rad/s")):
        if v is not None and not v > 0:
            raise UserError(f"{opt} must be > 0 {unit}, got {v:g}")
    if a.criterion == "c" and a.target is None:
        raise UserError("--criterion c needs --target NAME (a free parameter)")
    if a.target is not None and a.target not in free:
        raise UserError(f"--target {a.target} is not free; choose from {', '.join(free)}")
    _design_outputs(a)
    scene = load_scene(a.scene)
    refuse_input_loads(scene, a.scene, "design")
    try:
        d = design(scene, free, a.t1, a.rate, amplitude=a.torque_amplitude, tones=a.tones,
                   criterion=a.criterion, target=a.target, noise_std=a.noise_std,
                   iterations=a.iterations, seed=a.seed, progress=not a.quiet,
                   force_amplitude=a.force_amplitude, release=a.release,
                   release_speed=a.release_speed)
    except ValueError as e:  # name the CLI's option, not the function's argument
        raise UserError(cli_message(str(e))) from None
    print(f"log det Fisher: designed {d.log_det_fisher:.4g}, baseline "
          f"{d.baseline_log_det_fisher:.4g}")
    for n, se in d.predicted_stderr.items():
        ratio = se["baseline"] / se["designed"] if se["designed"] > 0 else float("inf")
        print(f"{n:>8}: predicted stderr {se['designed']:.3g} (baseline {se['baseline']:.3g}, "
              f"{ratio:.3g}x smaller)")
    save_scene(d.scene, a.scene_out)
    with atomic_write(a.out) as f:
        json.dump(d.to_json(), f, indent=1)
        f.write("\n")
    print(f"wrote {a.scene_out} and {a.out}", file=sys.stderr)
    if a.plot:
        from ..bayes.corner import plot_design

        plot_design(d, a.plot)
        print(f"wrote {a.plot}", file=sys.stderr)
    return 0


#: Subcommands added to `crank-jax` (see `cli.main` for the tuple layout).
COMMANDS: list = [
    ("posterior", "sample the Bayesian posterior of free parameters (NUTS), with R-hat, ESS "
                  "and divergences", _posterior_args, _posterior_run),
    ("design", "design a multisine crank torque that makes free parameters identifiable "
               "(max log det Fisher, or min one variance)", _design_args, _design_run),
]
