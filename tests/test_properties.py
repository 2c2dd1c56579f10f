"""Property-based tests of every boundary (hypothesis): whatever a user passes, the answer is a
result or the boundary's own error naming the problem — never another exception, a traceback
or a file written. Scene files (valid ones load and render finite), fit options (accepted exactly
when their domain admits them), command-line numbers, meshes and images.

The example counts are kept small for the 2-core suite; ``HYPOTHESIS_PROFILE=soak`` runs 20x more."""

from __future__ import annotations

import copy
import functools
import io
import math
import os
import tempfile
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

import diffshade as ds  # noqa: E402
from fitting import FitError, Observations, Optimistix, VarPro  # noqa: E402
from fitting._domains import CLI, FIT  # noqa: E402

settings.register_profile(
    "suite", max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True
)
settings.register_profile("soak", max_examples=800, deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "suite"))

BASE = {
    "mesh": {"icosphere": 1},
    "camera": {"eye": [0, 0.5, 3], "width": 12, "height": 12, "near": 0.1, "far": 20},
    "render": {"shading": "phong", "specular": "blinn", "fog": "linear"},
    "material": {"ambient": 0.1, "diffuse": [0.7, 0.3, 0.2], "specular": 0.4, "shininess": 30},
    "light": [
        {"type": "point", "position": [2, 2, 3], "attenuation": [1, 0.1, 0.01]},
        {"type": "spot", "position": [0, 2, 2], "axis": [0, -1, -1], "cutoff": 30, "exponent": 4},
        {"type": "directional", "direction": [0, -1, -1]},
    ],
    "fog": {"color": [0.5, 0.5, 0.6], "start": 1, "end": 6},
}


def _paths(d, prefix=()):
    """Every (path, value) of a nested scene dictionary (lists of tables by index)."""
    for k, v in d.items() if isinstance(d, dict) else enumerate(d):
        p = (*prefix, k)
        yield p, v
        if isinstance(v, dict) or (isinstance(v, list) and v and isinstance(v[0], dict)):
            yield from _paths(v, p)


PATHS = [p for p, _ in _paths(BASE)]
NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 1e-300, -1e-300, 1e300, -1.0, 0.5, 2.0, 90.0, 180.0]),
    st.integers(-(2**40), 2**40),
)
BAD_VALUES = st.one_of(
    NUMBERS, st.text(max_size=5), st.booleans(), st.lists(NUMBERS, max_size=4), st.just({}), st.just([[1, 2, 3]])
)


@st.composite
def scene_dicts(draw):
    """The base scene with one to three fields deleted, replaced or added."""
    d = copy.deepcopy(BASE)
    for _ in range(draw(st.integers(1, 3))):
        path = draw(st.sampled_from(PATHS))
        parent = d
        try:
            for k in path[:-1]:
                parent = parent[k]
            op = draw(st.sampled_from(["delete", "replace", "replace", "unknown"]))
            if op == "delete":
                del parent[path[-1]]
            elif op == "replace":
                parent[path[-1]] = draw(BAD_VALUES)
            elif isinstance(parent, dict):
                parent["bogus_" + str(path[-1])] = draw(BAD_VALUES)
        except (KeyError, IndexError, TypeError):
            pass  # an earlier change removed or replaced the parent
    return d


@functools.cache
def _render(opts):
    return jax.jit(lambda s: ds.render(s, opts))


@given(scene_dicts())
def test_scene_dictionaries_load_or_name_the_field(d):
    try:
        scene, opts = ds.scene_from_dict(d)
    except ds.SceneError as exc:
        assert str(exc).strip() and "Traceback" not in str(exc)
        return
    img = _render(opts)(scene)
    assert bool(np.isfinite(np.asarray(img)).all()), d


@given(st.integers(0, 400), st.sampled_from(["", "\x00", "[", "= 1", "]]"]))
def test_truncated_scene_files_are_scene_errors(cut, tail):
    text = "\n".join(
        [
            "[mesh]",
            "icosphere = 1",
            "[camera]",
            "eye = [0, 0, 3]",
            "width = 8",
            "height = 8",
            "[material]",
            "diffuse = [0.5, 0.5, 0.5]",
            "[[light]]",
            'type = "point"',
            "position = [1, 1, 2]",
        ]
    )
    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / "s.toml"
        p.write_text(text[:cut] + tail)
        try:
            ds.load_scene(p)
        except ds.SceneError as exc:
            assert str(p) in str(exc)


OPTION_VALUES = st.one_of(
    st.none(),
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-5, 10**6),
    st.sampled_from([True, "3", 1.5, 0, -0.0, 1e-320]),
)


