"""Distributions for Monte Carlo sweeps, and their one-line text form.

Samples are drawn on the host with NumPy, one independent stream per varied field and
block of [`DRAW_BLOCK`][] samples, seeded by `(seed, field name, block)`: the same seed
gives the same samples on every machine and every host of a distributed run, adding a
second varied field never changes the first field's samples, and any range of samples can
be drawn alone (`draw(..., start=, stop=)`), so a sweep draws chunk by chunk in bounded
memory and its samples do not depend on its chunk size.

Text form (as on the command line): `normal(mu,sd)`, `uniform(lo,hi)`,
`lognormal(median,sigma)`, `loguniform(lo,hi)`, `const(x)`, or a bare number.
"""

from __future__ import annotations

import abc
import math
import re
import zlib
from collections.abc import Mapping

import equinox as eqx
import numpy as np

__all__ = [
    "AbstractDistribution", "Normal", "Uniform", "LogNormal", "LogUniform", "Const",
    "parse_distribution", "draw", "DISTRIBUTIONS", "DRAW_BLOCK", "Spec", "parse_spec",
]

#: The largest seed accepted anywhere (sweeps, fits, synthetic records): a sweep's result
#: stores its seed as int64.
MAX_SEED = 2**63 - 1

#: Samples per seeded stream block (see the module docstring). Part of the seed's meaning:
#: changing it changes every sample drawn.
DRAW_BLOCK = 65536


class AbstractDistribution(eqx.Module):
    """A scalar distribution that draws float64 samples on the host."""

    @abc.abstractmethod
    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """`n` independent samples, shape (n,), float64."""

    @abc.abstractmethod
    def may_be_nonzero(self) -> bool:
        """Whether a sample can be nonzero (a term varied away from 0 must be compiled in)."""


def _finite(name: str, **values: float) -> None:
    for key, v in values.items():
        if not math.isfinite(v):
            raise ValueError(f"{name}: {key} must be finite, got {v}")


class Normal(AbstractDistribution):
    """Gaussian with mean `mu` and standard deviation `sd >= 0`."""

    mu: float
    sd: float

    def __check_init__(self):
        _finite("normal", mu=self.mu, sd=self.sd)
        if self.sd < 0:
            raise ValueError(f"normal(mu, sd) needs sd >= 0, got sd={self.sd}")

    def sample(self, rng, n):
        return rng.normal(self.mu, self.sd, size=n)

    def may_be_nonzero(self):
        return self.sd > 0 or self.mu != 0

    def __str__(self):
        return f"normal({self.mu:g},{self.sd:g})"


class Uniform(AbstractDistribution):
    """Uniform on `[lo, hi)`, `lo <= hi`."""

    lo: float
    hi: float

    def __check_init__(self):
        _finite("uniform", lo=self.lo, hi=self.hi)
        if self.hi < self.lo:
            raise ValueError(f"uniform(lo, hi) needs lo <= hi, got lo={self.lo}, hi={self.hi}")

    def sample(self, rng, n):
        return rng.uniform(self.lo, self.hi, size=n)

    def may_be_nonzero(self):
        return self.lo != 0 or self.hi != 0

    def __str__(self):
        return f"uniform({self.lo:g},{self.hi:g})"


class LogNormal(AbstractDistribution):
    """`exp(N(log(median), sigma))`: always positive; `median > 0`, `sigma >= 0`."""

    median: float
    sigma: float

    def __check_init__(self):
        _finite("lognormal", median=self.median, sigma=self.sigma)
        if self.median <= 0 or self.sigma < 0:
            raise ValueError(f"lognormal(median, sigma) needs median > 0 and sigma >= 0, got "
                             f"median={self.median}, sigma={self.sigma}")

    def sample(self, rng, n):
        return self.median * np.exp(rng.normal(0.0, self.sigma, size=n))

    def may_be_nonzero(self):
        return True

    def __str__(self):
        return f"lognormal({self.median:g},{self.sigma:g})"


class LogUniform(AbstractDistribution):
    """Uniform in `log(x)` on `[lo, hi)`, `0 < lo <= hi`: for parameters spanning decades."""

    lo: float
    hi: float

    def __check_init__(self):
        _finite("loguniform", lo=self.lo, hi=self.hi)
        if not 0 < self.lo <= self.hi:
            raise ValueError(f"loguniform(lo, hi) needs 0 < lo <= hi, got lo={self.lo}, "
                             f"hi={self.hi}")

    def sample(self, rng, n):
        return np.exp(rng.uniform(math.log(self.lo), math.log(self.hi), size=n))

    def may_be_nonzero(self):
        return True

    def __str__(self):
        return f"loguniform({self.lo:g},{self.hi:g})"


class Const(AbstractDistribution):
    """Always `value`."""

    value: float

    def __check_init__(self):
        _finite("const", value=self.value)

    def sample(self, rng, n):
        return np.full(n, float(self.value))

    def may_be_nonzero(self):
        return self.value != 0

    def __str__(self):
        return f"const({self.value:g})"


#: Text name -> (class, number of arguments).
DISTRIBUTIONS: dict[str, tuple[type[AbstractDistribution], int]] = {
    "normal": (Normal, 2), "uniform": (Uniform, 2), "lognormal": (LogNormal, 2),
    "loguniform": (LogUniform, 2), "const": (Const, 1),
}

_CALL = re.compile(r"^\s*([a-z_]+)\s*\((.*)\)\s*$")


