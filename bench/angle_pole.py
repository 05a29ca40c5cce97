#!/usr/bin/env python3
"""Why a d = 8 angle policy gets stuck with one coordinate of a pair unsolved: the
lever of the pair's step entry on that coordinate at the poles of its angle entry.

One pair of the angle env (docs/ALGORITHM.md §2): step s = 0.1*a0, angle
phi = (a1 + 1)*pi/2, dx = s*sin(phi), dy = s*cos(phi), each action entry drawn from
N(mu, sigma) and clipped to [-1, 1]. The per-coordinate reward is r_x = |x| - |x + dx|
(goal 0). At the poles of phi (a1 = -1 or +1: phi = 0 or pi) the pair moves along y
only, and x's lever on the step, d E[r_x]/d mu0, is proportional to sigma: it comes from
the angle's exploration alone. This prints, by Monte Carlo with common draws and central
differences, every entry of the expected per-coordinate reward's gradient for a grid
of (mu1, sigma) at the situations a trained pair meets, so that one sees

  * that with y still to bring in (y = -0.5) and s of the sign y wants (mu0 = +0.5),
    both coordinates' gradients on mu1 push the angle further into the pole (r_x: the
    pole stops x moving the wrong way; r_y: it puts all of s into y): the pole is a
    stable point while y is unsolved, and the tanh head then saturates;
  * that once y is in (y = 0, mu0 = 0), x's lever on mu0 at the pole is ~0.06*sigma
    (0.003 at sigma = 0.05) against 0.1 at phi = pi/2: the way out is ~30x weaker than
    the normal signal at the sigma the trained policies reach (log sigma -2.2 to -2.8,
    results/README.md), so the vector advantage of x is mostly noise there.

    bench/angle_pole.py [--draws 2000000] [--seed 0]

The first line checks the estimator against a hand calculation: at mu1 = 0 (phi = pi/2)
and small sigma, dx = 0.1*a0, so d E[r_x]/d mu0 = -0.1 for x > 0.
"""
import argparse

import numpy as np


def rewards(mu0, mu1, sigma, x, y, e0, e1):
    """E[r_x], E[r_y] of one pair at (x, y) under N(mu, sigma) clipped to [-1, 1]."""
    a0 = np.clip(mu0 + sigma * e0, -1.0, 1.0)
    a1 = np.clip(mu1 + sigma * e1, -1.0, 1.0)
    phi = (a1 + 1.0) * np.pi / 2.0
    dx, dy = 0.1 * a0 * np.sin(phi), 0.1 * a0 * np.cos(phi)
    return (abs(x) - abs(x + dx)).mean(), (abs(y) - abs(y + dy)).mean()


def gradient(mu0, mu1, sigma, x, y, e0, e1, h=1e-3):
    """[[dr_x/dmu0, dr_x/dmu1], [dr_y/dmu0, dr_y/dmu1]] by central differences."""
    g = np.zeros((2, 2))
    for i, (d0, d1) in enumerate([(h, 0.0), (0.0, h)]):
        p = rewards(mu0 + d0, mu1 + d1, sigma, x, y, e0, e1)
        m = rewards(mu0 - d0, mu1 - d1, sigma, x, y, e0, e1)
        g[0, i], g[1, i] = (p[0] - m[0]) / (2 * h), (p[1] - m[1]) / (2 * h)
    return g


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--draws", type=int, default=2_000_000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    e0, e1 = rng.standard_normal(args.draws), rng.standard_normal(args.draws)

    check = gradient(0.0, 0.0, 0.01, 0.5, 0.0, e0, e1)[0, 0]
    print(f"check: d E[r_x]/d mu0 at phi = pi/2, sigma 0.01: {check:+.4f} (hand: -0.1000)")
    assert abs(check + 0.1) < 2e-3, check

    cases = [
        ("y unsolved, s of y's sign", 0.5, -0.5, 0.5),
        ("y solved, s at 0", 0.5, 0.0, 0.0),
    ]
    for title, x, y, mu0 in cases:
        print(f"\n{title}: x = {x}, y = {y}, mu0 = {mu0:+.1f}")
        print("   mu1  sigma |  E r_x    E r_y  | drx/dmu0 drx/dmu1 | dry/dmu0 dry/dmu1")
        for mu1 in [-1.0, -0.9, -0.5, 0.0]:
            for sigma in [0.05, 0.1, 0.2, 0.4]:
                rx, ry = rewards(mu0, mu1, sigma, x, y, e0, e1)
                g = gradient(mu0, mu1, sigma, x, y, e0, e1)
                print(
                    f"  {mu1:+.1f}  {sigma:.2f}  | {rx:+.5f} {ry:+.5f} |"
                    f" {g[0, 0]:+.4f}  {g[0, 1]:+.4f}  | {g[1, 0]:+.4f}  {g[1, 1]:+.4f}"
                )


if __name__ == "__main__":
    main()
