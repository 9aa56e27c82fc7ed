"""The plan of a sweep: its arguments checked once, before any compute; the static
structure; the batched loads; and the batch of any block of samples, built on demand.

A block of samples is drawn ([`draw`][] with `start`/`stop`), checked against the one set
of validation rules (`model.params.validation_rules`, plus finiteness and `freq_hz >= 0`
for the initial state and load parameters), and sorted by stiffness, all in memory bounded
by the block size, whatever the number of samples. Only the result (the samples, the
outputs and the status of every sample) grows with `n`, and [`make_plan`][] refuses a
sweep whose result would not fit in memory.
"""

from __future__ import annotations

import os
import types
from collections.abc import Mapping, Sequence

import equinox as eqx
import jax
import numpy as np

from ..model.dynamics import Structure
from ..model.loads import (
    LOAD_PARAMS,
    ROLES,
    SIDES,
    AbstractLoad,
    get_param,
    load_kind,
    param_name,
    promote,
    set_param,
    toml_key,
)
from ..model.params import FIELDS, SliderCrank, validation_rules
from ..simulation import linearize
from ..solve.policy import check_solver, fastest_mode
from .distributions import MAX_SEED, AbstractDistribution, Spec, draw, parse_spec, whole
from .reductions import REDUCTIONS, TRAJECTORY_OUTPUTS

__all__ = ["VARIABLES", "STATE_NAMES", "SORT_BLOCK", "Plan", "make_plan", "result_bytes",
           "chunk_bytes", "host_memory"]

STATE_NAMES = ("phi0", "dphi0")
#: Names a sweep can vary: the mechanism's fields, the initial state and the loads'
#: parameters from the load table (`model.loads.LOAD_PARAMS`: mean, amplitude, frequency
#: in Hz and phase in rad of the slider force `P` and the crank torque `tau`).
VARIABLES: tuple[str, ...] = FIELDS + STATE_NAMES + tuple(LOAD_PARAMS)
#: Samples drawn, validated and sorted by stiffness together. Sorting within blocks of
#: this size (not over all samples) keeps the memory bounded; a chunk of a sorted block
#: is as uniform in stiffness as a chunk of a globally sorted sweep unless chunks are
#: nearly as large as a block.
SORT_BLOCK = 65536


