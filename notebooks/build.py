"""Write the notebooks from the cell sources below and execute them, saving the outputs.

    python notebooks/build.py            # write and execute all seven (full sizes)
    python notebooks/build.py --no-run   # write only

The test suite executes the saved notebooks again with ``DIFFSHADE_NOTEBOOK_SMALL=1`` (small
images, fewer configurations) and fails on any error or failed ``assert`` in a cell.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import nbformat

HERE = Path(__file__).resolve().parent

SETUP = """\
import os, time
import numpy as np
import jax, jax.numpy as jnp
import matplotlib.pyplot as plt
import diffshade as ds

SMALL = os.environ.get("DIFFSHADE_NOTEBOOK_SMALL") == "1"   # the test suite runs small
render = jax.jit(ds.render, static_argnames="opts")

def show(images, titles, cols=4, scale=2.6):
    rows = -(-len(images) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(scale * cols, scale * rows), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, img, t in zip(axes.flat, images, titles):
        ax.imshow(np.clip(np.asarray(img), 0, 1)); ax.set_title(t, fontsize=9)
    plt.tight_layout(); plt.show()

import equinox as eqx

def scene_with(size, **over):
    # The default scene at size², sections updated (a dict), replaced (a list) or removed (None).
    d = {k: (dict(v) if isinstance(v, dict) else v) for k, v in ds.DEFAULT_SCENE.items()}
    d["camera"] = dict(d["camera"], width=size, height=size)
    for k, v in over.items():
        if v is None:
            d.pop(k, None)
        else:
            d[k] = dict(d.get(k, {}), **v) if isinstance(v, dict) and k not in ("light", "mesh") else v
    return ds.scene_from_dict(d)

def with_blinn(s):
    # The same material with its Phong exponent converted to Blinn–Phong (m' = 4m).
    return eqx.tree_at(lambda x: x.material.shininess, s, ds.phong_to_blinn(s.material.shininess))
"""

TOUR = [
    (
        "md",
        """\
# 1 · A tour of every illumination term

The classic local model of `docs/model.md` (eq. 14–15):

$$I = I_{emit} + k_a I_a + \\sum_i f_{rad,i}\\, f_{ang,i} \\big(k_a I_{a,i} + I_{p,i}(k_d (n\\cdot l_i)^+ + k_s\\,\\mathrm{spec}_i)\\big),$$

then optional clamping, then fog. Each term is switched on in `RenderOptions` (static: a term
a scene does not use is not in the compiled program) and every number lives in the `Scene`
(traced: changing it never recompiles). All images are linear and unclamped; they are clipped
only for display.""",
    ),
    (
        "code",
        SETUP
        + """
SIZE = 64 if SMALL else 192
scene, opts = scene_with(SIZE, fog=None, background=[0, 0, 0])
print(opts)""",
    ),
    (
        "md",
        "## The terms one at a time, and their sum\n\nThe image is linear in the terms: ambient + diffuse + specular rendered separately add up to the full render (checked below).",
    ),
    (
        "code",
        """\
nofog = opts.with_keys(fog="none")
parts = {
    "ambient k_a I_a": nofog.with_keys(diffuse=False, specular="none"),
    "Lambert k_d (n·l)": nofog.with_keys(ambient=False, specular="none"),
    "Phong k_s (v·r)^m": nofog.with_keys(ambient=False, diffuse=False),
    "Blinn k_s (n·h)^4m": nofog.with_keys(ambient=False, diffuse=False, specular="blinn"),
}
imgs = {k: render(with_blinn(scene) if "Blinn" in k else scene, o) for k, o in parts.items()}
full = render(scene, nofog)
summed = imgs["ambient k_a I_a"] + imgs["Lambert k_d (n·l)"] + imgs["Phong k_s (v·r)^m"]
err = float(jnp.max(jnp.abs(summed - full)))
print(f"max |ambient + diffuse + specular - full| = {err:.2e}")
assert err < 1e-5
show(list(imgs.values()) + [full], list(imgs) + ["sum (no fog)"], cols=5)""",
    ),
    (
        "md",
        "## Light kinds: directional, point with radial attenuation $1/(a_0 + a_1 d + a_2 d^2)$, spot with a hard and a smooth cutoff",
    ),
    (
        "code",
        """\
base = dict(ds.DEFAULT_SCENE["material"])
lights = {
    "directional": [{"type": "directional", "color": [1, 1, 1], "direction": [1, -0.5, -1]}],
    "point, a = (1, 0, 0)": [{"type": "point", "color": [1, 1, 1], "position": [2, 2, 3], "attenuation": [1, 0, 0]}],
    "point, a = (1, 0.05, 0.3)": [{"type": "point", "color": [1, 1, 1], "position": [2, 2, 3], "attenuation": [1, 0.05, 0.3]}],
    "spot, hard cutoff 8°": [{"type": "spot", "color": [1, 1, 1], "position": [0, 0, 4], "axis": [0, 0, -1],
                               "cutoff": 8.0, "exponent": 2.0}],
    "spot, smooth edge 4°": [{"type": "spot", "color": [1, 1, 1], "position": [0, 0, 4], "axis": [0, 0, -1],
                              "cutoff": 8.0, "exponent": 2.0, "edge": 4.0}],
}
out = []
for name, ls in lights.items():
    s, o = scene_with(SIZE, light=ls, render={"fog": "none", "spot_edge": "smooth" if "smooth" in name else "hard"},
                      fog=None, background=[0, 0, 0])
    out.append(render(s, o))
# Spot: outside the cone nothing but ambient; inside the hard cone the full spot term.
centre, corner = np.asarray(out[3])[SIZE // 2, SIZE // 2], np.asarray(out[3])[SIZE // 2, int(SIZE * 0.82)]
print("hard spot: centre", centre.round(3), " outside the cone", corner.round(3))
assert centre.sum() > 3 * corner.sum()
show(out, list(lights), cols=5)""",
    ),
    (
        "md",
        "## Specular variants: Fresnel (Schlick, dielectric), per-light ambient, emission, two-sided lighting with a back material",
    ),
    (
        "code",
        """\
variants = {
    "Blinn–Phong": {"specular": "blinn"},
    "Blinn + Schlick Fresnel": {"specular": "blinn", "fresnel": "schlick"},
    "Blinn + dielectric Fresnel": {"specular": "blinn", "fresnel": "dielectric"},
    "per-light ambient": {"per_light_ambient": True},
}
out = []
for name, r in variants.items():
    s, o = scene_with(SIZE, render=dict(r, fog="none"), fog=None, background=[0, 0, 0])
    out.append(render(with_blinn(s) if r.get("specular") == "blinn" else s, o))
s, o = scene_with(SIZE, material=dict(base, emission=[0.25, 0.0, 0.1]), render={"fog": "none", "emission": True},
                  fog=None, background=[0, 0, 0])
out.append(render(s, o))
show(out, list(variants) + ["emission (0.25, 0, 0.1)"], cols=5)""",
    ),
    (
        "md",
        "## Shading modes: flat (one colour per triangle), Gouraud (vertex colours interpolated), Phong (normals interpolated) — on a coarse sphere, where they differ most",
    ),
    (
        "code",
        """\
out = []
for mode in ("flat", "gouraud", "phong"):
    s, o = scene_with(SIZE, mesh={"icosphere": 1}, render={"shading": mode, "fog": "none"}, fog=None, background=[0, 0, 0])
    out.append(render(s, o))
show(out, ["flat", "Gouraud", "Phong"], cols=3)""",
    ),
    ("md", "## Fog: linear, exp, exp² by eye distance; the background takes the fog colour"),
    (
        "code",
        """\
out, names = [], []
for mode, f in (("linear", {"start": 2.0, "end": 4.5}), ("exp", {"density": 0.3}), ("exp2", {"density": 0.3})):
    s, o = scene_with(SIZE, render={"fog": mode}, fog=dict(f, color=[0.55, 0.6, 0.7]))
    out.append(render(s, o)); names.append(f"{mode} {f}")
show(out, names, cols=3)""",
    ),
    (
        "md",
        "## Model only what a scene needs\n\nThe compiled program of a diffuse-only scene against the all-terms one (XLA HLO "
        "instructions, and which transcendental operations it holds: the specular power, Fresnel's and the fog's "
        "exponentials are exp and log; a diffuse-only program computes none). These are the JAX stages' programs "
        '(`backend="jax"`): on a CPU the native shading kernel renders both scenes, and it takes the same '
        "switches, branching on them outside its loops over the pixels.",
    ),
    (
        "code",
        """\
import re

s, _ = scene_with(SIZE)
s_all = eqx.tree_at(lambda x: x.back_material, s, s.material, is_leaf=lambda x: x is None)
stages = ds.Raster(backend="jax")
diffuse_only = ds.RenderOptions(raster=stages, lighting=ds.Lighting(specular="none", ambient=False))
all_terms = ds.RenderOptions(raster=stages, lighting=ds.Lighting(specular="blinn", fresnel="dielectric", emission=True,
                                                                per_light_ambient=True), fog=ds.FogModel("exp2"))
sizes, ops = {}, {}
# the all-terms scene has a back material (two-sided lighting uses it); the diffuse-only one has none.
# Instructions, not text lines: the text also carries metadata (source lines) that moves with the code.
# Shading only, the visibility given (with backend="jax" the rasterizer's own program is large).
for name, sc, o in (("diffuse only", s, diffuse_only), ("all terms", s_all, all_terms)):
    ids = ds.scene_visibility(sc, o)
    text = jax.jit(lambda s, i, o=o: ds.render(s, o, i)).lower(sc, ids).compile().as_text()
    sizes[name] = len(re.findall(r" = \\S+ [\\w-]+\\(", text))
    ops[name] = [op for op in ("exponential", "log") if re.search(rf" {op}\\(", text)]
print(sizes, ops)
assert ops["diffuse only"] == [] and ops["all terms"] == ["exponential", "log"]
assert sizes["all terms"] > 1.3 * sizes["diffuse only"]""",
    ),
]

FITTING = [
    (
        "md",
        """\
# 2 · Fitting material, attenuation and fog from images

The default scene (5,120-face icosphere, a point and a directional light, exp fog) is rendered
from known parameters; the target is quantised to 8 bits with Gaussian noise σ = 2/255. We fit 13
numbers — $k_a, k_d, k_s$ (RGB), $m$, the point light's $a_1, a_2$ ($a_0 = 1$ fixed: the gauge of
the attenuation, as OpenGL's default) and the fog density from a start up to 30% off: variable
projection (the reflectances solved exactly at every step, Levenberg–Marquardt on the rest), a
float64 polish, and for each parameter the standard error and the profile-likelihood interval
(the range where the χ², the others re-fitted, rises by less than 9: ±3 s.e. where the image is
linear in the parameters, wider where a trade-off bends).""",
    ),
    (
        "code",
        SETUP
        + """
from fitting import Observations, Optimistix, ParamSet, VarPro, fit
from fitting.cli import DEMO_FREE

SIZE = 48 if SMALL else 256
scene, opts = scene_with(SIZE)
pset = ParamSet(DEMO_FREE, scene)
true = np.asarray(pset.theta_of(scene), np.float64)
clean = np.asarray(render(scene, opts), np.float64)

def noisy_target(seed):
    rng = np.random.default_rng(seed)
    return np.round(np.clip(clean + rng.normal(0, 2 / 255, clean.shape), 0, 1) * 255) / 255

rng = np.random.default_rng(7)
start = true * rng.uniform(0.7, 1.3, true.shape)
s0 = pset.apply(scene, jnp.asarray(start, jnp.float32))
target = noisy_target(0)
r = fit(s0, opts, Observations(target, saturation=1.0, quantum=1 / 255), DEMO_FREE, history=True)
print(f"{r.result or 'successful'}: {r.steps} steps, compile {r.compile_s:.1f} s, solve {r.solve_s:.2f} s, "
      f"PSNR {r.residual.psnr:.1f} dB, SSIM {r.residual.ssim:.4f}")
print(f"{'parameter':22s} {'true':>9s} {'fitted':>9s} {'std.err':>9s} {'z':>6s}   3σ profile interval (Δχ² = 9)")
for n, t, v, e, (lo, hi) in zip(r.names, true, r.values, r.stderr, r.intervals.bounds):
    print(f"{n:22s} {t:9.4f} {v:9.4f} {e:9.2e} {(v - t) / e:6.2f}   [{lo:.4f}, {hi:.4f}]")
print(r.notes[-1])
assert r.successful and r.within(true).all()""",
    ),
    (
        "md",
        "## Convergence\n\nThe loss of every accepted step (variable-projection LM, then the polish) and the relative error of every parameter along the way (recorded with `fit(..., history=True)`).",
    ),
    (
        "code",
        """\
loss = np.array([h[0] for h in r.history]); th = np.array([h[1] for h in r.history])
fig, ax = plt.subplots(1, 2, figsize=(11, 3.6))
ax[0].semilogy(loss, ".-"); ax[0].set_xlabel("step"); ax[0].set_ylabel("½‖r‖²"); ax[0].set_title("loss")
rel = np.abs(th - true) / np.abs(true)
for j, n in enumerate(r.names):
    ax[1].semilogy(rel[:, j], lw=1, label=n)
ax[1].set_xlabel("step"); ax[1].set_title("relative parameter error"); ax[1].legend(fontsize=6, ncol=2)
plt.tight_layout(); plt.show()
fitted = render(pset.apply(scene, jnp.asarray(r.values, jnp.float32)), opts)
show([target, render(s0, opts), fitted, 0.5 + 10 * (np.asarray(fitted) - target)],
     ["target (8-bit + noise)", "start", "fit", "10 × residual + ½"])""",
    ),
    (
        "md",
        """\
## Uncertainty: are the reported standard errors honest?

Over independent noise seeds, $z = (\\hat\\theta - \\theta)/\\mathrm{se}$ should be close to a
standard normal: nearly all $|z| \\le 3$.""",
    ),
    (
        "code",
        """\
seeds = range(3 if SMALL else 20)
zs = []
for seed in seeds:
    rr = fit(s0, opts, Observations(noisy_target(100 + seed), saturation=1.0, quantum=1 / 255), DEMO_FREE)
    zs.append((rr.values - true) / rr.stderr)
zs = np.array(zs)
inside = np.mean(np.abs(zs) <= 3)
print(f"{len(zs)} seeds × {zs.shape[1]} parameters: {100 * inside:.1f}% within 3 standard errors; "
      f"std of z = {zs.std():.2f}")
plt.figure(figsize=(5, 3)); plt.hist(zs.ravel(), bins=20, density=True, alpha=0.7)
x = np.linspace(-4, 4, 200); plt.plot(x, np.exp(-x ** 2 / 2) / np.sqrt(2 * np.pi)); plt.xlabel("z"); plt.show()
assert inside >= 0.95""",
    ),
    (
        "md",
        """\
## Identifiability: what the images cannot tell

Without a specular term the image says nothing about $m$ (a zero Jacobian column: reported as
*undetermined*, standard error ∞, value = the start). $k_a$ and the ambient light $I_a$ appear only
as a product: a *gauge*, reported with the weakest combination. The fit never returns these as
if they were recovered.""",
    ),
    (
        "code",
        """\
s2, o2 = scene_with(SIZE, render={"specular": "none"})
t2 = render(s2, o2)
r2 = fit(s2, o2, Observations(t2), ["material.diffuse", "material.shininess", "material.ambient", "ambient_light"],
         shared=["material.ambient", "ambient_light"], strategy=VarPro(max_steps=30))
print("undetermined:", r2.diagnostics.undetermined)
print("gauges:", r2.diagnostics.gauges)
assert r2.diagnostics.undetermined == ["material.shininess"] and r2.diagnostics.gauges""",
    ),
    (
        "md",
        "## Which terms do the images support?\n\n`compare_models` fits nested and competing term sets (no specular; the reflectance ladder of diffuse × specular models, Lambert / Oren–Nayar × Phong / Blinn–Phong / Beckmann / GGX / Ward; no fog) and ranks them by BIC, each with its time per fit. (At the small test size, a part of the ladder.)",
    ),
    (
        "code",
        """\
from fitting import compare_models, model_variants
ladder = dict(diffuse=("lambert",), specular=("phong", "blinn", "ggx")) if SMALL else {}
scores = compare_models(s0, opts, Observations(target, saturation=1.0), DEMO_FREE, given=r,
                        variants=model_variants(s0, opts, DEMO_FREE, **ladder), intervals=False)
for m in scores:
    print(f"{m.name:20s} k={m.k:2d}  RSS={m.rss:.4e}  ΔBIC={m.bic - scores[0].bic:10.1f}  {m.seconds:6.3f} s/fit  {m.fit.result or 'successful'}")
assert scores[0].name == "as given\"""",
    ),
]

