"""Which imaging terms does a capture need? A randomised suite of synthetic captures, each with a
random subset of the imaging effects (near LEDs at 15-30 object radii, per-light calibration
errors of ±2 %, a black level), and always level-dependent noise and bloom around clipped
highlights; the shape a normal map (a sphere or the scanned bunny, orthographic, no K.txt, as
DiLiGenT ships objects). Every subset of the terms is fitted (fitting.imaging_variants) and the
lowest BIC picks one: how often is it the truth's, does the picked fit recover the material
(within 3 s.e.), is the verdict right, and is each present term, left out, rejected and named
in the notes?

    python benchmarks/bench_imaging.py --cases 20 [--size 48] [--views 12]
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

EFFECTS = ("near lights", "gains", "black level")
HOLDOUT = 3  # the picked model's held-out check: every 3rd view held out
FREE = ["material.diffuse", "material.specular", "material.shininess"]


def bunny():
    import diffshade as ds

    b = ds.load_mesh(Path(__file__).resolve().parents[1] / "tests" / "data" / "meshes" / "bunny.ply")
    v = np.asarray(b.vertices, np.float64)
    c = (v.min(0) + v.max(0)) / 2
    R = np.diag([1.0, -1.0, -1.0])
    return ds.Mesh((v - c) / np.linalg.norm(v - c, axis=1).max() @ R.T + [0.0, 0.0, 4.0], np.asarray(b.faces))


def case(seed: int, folder: Path, size: int, views: int, noise: float, depth: bool = False):
    """One random capture: ``(effects present, its write_capture keywords)``."""
    rng = np.random.default_rng(1000 + seed)
    present = [e for e in EFFECTS if rng.uniform() < 0.5]
    kw = dict(
        n=views,
        size=size,
        noise=noise,
        photon=noise**2 * 4,  # read + photon noise: the variance 5x the read noise at level 1
        bloom=0.3,
        mixed=4,  # the silhouette's pixels mixed with the background (coverage of 4x4 sub-pixels)
        seed=seed,
        camera="orthographic",
        normal_map="Normal_gt.mat",
        mesh=bunny() if seed % 2 else None,
        depth_map="depth.npy" if depth else None,
    )
    if "near lights" in present:
        kw["light_distance"] = float(rng.uniform(15, 30))
    if "gains" in present:
        kw["gain_error"] = 0.02
    if "black level" in present:
        kw["black_level"] = float(rng.uniform(0.01, 0.02))
    write_capture(folder, **kw)
    return present, kw


def run(seed: int, size: int, views: int, noise: float, depth: bool = False) -> dict:
    from fitting import compare_models, holdout_fit, imaging_variants, load_photometric_stereo, mean_gauge

    with tempfile.TemporaryDirectory() as tmp:
        present, kw = case(seed, Path(tmp), size, views, noise, depth)
        cap = load_photometric_stereo(tmp)
        obs = cap.observations()
        t0 = time.perf_counter()
        scores = compare_models(
            cap.scene, cap.opts, obs, FREE, variants=imaging_variants(cap.scene, cap.opts, obs, FREE, centre=cap.centre)
        )
        seconds = time.perf_counter() - t0
        best = scores[0]
        v = next(x for x in imaging_variants(cap.scene, cap.opts, obs, FREE, centre=cap.centre) if x[0] == best.name)
        _, held = holdout_fit(v[3], v[1], v[4], v[2], HOLDOUT)
        f = Path(tmp) / "true_intensities.txt"  # (each light's calibration error, where the lights have one)
        g = np.loadtxt(f)[:, 0] / np.loadtxt(Path(tmp) / "light_intensities.txt")[:, 0] if f.exists() else np.ones(1)
    picked = [] if best.name == "as given" else best.name[2:].split(" + ")
    r = best.fit
    truth = np.r_[TRUTH["diffuse"], [TRUTH["specular"]] * 3, TRUTH["shininess"]]
    k = [
        r.names.index(n)
        for n in [
            "material.diffuse[r]",
            "material.diffuse[g]",
            "material.diffuse[b]",
            "material.specular[r]",
            "material.specular[g]",
            "material.specular[b]",
            "material.shininess",
        ]
    ]
    # the k's in the fit's gauge: view 0's light at its written intensity (with gains free, the
    # k's carry that light's calibration error g[0]); in the gains' mean gauge (fitting.mean_gauge:
    # their geometric mean 1) they carry the lights' mean error, the geometric mean of g
    vals, se, expect = np.asarray(r.values)[k], np.asarray(r.stderr)[k], truth
    if "gains" in picked:
        expect = truth * np.r_[[g[0]] * 6, 1.0]
        mg = mean_gauge(r)
        at = [mg.names.index(r.names[i]) for i in k[:6]]
        vals = np.r_[mg.values[at], vals[6]]
        se = np.r_[mg.stderr[at], se[6]]
        z = (vals - truth * np.r_[[np.exp(np.mean(np.log(g)))] * 6, 1.0]) / se
    else:
        z = (vals - truth) / se
    rel = float(np.max(np.abs(np.asarray(r.values)[k] / expect - 1)))
    return {
        "seed": seed,
        "object": "bunny" if seed % 2 else "sphere",
        "present": present,
        "picked": picked,
        "right": sorted(picked) == sorted(present),
        "accepted": bool(r.successful),
        "ratio": float(r.residual.noise_ratio),
        "max_abs_z_material": float(np.max(np.abs(z))),  # (with gains, in their mean gauge)
        "max_rel_error_material": rel,  # (in the fit's gauge)
        "delta_bic_next": float(scores[1].bic - scores[0].bic),
        "heldout_ratio": float(held.ratio_all),  # the picked model fitted on 2 views in 3, the others predicted
        "seconds": seconds,
        "rejected_without": {m.name: bool(not m.fit.successful) for m in scores},
        "left_out": left_out(scores, present),
    }


#: The parameter a rejected fit's notes name for each term (fitting._report.misfit_pointers).
NAMED_BY = {
    "near lights": "directional[0].distance",
    "gains": "view[*].camera.exposure",
    "black level": "camera.black_level",
}


def left_out(scores, present) -> dict:
    """For each term present: is the fit with every other present term but that one rejected,
    and do its notes name the term's parameter?"""
    by_name = {m.name: m for m in scores}
    out = {}
    for t in present:
        rest = [e for e in EFFECTS if e in present and e != t]
        m = by_name["+ " + " + ".join(rest) if rest else "as given"]
        out[t] = {"rejected": not m.fit.successful, "named": NAMED_BY[t] in " ".join(m.fit.notes)}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=20)
    ap.add_argument("--first", type=int, default=0, help="the first case's seed")
    ap.add_argument("--size", type=int, default=48)
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--noise", type=float, default=0.004)
    ap.add_argument("--json", type=str, default=None)
    ap.add_argument("--depth", action="store_true", help="the folders carry the truth's depth map (depth.npy)")
    a = ap.parse_args()
    rows = []
    for seed in range(a.first, a.first + a.cases):
        row = run(seed, a.size, a.views, a.noise, a.depth)
        rows.append(row)
        print(
            f"case {seed:2d} {row['object']:6s} present {row['present']!s:40s} picked {row['picked']!s:40s} "
            f"{'right' if row['right'] else 'WRONG'}  {'accepted' if row['accepted'] else 'rejected'} "
            f"({row['ratio']:.3g}x)  held out {row['heldout_ratio']:.3g}x  ΔBIC {row['delta_bic_next']:.1f}  material {row['max_rel_error_material']:.2g} "
            f"rel. off  {row['seconds']:.1f} s",
            flush=True,
        )
    right = sum(r["right"] for r in rows)
    print(
        f"selection right in {right}/{len(rows)}; picked fits accepted in {sum(r['accepted'] for r in rows)}/{len(rows)}"
    )
    ho = [r["heldout_ratio"] for r in rows]
    print(
        f"held-out RMS over the noise: median {np.median(ho):.3f}, max {max(ho):.3f}; <= 1.1 in {sum(h <= 1.1 for h in ho)}/{len(ho)}"
    )
    zs = [r["max_abs_z_material"] for r in rows if r["right"]]
    print(
        f"right picks: material within 1e-4 relative in {sum(r['max_rel_error_material'] <= 1e-4 for r in rows if r['right'])}"
        f"/{right}; within 3 s.e. in {sum(z < 3 for z in zs)}/{len(zs)} (with gains: the k's in their mean gauge, "
        "against the truth times the lights' mean calibration error)"
    )
    for t in EFFECTS:
        lo = [r["left_out"][t] for r in rows if t in r["left_out"]]
        print(
            f"{t} left out: rejected in {sum(x['rejected'] for x in lo)}/{len(lo)}, "
            f"the notes name {NAMED_BY[t]} in {sum(x['named'] for x in lo)}/{len(lo)}"
        )
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