def parse_distribution(text: str) -> AbstractDistribution:
    """Parse `normal(2.0,0.1)`, `uniform(lo,hi)`, `lognormal(median,sigma)`,
    `loguniform(lo,hi)`, `const(x)` or a bare number (a constant).

    Raises `ValueError` with the accepted forms on anything else.
    """
    forms = "normal(mu,sd), uniform(lo,hi), lognormal(median,sigma), loguniform(lo,hi), " \
            "const(x) or a number"
    try:
        return Const(float(text))
    except ValueError:
        pass
    m = _CALL.match(text)
    if not m or m.group(1) not in DISTRIBUTIONS:
        raise ValueError(f"cannot read distribution {text!r}; use {forms}")
    cls, nargs = DISTRIBUTIONS[m.group(1)]
    parts = [p.strip() for p in m.group(2).split(",")] if m.group(2).strip() else []
    try:
        args = [float(p) for p in parts]
    except ValueError:
        raise ValueError(f"cannot read distribution {text!r}: arguments must be numbers") from None
    if len(args) != nargs:
        raise ValueError(f"{m.group(1)} takes {nargs} argument(s), got {len(args)} in {text!r}")
    return cls(*args)


def _stream(seed: int, name: str, block: int) -> np.random.Generator:
    # crc32 is stable across processes and Python versions (unlike hash()).
    return np.random.default_rng(
        np.random.SeedSequence([int(seed), zlib.crc32(name.encode()), int(block)]))


def _draw_range(d: AbstractDistribution, seed: int, name: str, start: int, stop: int
                ) -> np.ndarray:
    parts = []
    for block in range(start // DRAW_BLOCK, (stop - 1) // DRAW_BLOCK + 1):
        lo = max(start - block * DRAW_BLOCK, 0)
        hi = min(stop - block * DRAW_BLOCK, DRAW_BLOCK)
        # NumPy fills an array from its stream in order, so the first `hi` samples of a
        # block are the same whether `hi` or DRAW_BLOCK are drawn.
        parts.append(d.sample(_stream(seed, name, block), hi)[lo:])
    return np.asarray(np.concatenate(parts), dtype=np.float64)


class Spec(eqx.Module):
    """A parsed sweep specification: `dists` (name -> distribution, constants included)
    and `arrays` (name -> explicit (n,) values), `n` samples, in the `names` order."""

    dists: dict
    arrays: dict
    n: int
    names: tuple


def whole(value, name: str, low: int, high: int | None = None) -> int:
    """`value` as an `int`; `ValueError` naming `name` unless it is an integer (a Python or
    NumPy integer: not a bool, and not a float, whose fraction would be dropped: `n=2.5` ran
    2 samples) from `low` to `high`."""
    if (isinstance(value, bool) or not isinstance(value, (int, np.integer))
            or value < low or (high is not None and value > high)):
        bounds = f">= {low}" if high is None else f"from {low} to {high}"
        raise ValueError(f"{name} must be an integer {bounds}, got {value!r}")
    return int(value)


def parse_spec(
    spec: Mapping[str, AbstractDistribution | str | float | np.ndarray], n: int | None = None
) -> Spec:
    """Check a specification and count its samples (see [`draw`][] for the arguments)."""
    arrays: dict[str, np.ndarray] = {}
    dists: dict[str, AbstractDistribution] = {}
    for name, v in spec.items():
        if isinstance(v, str):
            v = parse_distribution(v)
        if isinstance(v, AbstractDistribution):
            dists[name] = v
        elif np.ndim(v) == 0:
            dists[name] = Const(float(v))
        else:
            a = np.asarray(v, dtype=np.float64)
            if a.ndim != 1:
                raise ValueError(f"samples of {name!r} must be 1-D, got shape {a.shape}")
            arrays[name] = a
    lengths = {a.shape[0] for a in arrays.values()}
    if len(lengths) > 1:
        raise ValueError(f"explicit sample arrays have different lengths {sorted(lengths)}")
    if n is None:
        if not lengths:
            raise ValueError("give the number of samples n (no explicit arrays to count)")
        n = lengths.pop()
    elif lengths and lengths != {whole(n, "n", 1)}:
        raise ValueError(f"n = {n} but the explicit sample arrays have length {lengths.pop()}")
    return Spec(dists, arrays, whole(n, "n", 1), tuple(spec))


def draw(
    spec: Mapping[str, AbstractDistribution | str | float | np.ndarray] | Spec,
    n: int | None = None,
    seed: int = 0,
    *,
    start: int = 0,
    stop: int | None = None,
) -> dict[str, np.ndarray]:
    """Draw the samples of a sweep, or the range `[start, stop)` of them.

    **Arguments:**

    - `spec`: field name -> a distribution, its text form, a number (constant) or an
      explicit (n,) array of values (or a [`Spec`][] from [`parse_spec`][]).
    - `n`: number of samples; may be omitted when `spec` gives arrays.
    - `seed`: integer seed; field `name` uses the streams `(seed, crc32(name), block)`.
    - `start`, `stop`: the range of sample indices to draw (default: all `n`); the
      values do not depend on the range asked for.

    **Returns:** field name -> (stop - start,) float64 array.
    """
    sp = spec if isinstance(spec, Spec) else parse_spec(spec, n)
    stop = sp.n if stop is None else int(stop)
    if not 0 <= start < stop <= sp.n:
        raise ValueError(f"draw: need 0 <= start < stop <= n = {sp.n}, got [{start}, {stop})")
    out = {name: a[start:stop] for name, a in sp.arrays.items()}
    for name, d in sp.dists.items():
        out[name] = _draw_range(d, seed, name, start, stop)
    return {name: out[name] for name in sp.names}