SPEED = [
    (
        "md",
        """\
# 3 · Speed against error

Every choice trades time for accuracy. Errors are measured against a reference render (Phong
shading of a finely subdivided sphere, 4× supersampled, float64); times are steady-state
medians (compile apart). Points on the Pareto front (no other configuration is both faster and
more accurate) are marked.""",
    ),
    (
        "code",
        SETUP
        + """
jax.config.update("jax_enable_x64", True)
SIZE = 48 if SMALL else 192

def timed(fn, *args, repeats=5 if SMALL else 15):
    jax.block_until_ready(fn(*args))
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter(); jax.block_until_ready(fn(*args)); ts.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(ts))

def downsample(img, f):
    h, w, c = img.shape
    return img.reshape(h // f, f, w // f, f, c).mean(axis=(1, 3))

def cast(s, dtype):
    return jax.tree.map(lambda x: x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x, s)

def scene_at(size, sub, dtype=jnp.float32):
    s, o = scene_with(size, mesh={"icosphere": sub}, render={"fog": "none"}, fog=None, background=[0, 0, 0])
    return cast(s, dtype), o

ref_scene, ref_opts = scene_at(4 * SIZE, 5 if SMALL else 6, jnp.float64)
reference = downsample(np.asarray(render(ref_scene, ref_opts), np.float64), 4)

def pareto(points):
    front = []
    for i, (t, e) in enumerate(points):
        if not any((t2 <= t and e2 <= e) and (t2 < t or e2 < e) for t2, e2 in points):
            front.append(i)
    return front""",
    ),
    ("md", "## Shading mode × mesh resolution × supersampling"),
    (
        "code",
        """\
rows = []
subs = (2, 3) if SMALL else (2, 3, 4, 5)
sss = (1, 2) if SMALL else (1, 2, 3)
for mode in ("flat", "gouraud", "phong"):
    for sub in subs:
        for ss in sss:
            s, o = scene_at(SIZE * ss, sub)
            o = o.with_keys(shading=mode)
            fn = jax.jit(lambda s, o=o, ss=ss: ds.render(s, o).reshape(SIZE, ss, SIZE, ss, 3).mean(axis=(1, 3)))
            img = np.asarray(fn(s), np.float64)
            rows.append((mode, sub, ss, timed(fn, s), float(np.sqrt(np.mean((img - reference) ** 2)))))
pts = [(r[3], r[4]) for r in rows]
front = set(pareto(pts))
print(f"{'shading':8s} {'sub':>3s} {'ss':>2s} {'ms':>8s} {'RMS error':>10s}")
for i, (mode, sub, ss, t, e) in enumerate(rows):
    print(f"{mode:8s} {sub:3d} {ss:2d} {t:8.2f} {e:10.2e}" + ("   ← Pareto" if i in front else ""))
fig, ax = plt.subplots(figsize=(6.5, 4))
for mode, mk in (("flat", "s"), ("gouraud", "^"), ("phong", "o")):
    sel = [i for i, r in enumerate(rows) if r[0] == mode]
    ax.loglog([pts[i][0] for i in sel], [pts[i][1] for i in sel], mk, label=mode, alpha=0.7)
fr = sorted(front, key=lambda i: pts[i][0])
ax.loglog([pts[i][0] for i in fr], [pts[i][1] for i in fr], "k--", lw=1, label="Pareto front")
ax.set_xlabel("render time (ms)"); ax.set_ylabel("RMS error vs reference"); ax.legend(); plt.show()
# Phong shading of the finest mesh, supersampled, is the most accurate of all.
best = min(range(len(rows)), key=lambda i: rows[i][4])
assert rows[best][0] == "phong" and rows[best][2] == max(sss)""",
    ),
    (
        "md",
        """\
## The other local models: what each explains, at what cost

Oren–Nayar, Cook–Torrance (Beckmann, GGX) and Ward cost a little more than Lambert and
Blinn–Phong per pixel (an exponential, a square root, a division or two more). What do they buy? A target rendered with Cook–Torrance GGX (α = 0.3: the long-tailed
highlight of a real glossy ball), 8-bit, fitted by every model of the ladder from the usual
Blinn–Phong guess: each model's render time and time per fit against its residual. (At the
small test size, a part of the ladder.)""",
    ),
    (
        "code",
        """\
from fitting import Observations, compare_models, model_variants
ms, mo = scene_at(SIZE, 3)
mo = mo.with_keys(specular="ggx")
ms = eqx.tree_at(lambda x: x.material.roughness, ms, jnp.float32(0.3))
clean = np.asarray(render(ms, mo), np.float64)
noisy = np.round(np.clip(clean + np.random.default_rng(0).normal(0, 1 / 255, clean.shape), 0, 1) * 255) / 255
guess = mo.with_keys(specular="blinn")
start = eqx.tree_at(lambda x: x.material.shininess, ms, jnp.float32(40.0))
free = ["material.diffuse", "material.specular", "material.shininess"]
ladder = dict(diffuse=("lambert",), specular=("phong", "blinn", "ggx")) if SMALL else {}
scores = compare_models(start, guess, Observations(noisy, saturation=1.0, quantum=1 / 255), free,
                        variants=[("blinn", guess, free, start)] + model_variants(start, guess, free, **ladder)[2:],
                        intervals=False)
print(f"{'model':22s} {'render ms':>9s} {'fit s':>7s} {'RMS residual':>12s} {'ΔBIC':>10s}")
pts = []
for m in scores:
    fn = jax.jit(lambda s, o=m.opts: ds.render(s, o))
    t = timed(fn, start)
    rms = float(np.sqrt(m.rss / m.n))
    pts.append((t, rms))
    print(f"{m.name:22s} {t:9.2f} {m.seconds:7.3f} {rms:12.2e} {m.bic - scores[0].bic:10.1f}")
assert scores[0].name == "ggx", scores[0].name  # the images pick the truth""",
    ),
    ("md", "## float32 against float64"),
    (
        "code",
        """\
res = {}
for dt in (jnp.float32, jnp.float64):
    s, o = scene_at(SIZE, 4, dt)
    fn = jax.jit(lambda s, o=o: ds.render(s, o))
    res[jnp.dtype(dt).name] = (timed(fn, s), np.asarray(fn(s), np.float64))
d = float(np.max(np.abs(res["float32"][1] - res["float64"][1])))
print(f"float32 {res['float32'][0]:.2f} ms, float64 {res['float64'][0]:.2f} ms; max |difference| {d:.1e}")
assert d < 1e-4""",
    ),
    (
        "md",
        "## Method and iteration count: time to fit against parameter error\n\nThe 13 parameters of the demo from a start 30% off, noise-free target, from that start alone (no global search, no polish), each method with a cap on its steps: the default compiled variable-projection program (9 reflectances solved exactly under their bounds at every step, Marquardt-scaled LM on the 4 nonlinear parameters with Kaufman's Jacobian), optimistix's LM or Dogleg on the same reduced residual, and Levenberg–Marquardt on all 13.",
    ),
    (
        "code",
        """\
from fitting import Observations, Optimistix, ParamSet, VarPro, fit
from fitting.cli import DEMO_FREE
fs, fo = scene_with(SIZE)
fs = cast(fs, jnp.float32)
pset = ParamSet(DEMO_FREE, fs)
true = np.asarray(pset.theta_of(fs), np.float64)
tgt = render(fs, fo)
s0 = pset.apply(fs, jnp.asarray(true * np.random.default_rng(3).uniform(0.7, 1.3, true.shape), jnp.float32))
methods = {"varpro (default)": (VarPro, dict(method="auto")), "varpro + lm": (Optimistix, dict(method="auto", solver="lm")),
           "varpro + dogleg": (Optimistix, dict(method="auto", solver="dogleg")),
           "full lm": (Optimistix, dict(method="full", solver="lm"))}
if SMALL:
    methods.pop("varpro + dogleg")
    methods.pop("full lm")
caps = (5, 100) if SMALL else (3, 5, 10, 20, 100)
runs = []
for name, (kind, kw) in methods.items():
    # the default program takes its step limit as data; optimistix's solvers compile once per limit
    for cap in (caps if name == "varpro (default)" or not SMALL else caps[-1:]):
        rr = fit(s0, fo, Observations(tgt), DEMO_FREE,
                 strategy=kind(max_steps=cap, starts=1, restarts=0, polish_steps=0, **kw))  # the cap is the cap
        runs.append((name, cap, rr.steps, rr.solve_s * 1e3, float(np.max(np.abs(rr.values - true) / true)),
                     (rr.result or "successful").split(".")[0][:40]))
pts = [(r[3], r[4]) for r in runs]
front = set(pareto(pts))
print(f"{'method':16s} {'cap':>4s} {'steps':>5s} {'ms':>8s} {'max rel err':>11s}  result")
for i, r in enumerate(runs):
    print(f"{r[0]:16s} {r[1]:4d} {r[2]:5d} {r[3]:8.1f} {r[4]:11.2e}  {r[5]}" + ("   ← Pareto" if i in front else ""))
fig, ax = plt.subplots(figsize=(6.5, 4))
for name in methods:
    sel = [i for i, r in enumerate(runs) if r[0] == name]
    ax.loglog([pts[i][0] for i in sel], [pts[i][1] for i in sel], "o-", label=name)
ax.set_xlabel("solve time (ms)"); ax.set_ylabel("max relative parameter error"); ax.legend(); plt.show()
lm = [r for r in runs if r[0] == "varpro + lm" and r[1] == 100][0]
assert lm[4] < 1e-4""",
    ),
]


