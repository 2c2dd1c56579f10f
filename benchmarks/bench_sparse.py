"""The sparse factorisations of a map fit's blocks (fitting._sparse.Factor): the supernodal
Cholesky factorisation (fitting._cholesky) against SuperLU in its symmetric mode, both in METIS's
nested-dissection ordering, on the normal matrix of a texture channel: a 2-D grid of n² texels, each
pixel's bilinear footprint coupling a texel with its eight neighbours, random weights (seeds of its
own), a ridge of 1e-13 on the unit diagonal as the fit's. Reports medians of fresh factorisations
and of solves with 1 and 32 columns (the Newton steps' and the standard errors' probes), their
ratios, and the relative residual of each solve.

    python benchmarks/bench_sparse.py --n 235 --repeats 7     # 55,225 scalars: a 256² channel's size
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from fitting import _cholesky, _sparse  # noqa: E402


def channel(n: int, rng) -> sp.csc_matrix:
    """``AᵀA`` of random bilinear footprints on an n × n grid (pixels at random sub-texel offsets,
    weights from a random lighting), scaled to a unit diagonal, plus the fit's ridge."""
    pixels = 4 * n * n
    ij = rng.integers(0, n - 1, (pixels, 2))
    f = rng.random((pixels, 2))
    light = rng.uniform(0.05, 1.0, pixels)
    rows = np.repeat(np.arange(pixels), 4)
    cols, vals = [], []
    for di, dj, w in [
        (0, 0, (1 - f[:, 0]) * (1 - f[:, 1])),
        (1, 0, f[:, 0] * (1 - f[:, 1])),
        (0, 1, (1 - f[:, 0]) * f[:, 1]),
        (1, 1, f[:, 0] * f[:, 1]),
    ]:
        cols.append((ij[:, 0] + di) * n + ij[:, 1] + dj)
        vals.append(w * light)
    A = sp.csr_matrix((np.stack(vals, 1).ravel(), (rows, np.stack(cols, 1).ravel())), shape=(pixels, n * n))
    G = (A.T @ A).tocsc()
    d = 1 / np.sqrt(np.maximum(G.diagonal(), 1e-300))
    return (sp.diags(d) @ G @ sp.diags(d) + 1e-13 * sp.identity(n * n)).tocsc()


def median_time(fn, repeats: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times)), out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, nargs="+", default=[235], help="grid sides (n² scalars per channel)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    if not _cholesky.available():
        sys.exit("the Cholesky library does not build here")
    from scipy.sparse.linalg import splu

    print(
        "n² scalars, seed | factorise: SuperLU, Cholesky, ratio | 1 column | 32 columns | residual (Cholesky, SuperLU)"
    )
    for n in args.n:
        for seed in args.seeds:
            rng = np.random.default_rng(seed)
            M = channel(n, rng)
            order = _sparse.nested_dissection(_sparse._graph(M))
            Mo = M[order][:, order].tocsc()
            t_lu, lu = median_time(
                lambda: splu(Mo, permc_spec="NATURAL", diag_pivot_thresh=0.0, options=dict(SymmetricMode=True)),
                args.repeats,
            )
            t_ch, ch = median_time(lambda: _cholesky.Cholesky(M, order), args.repeats)
            row = [f"{n * n:7d}, {seed} | {t_lu * 1e3:6.1f} {t_ch * 1e3:6.1f} ms {t_lu / t_ch:4.1f}x"]
            res = []
            for k in (1, 32):
                b = rng.normal(size=(n * n, k))[:, 0] if k == 1 else rng.normal(size=(n * n, k))

                def superlu(b=b):
                    x = np.empty_like(b)
                    x[order] = lu.solve(np.asfortranarray(b[order]))
                    return x

                s_lu, x_lu = median_time(superlu, args.repeats * (3 if k == 1 else 1))
                s_ch, x_ch = median_time(lambda b=b: ch.solve(b), args.repeats * (3 if k == 1 else 1))
                row.append(f"{s_lu * 1e3:6.1f} {s_ch * 1e3:6.1f} ms {s_lu / s_ch:4.1f}x")
                scale = np.abs(b).max()
                res.append(f"{np.abs(M @ x_ch - b).max() / scale:.1e} {np.abs(M @ x_lu - b).max() / scale:.1e}")
            print(" | ".join(row + [", ".join(res)]))
            print(
                f"    factor entries: SuperLU L+U {lu.L.nnz + lu.U.nnz:,}, Cholesky {ch.stored:,} in {ch.supernodes:,} supernodes"
            )


if __name__ == "__main__":
    main()
