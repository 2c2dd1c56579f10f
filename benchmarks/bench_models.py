"""Which local model do the images support? Targets rendered from each diffuse × specular model
of the ladder (Lambert / Oren–Nayar × Phong / Blinn–Phong / Cook–Torrance Beckmann / GGX /
Ward) on the randomised scenes of ``bench_fit_suite.py`` (icosphere, torus or the scanned bunny,
1–3 lights, any shading and fog), 8-bit with Gaussian noise σ = 2/255 before quantisation. The fit
starts from the user's usual guess, Lambert + Blinn–Phong, and ``compare_models`` fits the whole
ladder (``model_variants``) and picks by BIC. Counted: the pick is the truth; the truth is within
ΔBIC 2 of the pick (the images do not tell them apart: said, not an error); the pick is wrong
with the truth more than ΔBIC 2 behind. Also each model's fit time (compile apart): the ladder of
error against cost.

    python benchmarks/bench_models.py [--cases 20] [--size 48] [--seed0 0]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from bench_fit_suite import BUNNY, make_case, with_model  # noqa: E402

import diffshade as ds  # noqa: E402
from fitting import Observations, compare_models, model_variants  # noqa: E402
from fitting._models import DIFFUSE_MODELS, SPECULAR_MODELS, TOLD_APART  # noqa: E402

GUESS = ("lambert", "blinn")  # the start's model: what a user tries first
MODELS = [(d, s) for d in DIFFUSE_MODELS for s in SPECULAR_MODELS]


def model_of(name: str) -> tuple[str, str] | None:
    """The (diffuse, specular) of a ``model_variants`` name (None: not a ladder entry)."""
    if name == "as given":
        return GUESS
    if name in SPECULAR_MODELS:
        return GUESS[0], name
    if " + " in name:
        d, s = name.split(" + ")
        return d, s
    return None


def run(case: int, size: int) -> dict:
    scene, opts, free, name, rng = make_case(case, size, BUNNY)
    truth_model = MODELS[case % len(MODELS)]
    scene, opts, free, name = with_model(scene, opts, free, name, "+".join(truth_model), rng)
    clean = np.asarray(jax.jit(ds.render, static_argnames="opts")(scene, opts))
    target = np.round(np.clip(clean + rng.normal(0, 2 / 255, clean.shape), 0, 1) * 255) / 255
    obs = Observations(target, saturation=1.0, quantum=1 / 255)
    # the start: the user's guess (Lambert + Blinn-Phong, m' = 40), the other parameters the truth's
    start = eqx.tree_at(lambda s: s.material.shininess, scene, jnp.asarray(40.0, scene.material.shininess.dtype))
    guess_opts = opts.with_keys(diffuse_model=GUESS[0], specular=GUESS[1])
    guess_free = [n for n in free if n.split(".")[-1] not in ("roughness", "roughness_y", "diffuse_roughness")]
    guess_free = [*guess_free, "material.shininess"] if "material.shininess" not in guess_free else guess_free
    variants = model_variants(start, guess_opts, guess_free)
    scores = compare_models(start, guess_opts, obs, guess_free, variants=variants, intervals=False)
    by = {model_of(m.name): m for m in scores if model_of(m.name) is not None}
    pick = model_of(scores[0].name)
    t = by[truth_model]
    lobe = [
        n for n in t.fit.names if n.split(".")[-1] in ("shininess", "roughness", "roughness_y", "diffuse_roughness")
    ]
    determined = not any(n in t.fit.diagnostics.undetermined for n in lobe)
    gap = t.bic - scores[0].bic
    return {
        "case": case,
        "scene": name,
        "truth": "+".join(truth_model),
        "pick": "+".join(pick) if pick else scores[0].name,
        "right": pick == truth_model,
        "told_apart": pick == truth_model or gap >= TOLD_APART,
        "truth_delta_bic": float(gap),
        "close": [
            "+".join(model_of(m.name)) for m in scores if model_of(m.name) and m.bic - scores[0].bic < TOLD_APART
        ],
        "determined": determined,
        "truth_successful": bool(t.fit.successful),
        "seconds": {"+".join(k): v.seconds for k, v in by.items()},
    }


def summary(rows) -> None:
    """The counts: the truth picked, not told apart (said), wrong; cases whose images show no
    specular term at all (the pick "no specular": the truth's highlight not in them) or whose
    lobe the truth's own fit leaves undetermined are apart."""
    unseen = [r for r in rows if r["pick"] == "no specular"]
    det = [r for r in rows if r["determined"] and r not in unseen]
    print(
        f"picked the truth in {sum(r['right'] for r in det)}/{len(det)} cases whose lobe is determined; "
        f"not told apart (the truth within ΔBIC {TOLD_APART:g}) in {sum(not r['told_apart'] for r in det)}; "
        f"wrong in {sum(r['told_apart'] and not r['right'] for r in det)}; the images show no specular term in "
        f"{len(unseen)}; the lobe undetermined in {len(rows) - len(det) - len(unseen)}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=20)
    ap.add_argument("--size", type=int, default=48)
    ap.add_argument("--seed0", type=int, default=0)
    ap.add_argument("--json", default=None)
    ap.add_argument("--summary", nargs="*", help="only the summary of these --json files")
    a = ap.parse_args()
    if a.summary:
        return summary([r for f in a.summary for r in json.loads(Path(f).read_text())])
    rows = []
    for case in range(a.seed0, a.seed0 + a.cases):
        r = run(case, a.size)
        rows.append(r)
        print(
            f"{case:3d} {r['scene']:52s} truth {r['truth']:20s} pick {r['pick']:20s} "
            f"{'right' if r['right'] else ('not told apart' if not r['told_apart'] else 'WRONG')} "
            f"(truth ΔBIC {r['truth_delta_bic']:.1f}; within 2: {', '.join(r['close'])})"
            f"{'' if r['determined'] else ' [the truth lobe undetermined]'}",
            flush=True,
        )
    summary(rows)
    for m in MODELS:
        s = [r["seconds"]["+".join(m)] for r in rows if "+".join(m) in r["seconds"]]
        if s:
            print(f"  {'+'.join(m):22s} fit median {statistics.median(s):.3f} s (compile apart)")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