def host_memory() -> int:
    """Physical memory of this host, bytes (0 if unknown)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 0


def result_bytes(n: int, n_varied: int, reductions: Sequence[str], n_t: int) -> int:
    """Bytes a [`SweepResult`][] of `n` samples holds: the varied values, the outputs
    (8 bytes each, `n_t` per sample for trajectories), status, steps and solver."""
    per = 8 * n_varied + 1 + 8 + 1
    per += sum(8 * n_t if r in TRAJECTORY_OUTPUTS else 8 for r in reductions)
    return int(n) * per


def chunk_bytes(chunk: int, reductions: Sequence[str], n_t: int) -> int:
    """Working memory of one chunk of `chunk` samples, bytes, about: every sample's saved
    trajectory (phi, dphi and the solver's copies of them, 8 bytes each per save time),
    plus phi'' and the eight reaction outputs per save time when `peak_O` is asked for.
    It grows with the number of save times, not with `n`."""
    per_save = 4 + (9 if "peak_O" in reductions else 0)
    return int(chunk) * int(n_t) * 8 * per_save


class Plan(eqx.Module):
    """A checked sweep. `loads[side]` is `None` for a load that is not varied (it is
    shared by the batch), else `(base, roles)`: the scene's load promoted to a kind with
    the varied roles, and the roles to fill in per sample."""

    scene: object
    spec: Spec
    seed: int
    random: bool
    reductions: tuple
    ts: np.ndarray
    rtol: float
    atol: float
    solver: str
    structure: Structure
    loads: dict
    sort: bool

    @property
    def n(self) -> int:
        return self.spec.n

    def nominal(self, m: int) -> dict[str, np.ndarray]:
        """The scene's values of every batched number, (m,) each."""
        sc = self.scene
        cols = {f: np.full(m, float(np.asarray(getattr(sc.mech, f)))) for f in FIELDS}
        cols.update(phi0=np.full(m, float(np.asarray(sc.phi0))),
                    dphi0=np.full(m, float(np.asarray(sc.dphi0))))
        for name, (side, role) in LOAD_PARAMS.items():
            if name in self.spec.names:
                v = get_param(getattr(sc, side), role)
                cols[name] = np.full(m, 0.0 if v is None else float(np.asarray(v)))
        return cols

    def block(self, start: int, stop: int):
        """Samples `[start, stop)`: `(values, cols, invalid, order)`: the drawn values,
        every batched number with invalid samples set back to the scene's, the (m,)
        invalid mask, and the valid indices (into the block), sorted by stiffness."""
        values = draw(self.spec, seed=self.seed, start=start, stop=stop)
        m = stop - start
        cols = self.nominal(m)
        cols.update(values)
        bad = np.zeros(m, bool)
        with np.errstate(invalid="ignore"):
            for _, mask, _ in validation_rules({f: cols[f] for f in FIELDS}):
                bad |= mask
            for name in self.spec.names:
                bad |= ~np.isfinite(cols[name])
                if LOAD_PARAMS.get(name, ("", ""))[1] == "freq_hz":
                    bad |= cols[name] < 0
        # Invalid samples run on the scene's values and are reported as invalid: validated
        # inside jit, one of them would raise for the whole chunk.
        nominal = self.nominal(m)
        cols = {k: np.where(bad, nominal[k], v) for k, v in cols.items()}
        order = np.flatnonzero(~bad)
        if self.sort and order.size:
            mech, load, _, _, _ = self.batch({k: v[order] for k, v in cols.items()})
            rate, _ = fastest_mode(linearize(mech, load))
            order = order[np.argsort(np.asarray(rate), kind="stable")]
        return values, cols, bad, order

    def batch(self, cols: Mapping[str, np.ndarray]):
        """`(mech, load, torque, phi0, dphi0)` for columns of m samples; a load that is not
        varied is the scene's (unbatched)."""
        mech = SliderCrank(**{f: cols[f] for f in FIELDS})
        m = cols["phi0"].shape[0]
        loads = []
        for side in SIDES:
            if self.loads[side] is None:
                loads.append(getattr(self.scene, side))
                continue
            base, roles = self.loads[side]
            ld = jax.tree.map(lambda x: np.broadcast_to(np.asarray(x), (m,) + np.shape(x)),
                              base)
            for role in roles:
                ld = set_param(ld, role, cols[param_name(side, role)], side)
            loads.append(ld)
        return mech, loads[0], loads[1], cols["phi0"], cols["dphi0"]


def _may_be_nonzero(v) -> bool:
    if isinstance(v, AbstractDistribution):
        return v.may_be_nonzero()
    return bool(np.any(np.asarray(v) != 0))


def _structure(scene, spec: Spec) -> Structure:
    """The union of the scene's terms and every term a varied field may switch on."""
    vals = {f: np.asarray(getattr(scene.mech, f)) for f in FIELDS}
    for name in spec.names:
        if name in FIELDS:
            v = spec.dists.get(name, spec.arrays.get(name))
            vals[name] = np.asarray(float(_may_be_nonzero(v)))
    return Structure.of(scene.mech).union(Structure.of(types.SimpleNamespace(**vals)))


def _reachable_roles(nominal: AbstractLoad, side: str) -> set[str]:
    """The roles `nominal` has, or gains by promotion (none -> constant -> harmonic)."""
    roles = set(load_kind(nominal).fields)
    try:
        roles |= set(load_kind(promote(nominal, _TONE, side)).fields)
    except ValueError:  # a kind that is not promoted (a multi-sine, a sampled load...)
        pass
    return roles


_TONE = ("mean", "amp", "freq_hz", "phase")  # a harmonic load's roles


def _load_plan(scene, spec: Spec, side: str) -> tuple[AbstractLoad, tuple] | None:
    varied = {LOAD_PARAMS[n][1]: n for n in spec.names
              if n in LOAD_PARAMS and LOAD_PARAMS[n][0] == side}
    if not varied:
        return None
    nominal = getattr(scene, side)
    # Every varied parameter must be one the load has or can be promoted to: a value
    # dropped here would give the nominal scene's outputs with exit 0 (issue 37 item 4).
    reachable = _reachable_roles(nominal, side)
    for role, name in varied.items():
        if role not in reachable:
            kind = load_kind(nominal)
            has = [param_name(side, r) for r in ROLES if r in kind.fields] or "none"
            more = [param_name(side, r) for r in ROLES if r in reachable - set(kind.fields)]
            raise ValueError(f"cannot vary {name!r}: the scene's {side} is a "
                             f"{type(nominal).__name__} ({kind.name}), which has no {name}; "
                             f"its parameters are {has}"
                             + (f" (a sweep can also vary {more})" if more else ""))
    need = {r for r, n in varied.items()
            if _may_be_nonzero(spec.dists.get(n, spec.arrays.get(n)))}
    has = set(load_kind(nominal).fields)
    if "amp" not in need | has:
        need -= {"freq_hz", "phase"}  # a tone of zero amplitude needs no terms
    base = promote(nominal, need, side)
    return base, tuple(r for r in varied if r in load_kind(base).fields)


# A varied parameter that only multiplies terms this scene holds at zero cannot change any
# output: every sample would give the nominal result, with exit 0. Mechanism field -> the
# fields that, all held at zero, leave it without effect, and why.
_INERT_FIELDS: dict[str, tuple[tuple[str, ...], str]] = {
    "w_c": (("T_c",), "w_c is the smoothing width of the crank's Coulomb friction T_c"),
    "w_s": (("F_s",), "w_s is the smoothing width of the slider's Coulomb friction F_s"),
    "gravity_angle": (("g",), "gravity_angle turns gravity, of strength g"),
    "s": (("m_c",), "s places the crank's mass m_c"),
    "b": (("m_p",), "b places the coupler's mass m_p"),
}
# A load's tone `X1 sin(2 pi freq_hz t + phase)`: role -> the roles that, all held at zero,
# make the tone zero whatever this role's value.
_INERT_ROLES = {"amp": ("freq_hz", "phase"), "freq_hz": ("amp",), "phase": ("amp",)}


def _held_zero(scene, spec: Spec, name: str) -> bool:
    """Whether `name` is zero in every sample: varied only by zeros, or not varied and
    zero (or absent) in the scene."""
    if name in spec.names:
        return not _may_be_nonzero(spec.dists.get(name, spec.arrays.get(name)))
    if name in FIELDS:
        value = getattr(scene.mech, name)
    else:
        side, role = LOAD_PARAMS[name]
        value = get_param(getattr(scene, side), role)
    return value is None or not np.any(np.asarray(value) != 0)


def _check_effect(scene, spec: Spec) -> None:
    """`ValueError` for a varied parameter that has no effect on this scene's result."""
    for name in spec.names:
        if name in _INERT_FIELDS:
            needs, why = _INERT_FIELDS[name]
            fix = f"set {' or '.join(needs)} in the scene's mechanism"
        elif name in LOAD_PARAMS and LOAD_PARAMS[name][1] in _INERT_ROLES:
            side, role = LOAD_PARAMS[name]
            needs = tuple(param_name(side, r) for r in _INERT_ROLES[role])
            a, f, ph = (param_name(side, r) for r in ("amp", "freq_hz", "phase"))
            why = f"the {side}'s tone is {a} sin(2 pi {f} t + {ph})"
            key = toml_key(side, _INERT_ROLES[role][0])
            fix = f"give the scene's {side} a nonzero {key}"
        else:
            continue
        if all(_held_zero(scene, spec, x) for x in needs):
            held = " and ".join(needs)
            raise ValueError(f"cannot vary {name!r}: it has no effect on this scene, where "
                             f"{held} {'is' if len(needs) == 1 else 'are'} 0 ({why}), so "
                             "every sample would give the same result; vary "
                             f"{' or '.join(needs)} too, or {fix}")


def make_plan(scene, samples, outputs, *, n=None, seed=0, t1=None, num_saves=None,
              solver=None, chunk_size=1, sort=True, max_memory=None) -> Plan:
    """Check a sweep's arguments (see [`sweep`][]) and plan it; `ValueError` naming the
    argument on any mistake, and for a result larger than `max_memory` bytes (default:
    half of this host's memory)."""
    reductions = tuple(dict.fromkeys(outputs))
    for name in reductions:
        if name not in REDUCTIONS:
            raise ValueError(f"unknown sweep output {name!r}; choose from {list(REDUCTIONS)}")
    for name in samples:
        if name not in VARIABLES:
            raise ValueError(f"cannot vary {name!r}; choose from {list(VARIABLES)}")
    chunk_size = whole(chunk_size, "chunk_size", 1)
    seed = whole(seed, "seed", 0, MAX_SEED)
    n = None if n is None else whole(n, "n", 1)
    solver = check_solver(scene.solver if solver is None else solver)
    spec = parse_spec(samples, n if samples else (n or 1))
    t_end = scene.t1 if t1 is None else float(t1)
    n_t = int(scene.samples) if num_saves is None else whole(num_saves, "num_saves", 2)
    if not (np.isfinite(t_end) and t_end > 0 and n_t >= 2):
        raise ValueError(f"a sweep needs a finite t1 > 0 s and at least 2 save times, got "
                         f"t1 = {t_end:g} and {n_t} save times")
    # Both bounds are checked before the save times themselves are made (10^9 of them
    # would already take 8 GB).
    limit = host_memory() // 2 if max_memory is None else whole(max_memory, "max_memory", 1)
    why = "half this host's memory" if max_memory is None else "max_memory"
    need = result_bytes(spec.n, len(spec.names), reductions, n_t)
    if limit and need > limit:
        per = need // spec.n
        raise ValueError(f"n = {spec.n} samples need {need / 2**30:.1f} GiB for the result "
                         f"({per} bytes per sample) but the limit is {limit / 2**30:.1f} GiB "
                         f"({why}); give `n=` <= {limit // per}, or run "
                         "several sweeps with different seeds")
    chunk = min(chunk_size, spec.n)
    work = chunk_bytes(chunk, reductions, n_t)
    if limit and work > limit:
        per = work // n_t
        raise ValueError(f"{n_t} save times need {work / 2**30:.1f} GiB of working memory "
                         f"for a chunk of {chunk} samples but the limit is "
                         f"{limit / 2**30:.1f} GiB ({why}); give `num_saves=` "
                         f"<= {max(limit // per, 2)}, or a smaller `chunk_size=`")
    ts = np.linspace(0.0, t_end, n_t)
    loads = {side: _load_plan(scene, spec, side) for side in SIDES}
    _check_effect(scene, spec)
    # A result's seed is -1 when nothing was drawn at random (arrays and constants only).
    random = any(isinstance(v, (AbstractDistribution, str)) for v in samples.values())
    return Plan(scene, spec, int(seed), random, reductions, ts, float(np.asarray(scene.rtol)),
                float(np.asarray(scene.atol)), solver, _structure(scene, spec), loads,
                bool(sort))