@given(st.sampled_from(["noise", "saturation", "quantum", "margin"]), OPTION_VALUES)
def test_observation_options_are_accepted_exactly_in_their_domain(name, value):
    img = np.zeros((4, 4, 3))
    try:
        Observations(img, **{name: value})
        ok = True
    except FitError as exc:
        ok = False
        assert name in str(exc)
    assert ok == FIT[name].admits(value), (name, value)


@given(
    st.sampled_from(["starts", "restarts", "max_steps", "polish_steps", "visibility_passes", "rtol", "atol"]),
    OPTION_VALUES,
    st.sampled_from([VarPro, Optimistix]),
)
def test_strategy_options_are_accepted_exactly_in_their_domain(name, value, kind):
    if name == "atol" and kind is VarPro:
        kind = Optimistix
    try:
        kind(**{name: value})
        ok = True
    except FitError as exc:
        ok = False
        assert f"{kind.__name__}.{name}" in str(exc)
    assert ok == FIT[name].admits(value), (name, value)


@given(
    st.sampled_from([o for o in CLI if o not in ("--size", "--seed")]),
    st.one_of(st.text(max_size=8), st.floats().map(repr), st.integers(-(10**6), 10**6).map(str)),
)
@settings(suppress_health_check=[HealthCheck.function_scoped_fixture])
def test_command_line_numbers_are_checked_before_anything_is_read_or_written(option, text):
    from fitting.cli import EXIT_INPUT, main

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out"
        err = io.StringIO()
        argv = ["--no-cache", "fit", str(Path(tmp) / "missing.toml"), "t.png", "-p", "material.diffuse"]
        with redirect_stderr(err), redirect_stdout(io.StringIO()):
            rc = main([*argv, f"{option}={text}", "-o", str(out)])  # "=": argparse takes "-1e3" as the value
        assert rc == EXIT_INPUT and not out.exists()
        msg = err.getvalue()
        attr, dom = CLI[option]
        valid = _parses(text, int if dom.kind == "int" else float) and dom.admits(
            (int if dom.kind == "int" else float)(text)
        )
        # a valid number gets as far as the missing scene file; any other names the option
        assert ("scene file not found" in msg) if valid else (option in msg), (option, text, msg)
        assert "Traceback" not in msg


def _parses(text, kind):
    try:
        kind(text)
        return True
    except ValueError:
        return False


FINITE = st.floats(-1e3, 1e3)
COORDS = st.one_of(FINITE, FINITE, FINITE, st.sampled_from([0.0, 1e38, 1e-38]))


@st.composite
def meshes(draw):
    """Up to 10 vertices (huge, tiny, coincident; now and then one NaN or infinite) and up to 12 faces whose
    indices are mostly in range (repeats make degenerate, duplicate and non-manifold triangles)."""
    least = draw(st.sampled_from([0, 1, 1, 1]))  # now and then no vertices or no faces
    verts = draw(st.lists(st.tuples(COORDS, COORDS, COORDS), min_size=3 * least, max_size=10))
    n = len(verts)
    if n and draw(st.sampled_from([False, False, False, True])):  # one position NaN or infinite
        i, axis = draw(st.integers(0, n - 1)), draw(st.integers(0, 2))
        verts[i] = tuple(
            draw(st.sampled_from([math.nan, math.inf, -math.inf])) if a == axis else x for a, x in enumerate(verts[i])
        )
    index = st.one_of(*[st.integers(0, max(n - 1, 0))] * 4, st.integers(-1, n))
    faces = draw(st.lists(st.tuples(index, index, index), min_size=least, max_size=12))
    return verts, faces


@given(meshes(), st.booleans())
def test_random_meshes_load_or_raise_a_mesh_error(mesh, as_arrays):
    verts, faces = mesh
    v = np.asarray(verts, np.float64).reshape(-1, 3)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    if as_arrays:
        try:
            mesh = ds.mesh_from_arrays(v, f)
        except ds.MeshError:
            return
    else:
        lines = [f"v {a!r} {b!r} {c!r}" for a, b, c in v] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f]
        with tempfile.TemporaryDirectory() as tmp:
            p = Path(tmp) / "m.obj"
            p.write_text("\n".join(lines) + "\n")
            try:
                mesh = ds.load_mesh(p)
            except ds.MeshError as exc:
                assert str(p) in str(exc)
                return
    # what loads is a renderable mesh: finite vertices, faces in range; rendered (degenerate,
    # duplicate, zero-area and non-manifold triangles included) its image and gradient are finite
    assert np.isfinite(np.asarray(mesh.vertices)).all() and len(mesh.faces)
    assert 0 <= int(mesh.faces.min()) and int(mesh.faces.max()) < len(mesh.vertices)
    image, grads = _mesh_program()(*_padded(mesh))
    assert np.isfinite(np.asarray(image)).all() and all(np.isfinite(np.asarray(g)).all() for g in grads)


