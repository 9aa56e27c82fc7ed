"""Every fit's numbers to the last bit, to show that a refactor kept them.

Runs the misfit bench's records (`misfit_bench.py`: two rigs, six model misfits and a
zero start) and a few more fits (multistart, single and multiple shooting, optax, a
profile, the regressor start, a refused `load_by='angle'`), and dumps every field of each
`FitResult` but its timing: floats by `repr`, arrays by a hash of their bytes.

    python experiments/fit_bits.py OUT.json               # with this checkout's code
    PYTHONPATH=OTHER/src python experiments/fit_bits.py OTHER.json
    python experiments/fit_bits.py --compare A.json B.json   # what differs, and how much

`--compare` prints each fit whose dump differs (and in which fields), then per fit the
iterations, the verdicts and the largest change of a value, relative and over its
standard error. Nothing here is written to the docs: it is a check, not a benchmark.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import warnings

import numpy as np
from _bench import setup_jax

jax = setup_jax()

import misfit_bench as mb  # noqa: E402

import crank_jax as cj  # noqa: E402

#: The extra fits: name -> (rig, effect, fit options).
EXTRAS = {
    "osc/multistart": ("osc", "guide_friction", dict(multistart=3)),
    "osc/single": ("osc", "guide_friction", dict(shooting="single")),
    "osc/multiple3": ("osc", "guide_friction", dict(shooting="multiple", segments=3)),
    "osc/optax": ("osc", "guide_friction", dict(method="optax")),
    "osc/profile": ("osc", "guide_friction", dict(profile="k")),
    "osc/init_regressor": ("osc", "guide_friction", dict(init="regressor")),
    "rot/load_by_angle": ("rot", "guide_friction", dict(load_by="angle")),
}


def _plain(v):
    """`v` as JSON to the last bit: floats by `repr`, arrays by a hash of their bytes."""
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)) and not hasattr(v, "_asdict"):
        return [_plain(x) for x in v]
    if hasattr(v, "_asdict"):
        return _plain(v._asdict())
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, (str, bool, int)) or v is None:
        return v
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        return repr(v)
    return f"arr{a.shape}" + hashlib.sha1(a.tobytes()).hexdigest()[:16]


def dump(res) -> dict:
    out = {f: _plain(getattr(res, f)) for f in res._fields
           if f not in ("seconds", "data", "mech")}
    out["mech"] = _plain({k: getattr(res.mech, k) for k in ("k", "c", "I_c", "m_c")})
    return out


def fit(rig: str, effect: str, **options):
    cfg = mb.RIG[rig]
    data = mb.record(rig, effect, 0)
    start = dict(cfg["truth"], **cfg["start"])
    if effect == "zero_start":  # as misfit_bench.run_case: its first free parameter at 0
        start[cfg["free"][0]] = 0.0
    scene = mb.scene(rig, start, float(data.ts[-1]))
    return cj.fit(scene, data, free=cfg["free"], progress=False, warn=False, **options)


def run() -> dict:
    cases = {f"{rig}/{e}": (rig, e, {}) for rig in mb.RIGS
             for e in mb.EFFECTS + mb.START_CASES}
    out = {}
    for key, (rig, effect, options) in {**cases, **EXTRAS}.items():
        try:
            out[key] = dump(fit(rig, effect, **options))
        except ValueError as e:  # a refusal is behaviour too: its words are compared
            out[key] = {"error": str(e)}
        print(key, out[key].get("iterations", "refused"), flush=True)
    return out


def compare(a: dict, b: dict) -> int:
    """Print what differs between two dumps; returns the number of fits that differ."""
    differ = 0
    for key in sorted(set(a) | set(b)):
        x, y = a.get(key, {}), b.get(key, {})
        fields = sorted(f for f in set(x) | set(y) if x.get(f) != y.get(f))
        if not fields:
            continue
        differ += 1
        line = f"{key}: {', '.join(fields)}"
        if "values" in x and "values" in y:
            rel = se = 0.0
            for name, v in x["values"].items():
                v1, v2 = float(v), float(y["values"][name])
                rel = max(rel, abs(v1 - v2) / max(abs(v1), 1e-300))
                s = x["stderr"].get(name)
                if s is not None:
                    se = max(se, abs(v1 - v2) / float(s))
            line += (f" | iterations {x['iterations']} -> {y['iterations']}; values by "
                     f"{rel:.1e} relative, {se:.1e} standard errors")
        print(line)
    print(f"{differ} of {len(set(a) | set(b))} fits differ")
    return differ


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?", help="the dump to write")
    ap.add_argument("--compare", nargs=2, metavar=("A", "B"), help="compare two dumps")
    args = ap.parse_args()
    if args.compare:
        a, b = (json.loads(open(p).read()) for p in args.compare)
        raise SystemExit(1 if compare(a, b) else 0)
    if not args.out:
        ap.error("give OUT.json, or --compare A B")
    warnings.simplefilter("ignore")
    with open(args.out, "w") as f:
        json.dump(run(), f, indent=1, sort_keys=True)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
