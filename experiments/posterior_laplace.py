"""The posterior beside the fit's Laplace intervals, where they should agree and where they
should not.

- **well conditioned**: the lab rig, k and c free, 2 s at 100 Hz with 2 mrad noise. The
  posterior is nearly Gaussian: its 95% intervals and the Laplace intervals should agree.
- **near a bound**: the same rig with nearly no damping (c = 1e-5 N*m*s/rad, zeta 1e-4),
  1 s at 100 Hz with 10 mrad noise, c under a proper flat prior `uniform(0, 0.002)` (a flat
  prior in log c would be improper: the likelihood stays finite as c -> 0). The data
  hardly bound c away from 0, so the posterior of c piles up against the bound and is
  skewed, while the Laplace interval is symmetric about the estimate.

Run: `python experiments/posterior_laplace.py [draws]`; writes
`experiments/results/posterior_laplace.json` and `docs/figures/posterior_laplace.png`
(each case: the histograms of k and c with the Laplace 95% interval, and the (k, c) draws
with the Laplace 95% ellipse).
"""

import dataclasses
import json
import os
import sys

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import crank_jax as cj  # noqa: E402
from crank_jax.report.plotting import pyplot, save_figure  # noqa: E402
from crank_jax.runtime.io import atomic_write  # noqa: E402

cj.configure_cpu()

FREE = ("k", "c")
CASES = {
    "well conditioned": dict(c=0.002, t1=2.0, rate=100.0, noise=2e-3, priors=None),
    "near a bound (c -> 0)": dict(c=1e-5, t1=1.0, rate=100.0, noise=1e-2,
                                  priors={"c": "uniform(0, 0.002)"}),
}


def run_case(spec, draws):
    scene = cj.load_scene("lab-rig")
    scene = dataclasses.replace(scene, mech=scene.mech.replace(c=spec["c"]))
    data = cj.synthesize(scene, t1=spec["t1"], rate=spec["rate"], noise_std=spec["noise"],
                         seed=7)
    post = cj.posterior(scene, data, FREE, spec["priors"], draws=draws, chains=4,
                        warmup=300, seed=0, progress=False)
    s = post.summary()
    out = {"truth": {"k": 2.0, "c": spec["c"]}, "record": f"{spec['t1']:g} s at "
           f"{spec['rate']:g} Hz, {spec['noise'] * 1e3:g} mrad noise",
           "priors": post.priors, "divergences": post.divergences,
           "gradient_evaluations": post.gradient_evaluations, "seconds": post.seconds}
    for n in FREE:
        ci = post.fit.ci95[n]
        out[n] = {"posterior": s[n], "laplace": {"value": post.fit.values[n],
                                                 "stderr": post.fit.stderr[n],
                                                 "ci95": list(ci) if ci else None}}
    return post, out


def ellipse95(mean, cov, n=100):
    """(n, 2) points of the 95% ellipse of the 2-d Gaussian N(mean, cov): the unit circle
    scaled by the square roots of cov's eigenvalues and sqrt(chi2_2(0.95)), rotated by
    its eigenvectors."""
    t = np.linspace(0, 2 * np.pi, n)
    w, V = np.linalg.eigh(cov)
    radius = np.sqrt(-2 * np.log(0.05))  # sqrt of chi-square(2)'s 95% quantile
    circle = np.stack([np.cos(t), np.sin(t)], axis=1) * np.sqrt(np.maximum(w, 0)) * radius
    return mean + circle @ V.T


def draw(ax_row, post, title):
    x = {n: np.asarray(post.draws[n]).reshape(-1) for n in FREE}
    se, v = post.fit.stderr, post.fit.values
    for ax, n in zip(ax_row[:2], FREE):
        ax.hist(x[n], bins=50, density=True, color="C0", alpha=0.7, label="posterior")
        lo, hi = np.quantile(x[n], [0.025, 0.975])
        ax.axvline(lo, color="C0", ls="--", lw=1)
        ax.axvline(hi, color="C0", ls="--", lw=1, label="posterior 95%")
        ci = post.fit.ci95[n]  # the fit's: in log c for a positive c, so not symmetric
        ax.axvline(ci[0], color="C3", lw=1)
        ax.axvline(ci[1], color="C3", lw=1, label="Laplace 95%")
        ax.set_xlabel(n)
        ax.set_yticks([])
        ax.locator_params(axis="x", nbins=4)
        ax.tick_params(labelsize=7)
    ax_row[0].set_title(title, fontsize=9, loc="left")
    ax_row[0].legend(fontsize=6)
    ax = ax_row[2]
    ax.plot(x["k"], x["c"], ".", ms=1, alpha=0.3, color="C0")
    corr = np.asarray(post.fit.correlation)
    s = np.array([se["k"], se["c"]])
    cov = np.outer(s, s) * np.array([[1, corr[0, 1]], [corr[1, 0], 1]])
    e = ellipse95(np.array([v["k"], v["c"]]), cov)
    ax.plot(e[:, 0], e[:, 1], color="C3", lw=1)
    ax.set_xlabel("k")
    ax.set_ylabel("c")
    ax.locator_params(axis="x", nbins=4)
    ax.tick_params(labelsize=7)


def main() -> None:
    draws = int(sys.argv[1]) if len(sys.argv) > 1 else 1000
    plt = pyplot()
    plt.rcParams["axes.formatter.offset_threshold"] = 2  # 0.0019998 as 0.002 + offsets
    fig, axes = plt.subplots(len(CASES), 3, figsize=(10, 3.2 * len(CASES)))
    results = {}
    for row, (name, spec) in zip(axes, CASES.items()):
        post, results[name] = run_case(spec, draws)
        draw(row, post, name)
    fig.suptitle(f"posterior (blue, 4 chains x {draws} draws) and the fit's Laplace 95% "
                 "(red)", fontsize=10)
    fig.tight_layout()
    os.makedirs("docs/figures", exist_ok=True)
    save_figure(fig, "docs/figures/posterior_laplace.png")
    os.makedirs("experiments/results", exist_ok=True)
    with atomic_write("experiments/results/posterior_laplace.json") as f:
        json.dump(results, f, indent=1)
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