GLASS = [
    (
        "md",
        """\
# 4 · Transparency, absorption, transmission and shadows

docs/model.md §2 and §5 and the lecture notes' part on transparency (docs/model.md §5), on a floor,
a glass box and a ball with Kay's opacity (`examples/glass_and_shadows.toml`):

- opacity `t`, composited front to back over the `K` nearest surfaces, `I = t I₁ + (1 − t) I₂`;
- Kay's opacity `t = t_min + (t_max − t_min)[1 − (1 − |n_z|)^p]`;
- Bouguer's absorption `e^{−μℓ}`, `ℓ` the thickness between the entry and exit surfaces;
- directed transmission `k_t I_p cos^m β` with Snell refraction and total internal reflection;
- shadow maps for directional, point (six views) and spot lights, with percentage-closer filtering.

Everything numeric stays differentiable; the last section fits the glass back from an image.""",
    ),
    (
        "code",
        SETUP
        + """
from pathlib import Path
import diffshade._shade as S
EXAMPLE = Path(ds.__file__).resolve().parent.parent / "examples" / "glass_and_shadows.toml"
SIZE = 64 if SMALL else 256
scene, opts = ds.load_scene(EXAMPLE)
scene = eqx.tree_at(lambda s: s.camera, scene, ds.Camera(
    eye=scene.camera.eye, target=scene.camera.target, up=scene.camera.up, fov_y=scene.camera.fov_y,
    near=scene.camera.near, far=scene.camera.far, width=SIZE, height=SIZE))
if SMALL:
    opts = opts.with_keys(shadow_resolution=128)
print(opts)
print(len(scene.all_materials()), "materials,", scene.mesh.faces.shape[0], "faces")""",
    ),
    (
        "md",
        """\
## Depth layers

With `K` layers each pixel composites its `K` nearest surfaces; what lies beyond the last one is
replaced by the background (the light left over, `Π(1 − t_k)`, comes from it).
`ds.truncated_pixels` counts the pixels where that happens: here the floor seen through both walls
of the box and both sides of the ball needs `K = 5`.""",
    ),
    (
        "code",
        """\
images, titles = [render(scene, opts.with_keys(transparency=False, absorption=False, transmission=False))], ["opaque"]
for K in ((1, 5) if SMALL else (1, 2, 3, 5)):
    o = opts.with_keys(layers=K, absorption=K >= 2)
    images.append(render(scene, o))
    titles.append(f"K = {K}: {ds.truncated_pixels(scene, o)} px truncated")
show(images, titles, cols=5)
assert ds.truncated_pixels(scene, opts.with_keys(layers=5)) == 0""",
    ),
    (
        "md",
        """\
## Kay's opacity

`n_z` is the view-space z of the unit normal: 1 face-on, 0 at a silhouette. The seed's names
`t_min`, `t_max` are the values at `|n_z| = 0` and `1`; Kay's look — the material appears
thicker, more opaque, towards the silhouette — has `t_min > t_max`. The power `p` sets how close to
the silhouette the change happens. The rendered ball below is the example's (t_min 0.95,
t_max 0.35, p 2) against linear opacity 0.35.""",
    ),
    (
        "code",
        """\
nz = np.linspace(0, 1, 201)
fig, ax = plt.subplots(1, 2, figsize=(11, 3.6))
for p in (0.5, 1, 2, 4, 8):
    ax[0].plot(nz, S.kay_opacity(nz, 0.95, 0.35, p), label=f"p = {p}")
ax[0].set_xlabel("|n_z|"); ax[0].set_ylabel("opacity t"); ax[0].legend(); ax[0].set_title("t_min 0.95, t_max 0.35")
ball = scene.materials[1]
plain_ball = ds.Material(ambient=ball.ambient, diffuse=ball.diffuse, specular=ball.specular, opacity=ball.kay_max)
linear = eqx.tree_at(lambda s: s.materials[1], scene, plain_ball)
both = np.concatenate([np.clip(render(linear, opts), 0, 1), np.clip(render(scene, opts), 0, 1)], axis=1)
ax[1].imshow(both); ax[1].axis("off"); ax[1].set_title("linear t = 0.35  |  Kay")
plt.tight_layout(); plt.show()
assert abs(float(S.kay_opacity(1.0, 0.95, 0.35, 2.0)) - 0.35) < 1e-7 and abs(float(S.kay_opacity(0.0, 0.95, 0.35, 2.0)) - 0.95) < 1e-7""",
    ),
    (
        "md",
        """\
## Absorption through a slab

A slab of thickness 0.6 with invisible surfaces (`t = 0`) in front of a lit plane: each pixel is
the plane's colour times `e^{−μℓ}`, `ℓ = 0.6/|cos|` along its view ray. Measured on the centre
pixel against the closed form, per channel:""",
    ),
    (
        "code",
        """\
def slab(mu, size=32):
    mats = (ds.Material(ambient=0.2, diffuse=(0.9, 0.8, 0.7), specular=0.0),
            ds.Material(specular=0.0, opacity=0.0, absorption=mu))
    cam = ds.Camera(eye=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0], fov_y=20.0, near=0.5, far=20.0, width=size, height=size)
    return ds.Scene(mesh=ds.combine(ds.quad((6, 6), (0, 0, -1)), ds.box((2, 2, 0.6), (0, 0, 0.5))), camera=cam,
                    material=mats[0], materials=mats[1:], directional=ds.DirectionalLights(
                        color=[1.0, 1.0, 1.0], direction=[0, 0, -1], ambient=[0, 0, 0]), ambient_light=1.0)
slab_opts = ds.RenderOptions(transparency=ds.Transparency(layers=3, absorption=True),
                             lighting=ds.Lighting(specular="none"))
mus = np.linspace(0, 4, 9)
centre = np.array([np.asarray(render(slab(np.full(3, m)), slab_opts))[16, 16] for m in mus])
d = np.array([0.5 / 32 * np.tan(np.deg2rad(10)) * 2, 0.5 / 32 * np.tan(np.deg2rad(10)) * 2, -1.0])  # pixel (16, 16)
ell = 0.6 / abs(d[2] / np.linalg.norm(d))
C = 0.2 + np.array([0.9, 0.8, 0.7])
plt.figure(figsize=(5, 3.4))
for c, col in enumerate("rgb"):
    plt.semilogy(mus, centre[:, c], "o", color=col)
    plt.semilogy(mus, C[c] * np.exp(-mus * ell), "-", color=col, alpha=0.5)
plt.xlabel("μ"); plt.ylabel("centre pixel"); plt.title("dots: render, lines: C e^{−μℓ}"); plt.show()
err = np.abs(centre / (C * np.exp(-mus[:, None] * ell)) - 1).max()
print(f"max relative error {err:.1e}")
assert err < 1e-5""",
    ),
    (
        "md",
        """\
## Directed transmission and the critical angle

The factor `W cos^m β` for light from inside glass (η = 1.5) reaching a viewer on the normal,
as the light's angle of incidence grows. Without Fresnel (`W = 1`) it drops to 0 at the critical
angle `arcsin(1/η)` = 41.8° (total internal reflection; `f` turns tangent, so `cos β → 0`); with
the Fresnel split `W = 1 − F` falls to 0 there as well. From the other side (a back face: light
entering the denser medium) there is no critical angle.""",
    ),
    (
        "code",
        """\
theta = np.radians(np.linspace(0, 89.5, 400))
n = (jnp.zeros_like(theta), jnp.zeros_like(theta), jnp.ones_like(theta))
l = (jnp.sin(theta), jnp.zeros_like(theta), -jnp.cos(theta))
v = (jnp.zeros_like(theta), jnp.zeros_like(theta), jnp.ones_like(theta))
plt.figure(figsize=(6, 3.6))
for back, fres, style in ((False, "none", "-"), (False, "dielectric", "--"), (False, "schlick", ":"), (True, "dielectric", "-.")):
    plt.plot(np.degrees(theta), S.directed_transmission(n, l, v, 1.0, 1.5, back, fres), style,
             label=f"{'back' if back else 'front'} face, Fresnel {fres}")
plt.axvline(np.degrees(np.arcsin(1 / 1.5)), color="k", lw=0.5)
plt.xlabel("angle of incidence (deg)"); plt.ylabel("W cos^m β (m = 1)"); plt.legend(fontsize=8); plt.show()
g = jax.grad(lambda e: S.directed_transmission(n, l, v, 1.0, e, False, "dielectric").sum())(1.5)
assert np.isfinite(g)""",
    ),
    (
        "md",
        """\
## Shadows

One light at a time, with and without percentage-closer filtering, and the cost of the maps
(steady state, compile apart). A point light renders six 90° views; receiver-plane depth keeps
the lit floor free of acne with a bias of 10⁻³.""",
    ),
    (
        "code",
        """\
def timed(fn, *args, repeats=3 if SMALL else 10):
    jax.block_until_ready(fn(*args))
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter(); jax.block_until_ready(fn(*args)); ts.append(time.perf_counter() - t0)
    return 1e3 * np.median(ts)

images, titles = [], []
plain = opts.with_keys(transparency=False, absorption=False, transmission=False)
for kind in ("directional", "point", "spot"):
    one = scene
    for other in ("directional", "point", "spot"):
        if other != kind:
            one = eqx.tree_at(lambda s: getattr(s, other), one, {"directional": ds.no_directional,
                              "point": ds.no_point, "spot": ds.no_spot}[other]())
    for pcf in ((3,) if SMALL else (1, 3)):
        o = plain.with_keys(shadow_pcf=pcf)
        f = jax.jit(lambda s, o=o: ds.render(s, o))
        images.append(f(one)); titles.append(f"{kind}, PCF {pcf}: {timed(f, one):.0f} ms")
    if not SMALL:  # (the test suite skips the timing without shadows)
        off = jax.jit(lambda s: ds.render(s, plain.with_keys(shadows=False)))
        print(f"{kind:11s} without shadows {timed(off, one):6.1f} ms")
show(images, titles, cols=6, scale=2.4)""",
    ),
    (
        "md",
        """\
## Fitting the glass

Opacity, absorption and transmission of the box and Kay's three parameters of the ball, from
the image of the scene (Levenberg–Marquardt through forward-mode Jacobians; the shadows are
discrete, so the fit would see them as fixed: they are off here).

In the example every light is on the camera's side of the glass, so no light reaches the eye
*through* it: the image does not depend on `k_t` at all, and the fit says so — the transmission
is reported undetermined (infinite standard error) and left at its start.""",
    ),
    (
        "code",
        """\
from fitting import Observations, Optimistix, ParamSet, VarPro, fit
names = ["material[1].opacity", "material[1].absorption", "material[1].transmission",
         "material[2].kay_min", "material[2].kay_max", "material[2].kay_power"]
fopts = opts.with_keys(layers=5, shadows=False)

def fit_glass(scene):
    target = render(scene, fopts)
    ps = ParamSet(names, scene)
    theta = np.asarray(ps.theta_of(scene))
    start = ps.apply(scene, theta * np.random.default_rng(1).uniform(0.75, 1.25, theta.size))
    r = fit(start, fopts, Observations(target), names, strategy=VarPro(max_steps=60))
    rel = np.abs(np.asarray(r.values) / theta - 1)
    for lab, t0, s0, v, e, se in zip(ps.labels, theta, np.asarray(ps.theta_of(start)), np.asarray(r.values), rel, r.stderr):
        print(f"{lab:28s} true {t0:7.4f}  start {s0:7.4f}  fit {v:7.4f}  rel. error {e:.1e}  s.e. {se:.1e}")
    print(f"successful {r.successful}, {r.steps} steps, solve {r.solve_s:.2f} s (compile {r.compile_s:.1f} s); "
          f"undetermined: {r.diagnostics.undetermined}")
    return r, rel, ps

r, rel, ps = fit_glass(scene)
assert r.successful and sorted(r.diagnostics.undetermined) == [f"material[1].transmission[{c}]" for c in "bgr"]
known = np.array(["transmission" not in lab for lab in ps.labels])
assert rel[known].max() < 1e-3""",
    ),
    ("md", "A point light behind the box makes the transmission visible; now all ten values come back:"),
    (
        "code",
        """\
back = ds.PointLights(color=[[1.0, 1.0, 1.0]], position=[[-0.5, -0.1, -0.2]], attenuation=[[1.0, 0.0, 0.5]],
                      ambient=[[0.0, 0.0, 0.0]])
lit_behind = eqx.tree_at(lambda s: s.point, scene, ds.PointLights(
    color=jnp.concatenate([scene.point.color, back.color]), position=jnp.concatenate([scene.point.position, back.position]),
    attenuation=jnp.concatenate([scene.point.attenuation, back.attenuation]),
    ambient=jnp.concatenate([scene.point.ambient, back.ambient])))
show([render(scene, fopts), render(lit_behind, fopts)], ["example", "+ a light behind the glass"], cols=2, scale=3.5)
r2, rel2, _ = fit_glass(lit_behind)
assert r2.successful and not r2.diagnostics.undetermined and rel2.max() < 1e-3""",
    ),
]

