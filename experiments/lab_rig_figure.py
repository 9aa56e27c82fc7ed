"""Figure of a lab-rig run for the README: angle, rate, energy and crank-bearing load.

Run: `python experiments/lab_rig_figure.py [--out docs/figures/lab_rig.png]`.
"""

from __future__ import annotations

import argparse

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import crank_jax as cj  # noqa: E402
from crank_jax.report.plotting import pyplot, save_figure  # noqa: E402


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="docs/figures/lab_rig.png")
    args = ap.parse_args(argv)

    scene = cj.load_scene("lab-rig")
    tr = scene.simulate(scene.ts(5.0, 1001), outputs=("energy", "reactions"))
    lin = cj.linearize(scene.mech)
    t = np.asarray(tr.ts)
    # The linear model from the same release, to show where the nonlinearity matters.
    mu, chi, xi = (float(x) for x in (lin.mu, lin.chi, lin.xi))
    a, wd = chi / (2 * mu), np.sqrt(xi / mu - (chi / (2 * mu)) ** 2)
    phi_lin = float(scene.phi0) * np.exp(-a * t) * (np.cos(wd * t) + a / wd * np.sin(wd * t))

    plt = pyplot()
    fig, axes = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
    axes[0].plot(t, tr.phi, lw=1.0, label="nonlinear (crank-jax)")
    axes[0].plot(t, phi_lin, lw=0.8, ls="--", label="linearised, eq. 33 corrected")
    axes[0].set_ylabel("phi [rad]")
    axes[0].legend(fontsize=8, loc="upper right")
    axes[1].plot(t, tr.extras["energy"], lw=1.0, color="C2")
    axes[1].set_ylabel("T + V [J]")
    O = np.hypot(tr.extras["O_x"], tr.extras["O_y"])  # noqa: E741
    axes[2].plot(t, O, lw=1.0, color="C3")
    axes[2].set_ylabel("|F_O| bearing [N]")
    axes[2].set_xlabel("t [s]")
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[0].set_title(f"lab-rig: phi0 = {float(scene.phi0)} rad, "
                      f"f_n = {float(lin.omega_n) / (2 * np.pi):.2f} Hz, "
                      f"zeta = {float(lin.zeta):.3f}", fontsize=10)
    save_figure(fig, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
