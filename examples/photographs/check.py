"""Compare a `diffshade fit` of the photographs data set with the truth it was made from.

    python examples/photographs/check.py out/photos out/photos/fit

prints, per parameter, the true value, the fitted one, its standard error and the error in
standard errors (|z|), and for the per-vertex albedo the error distribution over the vertices the
images determine, and how many they do not.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np


def main(data: Path, fit_dir: Path) -> int:
    truth = json.loads((data / "truth.json").read_text())
    fit = json.loads((fit_dir / "fit.json").read_text())
    P = fit["parameters"]
    rows = [("point[0].a1", truth["a1"]), ("point[0].a2", truth["a2"]), ("material.shininess", truth["shininess"])]
    rows += [(f"material.specular[{c}]", truth["specular"]) for c in "rgb"]
    for view, wb in truth["white_balance"].items():
        rows += [(f"{view}.camera.white_balance[{c}]", v) for c, v in zip("rgb", wb)]
    print(f"result: {fit['result']}")
    print(f"{'parameter':34s} {'true':>9s} {'fitted':>9s} {'s.e.':>9s} {'|z|':>6s}")
    zs = []
    for name, true in rows:
        if name not in P:
            continue
        p = P[name]
        z = abs(p["value"] - true) / p["stderr"] if p["stderr"] > 0 else float("inf")
        zs.append(z)
        print(f"{name:34s} {true:9.4g} {p['value']:9.4g} {p['stderr']:9.3g} {z:6.2f}")
    alb = np.asarray(truth["albedo"])
    n = len(alb)
    val = np.array([[P[f"mesh.colors[{v}][{c}]"]["value"] for c in "rgb"] for v in range(n)])
    se = np.array([[P[f"mesh.colors[{v}][{c}]"]["stderr"] for c in "rgb"] for v in range(n)])
    det = np.isfinite(se)
    err = np.abs(val - alb)[det]
    z = err / se[det]
    print(
        f"albedo: {int(det.all(axis=1).sum())} of {n} vertices determined; |error| median {np.median(err):.4f}, "
        f"90th percentile {np.quantile(err, 0.9):.4f}; within 1 s.e. {np.mean(z < 1):.0%}, within 3 s.e. "
        f"{np.mean(z < 3):.0%}"
    )
    print(f"others: {sum(z < 3 for z in zs)} of {len(zs)} within 3 s.e.")
    return 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1]), Path(sys.argv[2])))