MIRRORS = [
    (
        "md",
        """\
# 5 · Mirrors and glass: the global model by ray tracing

docs/model.md §6 and the lecture notes' global model: at every surface point seen along a ray,

$$I = I_{local} + k_r I_r + k_{rt} I_t,$$

`I_local` every local term (§1–2), `I_r` the light arriving along the mirror direction
`R = 2(N·V)N − V`, `I_t` along Snell's refracted direction (index `η` entering, `1/η` leaving,
total internal reflection past the critical angle), traced recursively to `ray_depth`; Bouguer's
`e^{−μℓ}` over the true path inside, the background where a ray leaves the scene. Primary
visibility is the rasterizer's; secondary rays come from Intel Embree (or a portable JAX engine),
and every hit is recomputed in JAX from the vertices, so the image is differentiable in `η`,
`μ`, the weights, the lights and the geometry.

A glass ball (`refraction` 0.9, `mirror` 0.1) over a chequered floor, in front of a wall.""",
    ),
    (
        "code",
        SETUP
        + """
SIZE = 48 if SMALL else 160

def glass_scene(size, ball=None, render=None, tiles=6, floor=None):
    objs = [{"icosphere": 3, "translate": [0.0, 0.05, 0.0], "scale": 0.75,
             "material": {"diffuse": 0.0, "ambient": 0.0, "specular": 0.6, "shininess": 120, "refraction": 0.9,
                          "mirror": 0.1, "ior": 1.5, "absorption": [0.05, 0.3, 0.9], **(ball or {})}}]
    w = 8.0 / tiles
    for i in range(tiles):
        for j in range(tiles):
            col = [0.85, 0.82, 0.75] if (i + j) % 2 else [0.12, 0.2, 0.5]
            objs.append({"quad": [w, w], "normal": [0, 1, 0], "translate": [-4 + w * (i + 0.5), -0.7, -5 + w * (j + 0.5)],
                         "material": {"diffuse": col, "specular": 0.0, **(floor or {})}})
    objs.append({"quad": [8, 4], "normal": [0, 0, 1], "translate": [0, 1.3, -5], "divisions": 2,
                 "material": {"diffuse": [0.6, 0.35, 0.3], "specular": 0.0}})
    d = {"camera": {"eye": [0, 0.9, 3.6], "target": [0, -0.2, 0], "up": [0, 1, 0], "fov_y": 40, "near": 0.1,
                    "far": 50, "width": size, "height": size},
         "render": {"shading": "phong", "specular": "blinn", "fog": "none", **(render or {})},
         "object": objs,
         "light": [{"type": "point", "position": [2.0, 3.0, 2.5], "attenuation": [1, 0, 0.02]},
                   {"type": "directional", "direction": [-0.5, -1, -0.3], "color": 0.35}],
         "background": [0.55, 0.65, 0.8]}
    return ds.scene_from_dict(d)

scene, opts = glass_scene(SIZE)
print(scene.mesh.faces.shape[0], "faces,", len(scene.all_materials()), "materials; ray engine:",
      ds._rays.resolve_ray_backend("auto"))""",
    ),
    (
        "md",
        """\
## Term by term

The rasterizer's local terms alone (the ball is black glass with a highlight), then the mirror
ray, the refracted ray (bending the floor's chequers), absorption inside the glass, and the
Fresnel split of the weights (`k_r + k_rt F`, `k_rt (1 − F)`: more reflection at grazing angles).""",
    ),
    (
        "code",
        """\
D = 2 if SMALL else 4
steps = [("local (rasterizer)", dict(refraction=0.0, mirror=0.1), dict(ray_depth=0)),
         ("+ reflection", dict(refraction=0.0, mirror=0.1), dict(ray_depth=1)),
         ("+ refraction", dict(absorption=[0.0, 0.0, 0.0]), dict(ray_depth=D)),
         ("+ absorption", {}, dict(ray_depth=D)),
         ("+ Fresnel", {}, dict(ray_depth=D, fresnel="dielectric"))]
images = []
for title, ball, r in steps:
    s, o = glass_scene(SIZE, ball=ball, render=r)
    images.append(render(s, o))
show(images, [t for t, _, _ in steps], cols=5, scale=2.8)
diff = [float(np.abs(np.asarray(a) - np.asarray(b)).max()) for a, b in zip(images, images[1:])]
print("each step changes the image by up to", ", ".join(f"{d:.2f}" for d in diff))
assert min(diff) > 1e-2""",
    ),
    (
        "md",
        """\
## Depth against error and time

How deep must the recursion go? Each depth against a reference traced to depth 7 (error: RMS
over the image), and the time of a frame (median, compile apart) with the generations compacted
to the rays that live (`ray_capacity` from `ds.ray_counts`): only the ball's pixels spawn rays.
The error falls by the light lost inside the glass at each bounce; the cost grows with the rays
that stay alive.""",
    ),
    (
        "code",
        """\
def timed(fn, *args, repeats=3 if SMALL else 9):
    jax.block_until_ready(fn(*args))
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter(); jax.block_until_ready(fn(*args)); ts.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(ts))

REF = 3 if SMALL else 7
base, bopts = glass_scene(SIZE, render={"fresnel": "dielectric"})
counts = ds.ray_counts(base, bopts.with_keys(ray_depth=REF))
print("live rays per generation:", counts, f"(the image has {SIZE * SIZE} pixels)")
reference = np.asarray(render(base, bopts.with_keys(ray_depth=REF, ray_capacity=max(counts))))
rows = []
for depth in range(0, REF - 1 if SMALL else REF):
    o = bopts.with_keys(ray_depth=depth, ray_capacity=max(counts[:depth], default=0))
    img = np.asarray(render(base, o))
    rows.append((depth, timed(render, base, o), float(np.sqrt(np.mean((img - reference) ** 2)))))
for depth, ms, err in rows:
    print(f"depth {depth}: {ms:7.2f} ms  RMS error {err:.2e}")
fig, ax = plt.subplots(figsize=(5.5, 3.6))
ax.semilogy([r[1] for r in rows], [r[2] for r in rows], "o-")
for depth, ms, err in rows:
    ax.annotate(f"D={depth}", (ms, err), textcoords="offset points", xytext=(4, 4), fontsize=8)
ax.set_xlabel("ms per frame"); ax.set_ylabel(f"RMS error vs depth {REF}"); plt.show()
errs = [r[2] for r in rows]
assert all(b < a for a, b in zip(errs, errs[1:])), errs  # every bounce brings the image closer""",
    ),
    (
        "md",
        """\
## Exact shadows against shadow maps

Shadow rays decide each light's visibility exactly (no bias to tune, no texels); shadow maps
approximate it with a depth texture. An opaque ball here (maps leave glass out or treat it as
opaque; rays let it tint the shadow, next cell). Error: the fraction of floor pixels whose shadow
differs from the exact one, and the frame time.""",
    ),
    (
        "code",
        """\
opaque = dict(refraction=0.0, mirror=0.0, diffuse=[0.7, 0.3, 0.2], absorption=[0.0, 0.0, 0.0])
s_op, o_op = glass_scene(SIZE, ball=opaque)
exact = np.asarray(render(s_op, o_op.with_keys(shadow_rays=True)))
floor = np.asarray(ds.scene_visibility(s_op, o_op)[0]) >= 320
images, titles = [exact], [f"shadow rays: {timed(render, s_op, o_op.with_keys(shadow_rays=True)):.1f} ms"]
for res, pcf in ((512, 3),) if SMALL else ((128, 1), (512, 1), (2048, 1), (512, 3)):
    o = o_op.with_keys(shadows=True, shadow_resolution=res, shadow_pcf=pcf)
    img = np.asarray(render(s_op, o))
    wrong = float(np.mean(np.abs(img - exact).max(-1)[floor] > 0.02))
    images.append(img)
    titles.append(f"map {res}², PCF {pcf}: {timed(render, s_op, o):.1f} ms, {wrong:.1%} off")
show(images, titles, cols=len(images), scale=3.0)""",
    ),
    (
        "md",
        """\
Through glass, a straight shadow ray is multiplied by `k_rt` at each surface it crosses and by
`e^{−μℓ}` inside (up to `shadow_ray_crossings` surfaces): the coloured shadow of the ball.""",
    ),
    (
        "code",
        """\
s_g, o_g = glass_scene(SIZE, render={"fresnel": "dielectric"})
DEPTH = 1 if SMALL else 4
img_g = render(s_g, o_g.with_keys(ray_depth=DEPTH, shadow_rays=True))
img_b = render(s_g, o_g.with_keys(ray_depth=DEPTH, shadow_rays=True, shadow_ray_crossings=0))
show([img_b, img_g], ["glass as an opaque occluder", "coloured shadow (k_rt e^{−μℓ})"], cols=2, scale=3.6)
assert float(jnp.abs(img_g - img_b).max()) > 0.05""",
    ),
    (
        "md",
        """\
## Fitting η and k_rt from a photograph

A "photograph" of the glass ball: rendered at η = 1.52 and `k_rt` = 0.85, with Gaussian noise
(σ = 2/255) and 8-bit quantisation. First the cost as a function of η alone (the rest at the
truth): seen through the ball, the chequers move with η, so away from the truth the cost is far
from a parabola (its local minima are counted below) — a fit of a refractive index needs a start
in the right basin, as any local method does on a textured background.""",
    ),
    (
        "code",
        """\
from fitting import Observations, Optimistix, ParamSet, VarPro, fit
truth, topts = glass_scene(SIZE, ball=dict(ior=1.52, refraction=0.85), render={"ray_depth": 2 if SMALL else 3, "fresnel": "dielectric"})
clean = np.asarray(render(truth, topts))
photo = np.round(np.clip(clean + np.random.default_rng(0).normal(0, 2 / 255, clean.shape), 0, 1) * 255) / 255
etas = np.linspace(1.2, 1.8, 25 if SMALL else 61)
cost = [float(np.sum((np.asarray(render(eqx.tree_at(lambda s: s.material.ior, truth, jnp.asarray(e, truth.material.ior.dtype)),
                                           topts)) - photo) ** 2)) for e in etas]
plt.figure(figsize=(5.5, 3.2)); plt.semilogy(etas, cost, ".-"); plt.axvline(1.52, color="k", lw=0.5)
plt.xlabel("η"); plt.ylabel("sum of squared residuals"); plt.show()
minima = [i for i in range(1, len(cost) - 1) if cost[i] < cost[i - 1] and cost[i] < cost[i + 1]]
print(f"{len(minima)} local minima of the cost in η ∈ [1.2, 1.8]")
assert etas[int(np.argmin(cost))] == min(etas, key=lambda e: abs(e - 1.52))""",
    ),
    (
        "md",
        """\
On the chequers the refracted rays also cross tile edges as η changes: the image jumps there, no
derivative sees it, and a fit's standard errors come out optimistic (measured: η 3.8 s.e. off,
with the residual at the noise level). The fit below takes a plain floor lit by a nearby lamp
instead: what is seen through the ball varies smoothly, so the image is smooth in η. From η 2 %
off and the rest 15–25 % off, the fit recovers all five values and says how well the image
determines each.""",
    ),
    (
        "code",
        """\
truth, topts = glass_scene(SIZE, ball=dict(ior=1.52, refraction=0.85), tiles=1, floor={"diffuse": [0.8, 0.75, 0.6]},
                           render={"ray_depth": 2 if SMALL else 3, "fresnel": "dielectric"})
truth = eqx.tree_at(lambda s: (s.point.position, s.point.attenuation), truth,
                    (jnp.asarray([[0.8, -0.4, -1.2]]), jnp.asarray([[0.2, 0.0, 1.5]])))
clean = np.asarray(render(truth, topts))
photo = np.round(np.clip(clean + np.random.default_rng(0).normal(0, 2 / 255, clean.shape), 0, 1) * 255) / 255
names = ["material.ior", "material.refraction", "material.absorption"]
shared = ["material.refraction"]
ps = ParamSet(names, truth, shared=shared)
theta = np.asarray(ps.theta_of(truth), np.float64)
start = ps.apply(truth, jnp.asarray(theta * np.r_[0.98, 1.15, 1.25, 0.8, 1.2], truth.mesh.vertices.dtype))
r = fit(start, topts, Observations(photo, saturation=1.0, quantum=1 / 255), names, shared=shared)
for lab, t0, s0, v, se in zip(ps.labels, theta, np.asarray(ps.theta_of(start)), r.values, r.stderr):
    print(f"{lab:24s} true {t0:.4f}  start {s0:.4f}  fit {v:.4f} ± {se:.4f}  ({abs(v - t0) / se:.1f} s.e.)")
print(f"successful: {r.successful}; {r.steps} steps, solve {r.solve_s:.1f} s (compile {r.compile_s:.1f} s); "
      f"residual {r.residual.noise_ratio:.2f}× the noise")
show([photo, render(ps.apply(truth, jnp.asarray(r.values, truth.mesh.vertices.dtype)), topts), np.abs(photo - clean) * 10],
     ["photograph (8-bit, noise)", "fitted", "|noise| × 10"], cols=3, scale=3.2)
assert r.successful and abs(r.values[0] - 1.52) < 5e-3 and np.all(np.abs(r.values - theta) <= 4 * r.stderr)""",
    ),
]


