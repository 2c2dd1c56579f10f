"""Make a multi-view data set of "photographs" of a per-vertex-coloured object, as a camera would
record them, and the files `diffshade fit` reads.

    python examples/photographs/make_dataset.py out/photos

writes into that folder:

- `object.ply`: the mesh with grey vertex colours (the fit's start), and `truth.ply` with the
  true colours (an albedo pattern over the surface);
- `setup_a.toml`, `setup_b.toml`: the scene under two lighting set-ups (the point light in two
  places: with one set-up, a diffuse surface's albedo and the light's fall-off cannot be told
  apart); the start values of the material and the attenuation;
- `view0.png` … `view5.png`: 8-bit sRGB photographs (declared by their sRGB chunk), each with its
  own exposure and white balance, and sensor noise of 2 codes; view 0 is the reference (gains 1);
- `view0.json` …: each view's OpenCV calibration (K, R, t, image size);
- `truth.json`: every true value, for `check.py`.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import trimesh

import diffshade as ds
from diffshade import color as _color

HERE = Path(__file__).resolve().parent
MESH = HERE.parent.parent / "tests" / "data" / "meshes" / "rabbit.obj"
SIZE = 160
NOISE = 2 / 255  # in code values
LIGHTS = {"a": [3.0, 5.0, 4.0], "b": [-4.0, 3.0, 2.0]}
# (eye, lighting set-up, exposure, white balance)
VIEWS = [
    ((0.0, 2.2, 7.0), "a", 1.0, (1.0, 1.0, 1.0)),
    ((5.0, 3.0, 4.5), "a", 1.25, (1.08, 1.0, 0.86)),
    ((-5.0, 3.5, 4.0), "a", 0.85, (0.92, 1.0, 1.12)),
    ((0.5, 4.0, -6.5), "b", 1.1, (1.0, 1.0, 0.95)),
    ((-6.0, 1.5, -2.5), "b", 0.9, (1.05, 1.0, 0.9)),
    ((6.0, 2.5, -3.0), "b", 1.2, (0.95, 1.0, 1.05)),
]
TRUE = {"specular": 0.3, "shininess": 20.0, "a1": 0.15, "a2": 0.05}
START = {"specular": 0.5, "shininess": 40.0, "a1": 0.4, "a2": 0.1}

SCENE = """\
ambient_light = [0.2, 0.2, 0.2]
[mesh]
path = "object.ply"
[camera]
eye = [0, 2.2, 7]
target = [0, 2.2, 0]
width = {size}
height = {size}
[render]
shading = "phong"
vertex_color = "diffuse"
[material]
ambient = [0.2, 0.2, 0.2]
specular = {specular}
shininess = {shininess}
[[light]]
type = "point"
color = [2.5, 2.5, 2.5]
position = {position}
attenuation = [1.0, {a1}, {a2}]
"""


def albedo(v: np.ndarray) -> np.ndarray:
    """A smooth pattern of colours over the surface (linear RGB, in [0.08, 0.9])."""
    c = np.stack(
        [
            0.5 + 0.3 * np.sin(1.7 * v[:, 0] + 0.5 * v[:, 1]),
            0.45 + 0.3 * np.sin(1.3 * v[:, 1] - 0.8 * v[:, 2]),
            0.4 + 0.3 * np.cos(1.1 * v[:, 2] + 0.6 * v[:, 0]),
        ],
        -1,
    )
    return np.clip(c, 0.08, 0.9)


def look_at(eye, target=(0.0, 2.2, 0.0)):
    """OpenCV pose (R, t) of a camera at ``eye`` looking at ``target``, image y down."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    R = np.stack([right, np.cross(fwd, right), fwd])
    return R, -R @ eye


def main(out: Path) -> None:
    jax.config.update("jax_enable_x64", True)
    out.mkdir(parents=True, exist_ok=True)
    mesh = ds.load_mesh(MESH, "merged")
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    truth = albedo(v)
    grey = np.full((len(v), 4), [128, 128, 128, 255], np.uint8)
    trimesh.Trimesh(v, f, vertex_colors=grey, process=False).export(out / "object.ply")
    codes = np.round(np.asarray(_color.encode(truth, "srgb")) * 255).astype(np.uint8)
    trimesh.Trimesh(v, f, vertex_colors=np.c_[codes, np.full(len(v), 255, np.uint8)], process=False).export(
        out / "truth.ply"
    )
    for name, pos in LIGHTS.items():
        (out / f"setup_{name}.toml").write_text(SCENE.format(size=SIZE, position=pos, **START))
    f_px = SIZE / 2 / np.tan(np.deg2rad(20.0))
    K = np.array([[f_px, 0, (SIZE - 1) / 2 + 3.0], [0, f_px, (SIZE - 1) / 2 - 2.0], [0, 0, 1]])
    rng = np.random.default_rng(2026)
    render = jax.jit(ds.render, static_argnames="opts")
    for i, (eye, setup, exposure, wb) in enumerate(VIEWS):
        (out / "true.toml").write_text(SCENE.format(size=SIZE, position=LIGHTS[setup], **TRUE))
        scene, opts = ds.load_scene(out / "true.toml")
        R, t = look_at(eye)
        cam = ds.OpenCVCamera.from_opencv(
            K, R=R, t=t, width=SIZE, height=SIZE, near=0.5, far=50.0, exposure=exposure, white_balance=wb
        )
        scene = eqx.tree_at(lambda s: (s.camera, s.mesh.colors), scene, (cam, jnp.asarray(truth)))
        img = np.asarray(render(scene, opts), np.float64)
        # the sensor's noise first, then the clip to the file's range: a highlight above 1 stays
        # clipped (censored in the fit) unless the noise takes it below the top code
        coded = np.asarray(_color.encode(img, "srgb")) + rng.normal(0, NOISE, img.shape)
        ds.write_image(out / f"view{i}.png", _color.decode(np.clip(coded, 0, 1), "srgb"), "srgb", bits=8)
        (out / f"view{i}.json").write_text(
            json.dumps(
                {
                    "K": K.tolist(),
                    "R": R.tolist(),
                    "t": t.tolist(),
                    "width": SIZE,
                    "height": SIZE,
                    "near": 0.5,
                    "far": 50.0,
                },
                indent=1,
            )
        )
    (out / "true.toml").unlink()
    (out / "truth.json").write_text(
        json.dumps(
            {
                "albedo": truth.tolist(),
                **TRUE,
                "white_balance": {
                    f"view[{i}]": (e * np.asarray(wb)).tolist() for i, (_, _, e, wb) in enumerate(VIEWS) if i
                },
                "setups": [s for _, s, _, _ in VIEWS],
            },
            indent=1,
        )
    )
    print(f"wrote {len(VIEWS)} photographs of {len(v)}-vertex {MESH.name} at {SIZE}x{SIZE} into {out}")


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "out/photos"))
