"""Which margins does a capture need, at which resolution? Synthetic captures written at full
resolution with a camera's imaging at its pixels (each pixel the mean of 4×4 sub-pixels, so the
silhouette's pixels are mixed with the black background; bloom around clipped highlights; read +
photon noise), read at ``downsample_by`` 1, 2 and 4 (sampled: the block's centre pixel, as
``--downsample`` reads them), and fitted with the silhouette's ``margin`` 0-2 (at clip_margin 1)
and ``clip_margin`` 0-3 (at margin 1): is the fit accepted, how far is the material from the
truth (max |z| over k_d, k_s, m; the relative errors: a camera's pixel integrates over the
highlight, the renderer shades its centre), and what does each margin cost in entries?

    python benchmarks/bench_margins.py [--seeds 3] [--size 160] [--views 10]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from photometric_capture import TRUTH, write_capture  # noqa: E402

FREE = ["material.diffuse", "material.specular", "material.shininess"]
SETTINGS = [(0, 1), (1, 1), (2, 1), (1, 0), (1, 2), (1, 3)]  # (margin, clip_margin)


def run(seed: int, size: int, views: int, factors) -> list[dict]:
    from fitting import fit, load_photometric_stereo

    truth = np.r_[TRUTH["diffuse"], [TRUTH["specular"]] * 3, TRUTH["shininess"]]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        write_capture(
            tmp,
            n=views,
            size=size,
            noise=0.004,
            photon=6.4e-5,
            bloom=0.3,
            pixel_area=4,
            seed=seed,
            camera="orthographic",
            normal_map="Normal_gt.mat",  # (the shape exact at the pixels' centres: only the imaging is off)
        )
        for f in factors:
            cap = load_photometric_stereo(tmp, downsample_by=f)
            for margin, clip_margin in SETTINGS:
                t0 = time.perf_counter()
                r = fit(cap.scene, cap.opts, cap.observations(margin=margin, clip_margin=clip_margin), FREE)
                z = (np.asarray(r.values) - truth) / np.asarray(r.stderr)
                rows.append(
                    {
                        "seed": seed,
                        "downsample": f,
                        "size": size // f,
                        "margin": margin,
                        "clip_margin": clip_margin,
                        "accepted": bool(r.successful),
                        "ratio": float(r.residual.noise_ratio),
                        "max_abs_z": float(np.max(np.abs(z))),
                        "rel_error": {
                            n: float(e) for n, e in zip(("k_d", "k_s", "m"), _rel_errors(np.asarray(r.values), truth))
                        },
                        "entries": int(r.residual.n),
                        "seconds": time.perf_counter() - t0,
                    }
                )
                x = rows[-1]
                print(
                    f"seed {seed} /{f} ({x['size']}²) margin {margin} clip_margin {clip_margin}: "
                    f"{'accepted' if x['accepted'] else 'rejected'} {x['ratio']:.3f}x, max |z| {x['max_abs_z']:.2f}, "
                    f"{x['entries']} entries, error k_d {100 * x['rel_error']['k_d']:+.2f} % "
                    f"k_s {100 * x['rel_error']['k_s']:+.2f} % m {100 * x['rel_error']['m']:+.2f} %, {x['seconds']:.1f} s",
                    flush=True,
                )
    return rows


def _rel_errors(values, truth):
    """The relative errors of the mean k_d, the mean k_s and m."""
    return (
        values[:3].mean() / truth[:3].mean() - 1,
        values[3:6].mean() / truth[3:6].mean() - 1,
        values[6] / truth[6] - 1,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--size", type=int, default=160)
    ap.add_argument("--views", type=int, default=10)
    ap.add_argument("--factors", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--json", type=str, default=None)
    a = ap.parse_args()
    rows = [x for seed in range(a.seeds) for x in run(seed, a.size, a.views, a.factors)]
    print("\nper setting, over the seeds: accepted, median ratio, max |z|, median entries")
    for f in a.factors:
        for margin, clip_margin in SETTINGS:
            sel = [
                x for x in rows if x["downsample"] == f and x["margin"] == margin and x["clip_margin"] == clip_margin
            ]
            print(
                f"/{f} margin {margin} clip_margin {clip_margin}: accepted {sum(x['accepted'] for x in sel)}/{len(sel)}, "
                f"ratio {np.median([x['ratio'] for x in sel]):.3f}x, max |z| {max(x['max_abs_z'] for x in sel):.2f}, "
                f"entries {int(np.median([x['entries'] for x in sel]))}, median error k_s "
                f"{100 * np.median([x['rel_error']['k_s'] for x in sel]):+.2f} % m "
                f"{100 * np.median([x['rel_error']['m'] for x in sel]):+.2f} %"
            )
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