PHOTOS = [
    (
        "md",
        """\
# 6 · Photographs: sRGB, exposure, calibrated cameras, per-vertex albedo

A user's targets are photographs, not renders. They are 8-bit sRGB files, each with its own
exposure and white balance, taken by calibrated cameras, of an object whose colour varies over
its surface. This notebook makes such a data set (`examples/photographs/make_dataset.py`) and
fits it, first as `diffshade fit` does, then with the encoding declared wrongly.

The data set:
- six views of a per-vertex-coloured rabbit, under two placements of one point light;
- OpenCV calibrations;
- per-view gains: view 0 is the reference, with gains 1 (docs/model.md §10);
- sensor noise of 2 codes, added before the clip to 8 bits.

The fit frees:
- the albedo of every vertex (the sparse linear block of docs/model.md §12);
- each other view's white balance;
- the attenuation `a1, a2`, `k_s` and `m`.""",
    ),
    (
        "code",
        SETUP
        + """
import importlib.util, json, tempfile
from pathlib import Path
from diffshade import color as _color
from fitting import Observations, Optimistix, ParamSet, VarPro, fit

import fitting
ROOT = Path(fitting.__file__).resolve().parent.parent   # the repository (the examples are not a package)
spec = importlib.util.spec_from_file_location("make_dataset", ROOT / "examples" / "photographs" / "make_dataset.py")
M = importlib.util.module_from_spec(spec); spec.loader.exec_module(M)
M.SIZE = 64 if SMALL else 160
data = Path(tempfile.mkdtemp())
M.main(data)
truth = json.loads((data / "truth.json").read_text())
import skimage.io
codes = [skimage.io.imread(data / f"view{i}.png")[..., :3] / 255.0 for i in range(len(M.VIEWS))]  # 8-bit code values
views = []
for i, (_, setup, _, _) in enumerate(M.VIEWS):
    s, opts = ds.load_scene(data / f"setup_{setup}.toml")
    views.append(eqx.tree_at(lambda x: x.camera, s, ds.load_camera(data / f"view{i}.json")))
show(codes, [f"view {i}: set-up {v[1]}, exposure {v[2]}" for i, v in enumerate(M.VIEWS)], cols=6)""",
    ),
    (
        "md",
        """\
## The fit, as `diffshade fit` runs it

The photographs declare sRGB in their PNG chunks. The fit measures every residual in code values
(docs/model.md §9), with the clipped codes censored. `margin=1` leaves out the pixels next to
the silhouette and next to the occlusion edges inside it (an ear in front of the head).""",
    ),
    (
        "code",
        """\
free = ["mesh.colors", "view[*].camera.white_balance", "point[0].a1", "point[0].a2", "material.specular",
        "material.shininess"]
kw = dict(views=views, saturation=1.0, quantum=1 / 255, noise=2 / 255, margin=1)
t0 = time.perf_counter()
r = fit(views[0], opts, Observations(codes, encoding="srgb", **kw), free)
print(f"{r.result or 'successful'} in {time.perf_counter() - t0:.1f} s; {r.method}")
for n in r.notes: print("  ", n)

rows = [("point[0].a1", truth["a1"]), ("point[0].a2", truth["a2"]), ("material.shininess", truth["shininess"])]
rows += [(f"material.specular[{c}]", truth["specular"]) for c in "rgb"]
rows += [(f"{v}.camera.white_balance[{c}]", x) for v, wb in truth["white_balance"].items() for c, x in zip("rgb", wb)]
idx = {n: i for i, n in enumerate(r.names)}
z = []
print(f"{'parameter':34s} {'true':>8s} {'fitted':>8s} {'s.e.':>8s} {'|z|':>5s}")
for n, t in rows:
    i = idx[n]; z.append(abs(r.values[i] - t) / r.stderr[i])
    print(f"{n:34s} {t:8.4g} {r.values[i]:8.4g} {r.stderr[i]:8.2g} {z[-1]:5.2f}")
assert r.successful, r.result
assert max(z) < 4.5, max(z)   # 21 scalars: every one within a few standard errors""",
    ),
    (
        "md",
        """\
## The albedo on the mesh

The fitted colours next to the true ones, seen from a view no photograph was taken from. Below
them is the error of each vertex in standard errors. Grey marks the vertices the images cannot
determine, because no view shows them or the light never reaches them where a view does.""",
    ),
    (
        "code",
        """\
nv = views[0].mesh.vertices.shape[0]
alb = r.values[:3 * nv].reshape(nv, 3); se = r.stderr[:3 * nv].reshape(nv, 3)
true_alb = np.asarray(truth["albedo"])
det = np.isfinite(se).all(axis=1)
zv = np.where(det, np.max(np.abs(alb - true_alb) / np.where(det[:, None], se, 1), axis=1), np.nan)
print(f"{det.sum()} of {nv} vertices determined; albedo |error| median {np.median(np.abs(alb - true_alb)[det]):.3f}; "
      f"{np.mean(zv[det] < 3):.0%} within 3 s.e. (worst channel per vertex)")
cmap = plt.get_cmap("magma")
zcol = np.where(det[:, None], cmap(np.clip(np.nan_to_num(zv) / 4, 0, 1))[:, :3], 0.5)
c = views[0].camera
look = ds.Camera(eye=[3.0, 4.0, 6.0], target=[0.0, 2.0, 0.0], up=[0, 1, 0], fov_y=40.0, near=0.5, far=50.0,
                 width=c.width, height=c.height)
flat_light = opts.with_keys(specular="none")
def on_mesh(colors):
    s = eqx.tree_at(lambda x: (x.camera, x.mesh.colors, x.ambient_light), views[0],
                    (look, jnp.asarray(colors, views[0].mesh.vertices.dtype), jnp.ones(3)))
    s = eqx.tree_at(lambda x: x.point.color, s, jnp.zeros_like(s.point.color))
    s = eqx.tree_at(lambda x: x.material.ambient, s, jnp.zeros(3))
    return render(s, flat_light.with_keys(vertex_color="ambient_and_diffuse"))
show([on_mesh(true_alb), on_mesh(alb), on_mesh(zcol)], ["true albedo", "fitted albedo", "|error| / s.e. (0 → 4), grey: undetermined"], cols=3, scale=3.2)
assert np.mean(zv[det] < 3) > 0.9""",
    ),
    (
        "md",
        """\
## The same photographs, read as linear

This is what happens when a file's encoding is not declared and the code values are taken as
light. The fit cannot explain the images and says so. Every parameter it reports is biased, and
the specular term is explained away.""",
    ),
    (
        "code",
        """\
t0 = time.perf_counter()
wrong = fit(views[0], opts, Observations(codes, encoding="linear", **kw), free)
print(f"{wrong.result or 'successful'} ({time.perf_counter() - t0:.1f} s)")
names = [n for n, _ in rows]
rel = lambda res: [(res.values[idx[n]] - t) / t for n, t in rows]
x = np.arange(len(names))
fig, ax = plt.subplots(figsize=(11, 3.2))
ax.bar(x - 0.2, rel(r), 0.4, label=f"sRGB declared: residual {r.residual.noise_ratio:.2f}× the noise")
ax.bar(x + 0.2, rel(wrong), 0.4, label=f"read as linear: residual {wrong.residual.noise_ratio:.1f}× the noise")
ax.axhline(0, color="k", lw=0.5); ax.set_xticks(x, [n.replace("camera.white_balance", "wb") for n in names], rotation=60, fontsize=7)
ax.set_ylabel("relative error"); ax.set_yscale("symlog", linthresh=0.1); ax.legend(fontsize=8); plt.tight_layout(); plt.show()
assert not wrong.successful and wrong.residual.noise_ratio > 3""",
    ),
]