def _padded(mesh, nv=16, nf=16):
    """The mesh scaled into the view (its shape kept) and padded to one program's sizes: unused
    copies of vertex 0 and degenerate faces (0, 0, 0), themselves hard cases."""
    v, f = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces)
    v = v / max(1e-30, float(np.abs(v).max()))
    v = np.concatenate([v, np.repeat(v[:1], nv - len(v), 0)])
    return v, np.concatenate([f, np.zeros((nf - len(f), 3), f.dtype)])


@functools.cache
def _mesh_program():
    """One program for every random mesh: the image and the gradients of a weighted sum with
    respect to the vertices and the material."""
    import equinox as eqx

    base, opts = ds.scene_from_dict({**BASE, "mesh": {"icosphere": 0}}, "random meshes")

    def run(v, f):
        scene = eqx.tree_at(lambda s: s.mesh, base, ds.Mesh(v, f))

        def loss(v, mat):
            img = ds.render(eqx.tree_at(lambda s: (s.mesh.vertices, s.material), scene, (v, mat)), opts)
            return (img * jnp.linspace(0.5, 1.5, img.size).reshape(img.shape)).sum(), img

        (_, img), grads = jax.value_and_grad(loss, argnums=(0, 1), has_aux=True)(scene.mesh.vertices, scene.material)
        return img, jax.tree.leaves(grads)

    return jax.jit(run)


@given(
    st.integers(1, 20),
    st.integers(1, 20),
    st.sampled_from([None, 1, 2, 3, 4, 5]),
    st.sampled_from([np.uint8, np.uint16, np.float32, np.int32]),
    st.sampled_from(["png", "npy", "truncated", "garbage"]),
)
def test_random_images_load_or_raise_an_input_error(h, w, ch, dtype, kind):
    import skimage.io

    from fitting.cli import InputError, load_target

    rng = np.random.default_rng(h * 100 + w)
    shape = (h, w) if ch is None else (h, w, ch)
    a = (rng.uniform(0, 1, shape) * (255 if dtype == np.uint8 else 65535 if dtype == np.uint16 else 1)).astype(dtype)
    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / f"t.{'npy' if kind == 'npy' else 'png'}"
        if kind == "npy":
            np.save(p, a)
        elif kind == "garbage":
            p.write_bytes(rng.bytes(64))
        else:
            if dtype not in (np.uint8, np.uint16):
                return  # no PNG holds it
            try:
                skimage.io.imsave(p, a, check_contrast=False)
            except (ValueError, TypeError, OSError):
                return  # a pixel type or channel count the PNG writer refuses: nothing to read
            if kind == "truncated":
                p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2])
        try:
            img, sat = load_target(p, (8, 8))
        except InputError as exc:
            assert str(p) in str(exc)
            return
        assert img.shape == (8, 8, 3) and np.isfinite(img).all()


@pytest.mark.slow
def test_a_million_face_mesh_loads_renders_and_differentiates(tmp_path):
    # 1,310,720 faces (every 1,000th degenerate) and 1,000 unused duplicate vertices, from an
    # OBJ of 53 MB: loads, renders and differentiates finite; one NaN vertex among them is named
    import equinox as eqx
    import trimesh

    tm = trimesh.creation.icosphere(subdivisions=8)
    v, f = np.asarray(tm.vertices), np.asarray(tm.faces).copy()
    f[::1000, 2] = f[::1000, 1]
    path = tmp_path / "big.obj"
    trimesh.Trimesh(np.concatenate([v, v[:1000]]), f, process=False).export(path)
    mesh = ds.load_mesh(path)
    assert mesh.faces.shape == (1_310_720, 3)
    scene, opts = ds.scene_from_dict({**BASE, "camera": {**BASE["camera"], "width": 64, "height": 64}}, "big")
    scene = eqx.tree_at(lambda s: s.mesh, scene, mesh)
    loss = lambda s: ds.render(s, opts).sum()  # noqa: E731
    value, grads = eqx.filter_jit(eqx.filter_value_and_grad(loss))(scene)
    assert np.isfinite(float(value)) and float(value) > 0
    assert all(np.isfinite(np.asarray(g)).all() for g in jax.tree.leaves(eqx.filter(grads, eqx.is_inexact_array)))
    v[12_345] = np.nan
    trimesh.Trimesh(v, f, process=False).export(path)
    with pytest.raises(ds.MeshError, match=r"big\.obj.*NaN.*vertex 12345"):
        ds.load_mesh(path)
