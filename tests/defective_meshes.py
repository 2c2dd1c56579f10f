"""Random meshes with the defects scanned and hand-made meshes have, for the exactness tests and
``benchmarks/bench_exactness.py``: duplicate faces (either winding, over the same or coincident
vertices), degenerate faces (a repeated index, collinear or coincident corners), fins (two
opposite faces over the same three vertices: their normals cancel at every corner), holes through
which back faces show, vertices split along a seam, unreferenced vertices; and a random scene
(shading, lights, fog, camera distance) to render them in.

Each draw is a function of its seed alone (``numpy.random.default_rng(seed)``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import trimesh

import diffshade as ds
from fitting import Observations
from fitting._problem import Problem

_jit_render = jax.jit(ds.render, static_argnames="opts")

DEFECTS = ("holes", "duplicates", "opposite", "fins", "degenerate", "split", "soup", "unreferenced")


def _rotation(rng):
    q = rng.normal(size=4)
    return trimesh.transformations.quaternion_matrix(q / np.linalg.norm(q))[:3, :3]


def _base(rng):
    kind = str(rng.choice(["icosphere", "torus", "bowl", "blob"]))
    if kind == "torus":
        t = trimesh.creation.torus(1.0, float(rng.uniform(0.25, 0.5)), major_sections=24, minor_sections=12)
        v, f = np.asarray(t.vertices) / 1.4, np.asarray(t.faces)
    else:
        t = trimesh.creation.icosphere(2)
        v, f = np.asarray(t.vertices), np.asarray(t.faces)
        if kind == "blob":
            v = v * (1.0 + 0.15 * np.sin(3 * v[:, :1] + 2 * v[:, 1:2]) * np.cos(4 * v[:, 2:]))
        if kind == "bowl":  # an open hemisphere: its inside shows
            f = f[(v[f][:, :, 2] < 0.2).all(axis=1)]
    return kind, v.astype(np.float64), f.astype(np.int64)


def defective_mesh(rng, defects=None) -> tuple[np.ndarray, np.ndarray, str]:
    """``(vertices, faces, name)``: a base shape (icosphere, torus, open bowl, blob), randomly
    rotated, scaled and moved, with ``defects`` (default: each of :data:`DEFECTS` with
    probability 1/2, at least one), the faces in random order."""
    kind, v, f = _base(rng)
    if defects is None:
        defects = [d for d in DEFECTS if rng.uniform() < 0.5] or [str(rng.choice(DEFECTS))]
    v = v @ _rotation(rng).T * rng.uniform(0.6, 1.3) + rng.uniform(-0.2, 0.2, 3)
    verts, extra_f = list(v), []

    def new_vertex(p):
        verts.append(np.asarray(p, np.float64))
        return len(verts) - 1

    def some(frac):
        return f[rng.choice(len(f), max(1, int(frac * len(f))), replace=False)]

    if "holes" in defects:  # faces within a random cap removed
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        c = v[f].mean(1) - v.mean(0)
        cosang = c @ axis / np.maximum(np.linalg.norm(c, axis=1), 1e-12)
        f = f[cosang < rng.uniform(0.7, 0.95)]
    if "duplicates" in defects:  # the same winding, the corners rotated or not
        d = some(rng.uniform(0.05, 0.2))
        extra_f += list(np.roll(d, int(rng.integers(3)), axis=1))
    if "opposite" in defects:  # the same corners, the other winding
        d = some(rng.uniform(0.05, 0.2))
        extra_f += list(d[:, ::-1] if rng.uniform() < 0.5 else d[:, [1, 0, 2]])
    if "fins" in defects:  # a new vertex off an edge, two opposite faces over it
        for a, b, _ in some(0.02):
            p = (verts[a] + verts[b]) / 2 + rng.normal(size=3) * 0.05
            k = new_vertex(p)
            extra_f += [[a, b, k], [b, a, k]]
    if "degenerate" in defects:
        for a, b, _ in some(0.03):
            r = rng.uniform()
            if r < 1 / 3:
                extra_f.append([a, a, b])  # a repeated index
            elif r < 2 / 3:
                extra_f.append([a, b, new_vertex((verts[a] + verts[b]) / 2)])  # collinear corners
            else:
                extra_f.append([a, b, new_vertex(verts[b])])  # two coincident corners
    if "split" in defects:  # some faces' vertices split from the rest (seams: hard edges)
        rows = rng.choice(len(f), max(1, len(f) // 7), replace=False)
        copy = np.arange(len(verts) + len(np.unique(f[rows])))
        for i in np.unique(f[rows]):
            copy[i] = new_vertex(verts[i])
        f = f.copy()
        f[rows] = copy[f[rows]]
    if "soup" in defects:  # duplicates over new, coincident vertices, either winding
        for tri in some(0.05):
            ks = [new_vertex(verts[i]) for i in tri]
            extra_f.append(ks if rng.uniform() < 0.5 else ks[::-1])
    if "unreferenced" in defects:
        for _ in range(int(rng.integers(1, 20))):
            new_vertex(rng.normal(size=3) * 3)
    v = np.stack(verts)
    if extra_f:
        f = np.concatenate([f, np.asarray(extra_f, np.int64).reshape(-1, 3)])
    f = f[rng.permutation(len(f))]
    return v, f.astype(np.int32), f"{kind}+{'+'.join(defects)}"


def random_scene_dict(rng, size: int = 48) -> dict:
    """A scene file's dict (:func:`diffshade.scene_from_dict`) with a random look: shading,
    specular model, flat source, one to three lights of mixed kinds, fog, the camera's distance;
    its ``[mesh]`` is a placeholder to replace."""
    shading = str(rng.choice(["flat", "gouraud", "phong"]))
    fog = str(rng.choice(["none", "exp", "linear"]))
    render = {"shading": shading, "specular": str(rng.choice(["phong", "blinn"])), "fog": fog}
    if shading == "flat":
        render["flat_source"] = str(rng.choice(["centroid", "provoking"]))

    def pos():
        d = rng.normal(size=3)
        d[2] = abs(d[2]) + 0.3
        return list(2.5 * d / np.linalg.norm(d))

    lights = [
        {"type": "point", "color": list(rng.uniform(0.6, 1.2, 3)), "position": pos(), "attenuation": [1.0, 0.1, 0.02]}
    ]
    for _ in range(int(rng.integers(0, 3))):
        if rng.uniform() < 0.5:
            lights.append({"type": "directional", "color": list(rng.uniform(0.2, 0.5, 3)), "direction": pos()})
        else:
            p = pos()
            lights.append(
                {
                    "type": "spot",
                    "color": [1.0, 1.0, 1.0],
                    "position": p,
                    "axis": list(-np.asarray(p)),
                    "cutoff": 40.0,
                    "exponent": 4.0,
                }
            )
    d = {
        "mesh": {"icosphere": 1},
        "camera": {
            "eye": list(_rotation(rng)[2] * rng.uniform(2.2, 5.0)),
            "target": [0.0, 0.0, 0.0],
            "up": [0.0, 1.0, 0.0],
            "fov_y": 45.0,
            "near": 0.3,
            "far": 12.0,
            "width": size,
            "height": size,
        },
        "render": render,
        "material": {
            "ambient": list(rng.uniform(0.05, 0.3, 3)),
            "diffuse": list(rng.uniform(0.2, 0.9, 3)),
            "specular": float(rng.uniform(0.1, 0.8)),
            "shininess": float(np.exp(rng.uniform(np.log(5), np.log(100)))),
        },
        "light": lights,
        "ambient_light": [0.3, 0.3, 0.3],
    }
    if fog != "none":
        d["fog"] = {"color": list(rng.uniform(0.3, 0.8, 3)), "density": 0.1, "start": 0.0, "end": 9.0}
    return d


def fixed_scene_dict(rng, shading: str, size: int = 32) -> dict:
    """:func:`random_scene_dict` with a fixed structure (one point and one directional light, exp
    fog, ``shading``): random values only, so that cases share their compiled programs."""
    d = random_scene_dict(rng, size)
    d["render"] = {"shading": shading, "specular": "phong", "fog": "exp"}
    d["light"] = [d["light"][0], {"type": "directional", "color": [0.3, 0.3, 0.35], "direction": [1.0, -0.5, -1.0]}]
    d["fog"] = {"color": list(rng.uniform(0.3, 0.8, 3)), "density": float(rng.uniform(0.05, 0.2))}
    return d


def padded(mesh, vertices: int, faces: int):
    """``mesh`` (a :class:`diffshade.Mesh`) padded to ``vertices`` and ``faces`` (when below)
    with unreferenced copies of vertex 0 (and of its normal) and faces ``(0, 0, 0)``
    (degenerate: they draw nothing), so that meshes of one size share compiled programs."""
    v, f = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces)
    n = None if mesh.normals is None else np.asarray(mesh.normals, np.float64)
    extra = max(0, vertices - len(v))
    v = np.concatenate([v, np.repeat(v[:1], extra, 0)])
    n = None if n is None else np.concatenate([n, np.repeat(n[:1], extra, 0)])
    f = np.concatenate([f, np.zeros((max(0, faces - len(f)), 3), f.dtype)])
    return ds.Mesh(vertices=v, faces=f, normals=n)


def placed(mesh, rng):
    """The mesh as a user places it: centred on its bounding box, scaled to 1-2.5 units and
    rotated (its file normals, if it has them, rotated with it)."""
    v = np.asarray(mesh.vertices, np.float64)
    lo, hi = v.min(0), v.max(0)
    R = _rotation(rng)
    v = (v - (lo + hi) / 2) / (hi - lo).max() * rng.uniform(1.0, 2.5) @ R.T
    n = None if mesh.normals is None else np.asarray(mesh.normals, np.float64) @ R.T
    return ds.Mesh(vertices=v, faces=np.asarray(mesh.faces), normals=n)


def model_against_render(scene, opts, free=("material.diffuse", "material.specular", "material.shininess")):
    """The fit's forward model at the truth against :func:`diffshade.render` (eager) and
    ``jax.jit(diffshade.render)`` of the same scene: ``(fit, jit, jvp)``, each ``[H, W]`` the
    largest absolute difference over the channels, ``jvp`` the primal of the fit's forward-mode
    pass (the shading kernel's partials where it serves); and the problem (its options say
    whether the fit lights one side)."""
    img = np.asarray(ds.render(scene, opts))
    jitted = np.asarray(_jit_render(scene, opts))
    prob = Problem.build(scene, opts, Observations(img), list(free))
    theta = jnp.asarray(prob.pset.theta_of(scene))
    data = prob.device_data()
    model = prob.full_images(np.asarray(prob.images(theta, data)))[0]
    primal, _ = jax.jit(prob.images_jvp)(theta, jnp.eye(len(theta), dtype=theta.dtype)[:1], data)
    jvp = prob.full_images(np.asarray(primal))[0]
    return tuple(np.abs(a - img).max(-1) for a in (model, jitted, jvp)) + (prob,)