TEXTURES = [
    (
        "md",
        """\
# 7 · Textured objects: maps rendered, fitted and exported

A material field can vary over the surface as an image map (docs/model.md §15): `diffuse_map`,
`specular_map`, `ambient_map`, `emission_map`, `shininess_map` and `opacity_map` each multiply
their field at the texture coordinates of each pixel (the MTL convention, OpenGL's
`GL_MODULATE`). This notebook loads a textured object as authored (an OBJ with `vt`, its MTL and
the JPEG it names), looks at the filters, then fits a diffuse map from four 8-bit views and shows
which texels the views determine.""",
    ),
    (
        "code",
        SETUP
        + """
import dataclasses
from pathlib import Path
import fitting
from fitting import Observations, fit

ROOT = Path(fitting.__file__).resolve().parent.parent
obj = ROOT / "tests" / "data" / "meshes" / "fuze.obj"
authored = ds.load_mesh(obj)       # texture coordinates kept, vertices split at the UV seams
bottle = ds.load_material(obj)     # Kd, map_Kd "fuze uv.jpg", decoded from sRGB to linear
print(authored.vertices.shape[0], "vertices,", authored.faces.shape[0], "faces; map", bottle.diffuse_map.texels.shape)

v = np.asarray(authored.vertices)
mesh = ds.Mesh((v - (v.min(0) + v.max(0)) / 2) * (2 / np.ptp(v, axis=0).max()), authored.faces,
               normals=authored.normals, uv=authored.uv)   # centred, 2 units long (along z)
SIZE = 64 if SMALL else 160
base, opts = scene_with(SIZE, render={"shading": "phong", "fog": "none"}, fog=None)

def view(azimuth, material, size=SIZE, elevation=20.0):
    a, e = np.deg2rad(azimuth), np.deg2rad(elevation)
    eye = 3.0 * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    cam = dataclasses.replace(base.camera, eye=jnp.asarray(eye), target=jnp.zeros(3), up=jnp.asarray([0.0, 0.0, 1.0]),
                              width=size, height=size)
    return dataclasses.replace(base, mesh=mesh, camera=cam, material=material)""",
    ),
    (
        "md",
        """\
## Filters

`filter="bilinear"` is `GL_LINEAR`; `"trilinear"` (the default) adds a mipmap pyramid for
minification, the level of detail from the exact derivatives of the perspective-correct
coordinates. Far away (a 32² image of a 256² map) bilinear sampling aliases and trilinear
sampling averages; up close they agree.""",
    ),
    (
        "code",
        """\
mat = dataclasses.replace(base.material, diffuse=jnp.ones(3), specular=jnp.full(3, 0.2), diffuse_map=bottle.diffuse_map)
bil = dataclasses.replace(mat, diffuse_map=dataclasses.replace(bottle.diffuse_map, filter="bilinear"))
images, titles = [], []
for size in (32, SIZE):
    for m, name in ((bil, "bilinear"), (mat, "trilinear")):
        images.append(render(view(30, m, size), opts)); titles.append(f"{size}², {name}")
show(images, titles, cols=4, scale=2.6)
far = [np.asarray(images[0]), np.asarray(images[1])]
print(f"32²: bilinear and trilinear differ by up to {np.abs(far[0] - far[1]).max():.2f}")""",
    ),
    (
        "md",
        """\
## Fitting a diffuse map from four views

The truth is the bottle's map averaged to `RES`² texels; four 8-bit views (σ = 2 codes of
noise) from around the bottle are the data. The fit starts from a grey map and a wrong `k_s`:
the map is a sparse linear block of `RES² × 3` scalars (the per-vertex albedo's solver), `k_s`
a nonlinear parameter beside it (docs/model.md §15, "Fitting a map"). Texels that no pixel
samples, or only through averages with their neighbours, are reported as undetermined (infinite
standard error) and left at their start. The fitted map's saturated texels lie on the edges of
the seen regions, where few pixels sample a texel and the noise pushes its estimate onto a bound.
On these views slightly fewer determined texels lie within 3 s.e. than Gaussian noise would put
there (about 98 % against 99.73 %; the texels outside are mostly dark ones estimated too bright,
not on a bound): why is an open question.""",
    ),
    (
        "code",
        """\
RES = 16 if SMALL else 32
full = np.asarray(bottle.diffuse_map.texels)
f = full.shape[0] // RES
truth = full.reshape(RES, f, RES, f, 3).mean((1, 3))
true_mat = dataclasses.replace(mat, diffuse_map=ds.Texture(truth, filter="bilinear"))
start_mat = dataclasses.replace(true_mat, specular=jnp.full(3, 0.4), diffuse_map=ds.Texture(np.full((RES, RES, 3), 0.5), filter="bilinear"))
rng = np.random.default_rng(0)
azimuths = (0, 90, 180, 270)
clean = [np.asarray(render(view(a, true_mat), opts)) for a in azimuths]
photos = [np.round(np.clip(c + rng.normal(0, 2 / 255, c.shape), 0, 1) * 255) / 255 for c in clean]
starts = [view(a, start_mat) for a in azimuths]
r = fit(starts[0], opts, Observations(photos, views=starts, saturation=1.0, quantum=1 / 255),
        ["material.diffuse_map", "material.specular"], intervals=False)
n = truth.size
x, se = r.values[:n].reshape(truth.shape), r.stderr[:n].reshape(truth.shape)
det = np.isfinite(se)
z = np.abs(x - truth)[det] / se[det]
print(f"successful: {r.successful}; {r.steps} steps, solve {r.solve_s:.1f} s, compile {r.compile_s:.1f} s")
print(f"determined texel scalars: {det.mean():.1%}; within 3 s.e. of the truth: {np.mean(z <= 3):.2%} "
      f"(Gaussian: 99.73 %); k_s {r.values[n]:.4f} ± {r.stderr[n]:.4f} (truth 0.2)")
show(photos, [f"view {i} (8-bit)" for i in range(4)], cols=4)
shown = np.where(det, x, np.nan)
fig, axes = plt.subplots(1, 4, figsize=(12, 3.2))
for ax, img, t in zip(axes, [truth, np.clip(x, 0, 1), shown, det.all(-1)],
                      ["truth", "fitted (every texel)", "fitted, determined only", "determined (white)"]):
    ax.imshow(np.clip(np.nan_to_num(img, nan=0.0), 0, 1), cmap="gray", interpolation="nearest"); ax.set_title(t, fontsize=9); ax.axis("off")
plt.tight_layout(); plt.show()
assert r.successful and 0.2 < det.mean() < 1.0 and np.mean(z <= 3) >= 0.98
assert abs(r.values[n] - 0.2) <= 4 * r.stderr[n]""",
    ),
    (
        "md",
        """\
## Export

`ds.save_material` (which `diffshade fit` uses) writes the fitted material as an MTL; each fitted map goes beside it as a 16-bit
PNG (sRGB for colour), named by a `map_Kd` line, so the result opens in any viewer and loads back
with `ds.load_material`.""",
    ),
    (
        "code",
        """\
import tempfile
out = Path(tempfile.mkdtemp())
pset = fitting.ParamSet(["material.diffuse_map", "material.specular"], starts[0])
scene_fit = pset.apply(starts[0], jnp.asarray(r.values, starts[0].mesh.vertices.dtype))
ds.save_material(out / "material.mtl", scene_fit, opts, header="notebook 7")
print((out / "material.mtl").read_text())
back = ds.load_material(out / "material.mtl")
err = np.abs(np.asarray(back.diffuse_map.texels) - np.clip(x, 0, 1)).max()
print(f"loaded back: largest difference {err:.1e} (16-bit sRGB codes)")
assert err < 1e-4""",
    ),
]

NOTEBOOKS = {
    "01_tour_of_terms.ipynb": TOUR,
    "02_fitting.ipynb": FITTING,
    "03_speed_vs_error.ipynb": SPEED,
    "04_transparency_and_shadows.ipynb": GLASS,
    "05_mirrors_and_glass.ipynb": MIRRORS,
    "06_photographs.ipynb": PHOTOS,
    "07_textures.ipynb": TEXTURES,
}


def build(name: str, cells) -> nbformat.NotebookNode:
    nb = nbformat.v4.new_notebook()
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    nb.cells = [
        nbformat.v4.new_markdown_cell(src) if kind == "md" else nbformat.v4.new_code_cell(src) for kind, src in cells
    ]
    return nb


def execute(nb, cwd: Path, timeout: int = 1800):
    from nbclient import NotebookClient

    NotebookClient(nb, timeout=timeout, kernel_name="python3", resources={"metadata": {"path": str(cwd)}}).execute()
    return nb


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--no-run", action="store_true")
    ap.add_argument("names", nargs="*", help="notebooks to build (default: all)")
    args = ap.parse_args()
    for name, cells in NOTEBOOKS.items():
        if args.names and name not in args.names:
            continue
        nb = build(name, cells)
        if not args.no_run:
            os.environ.pop("DIFFSHADE_NOTEBOOK_SMALL", None)
            execute(nb, HERE)
        nbformat.write(nb, HERE / name)
        print("wrote", HERE / name)


if __name__ == "__main__":
    main()
