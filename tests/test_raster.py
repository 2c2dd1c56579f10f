import dataclasses
import functools
import os
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from conftest import check_grads, compiles, float32, float64, shared_mesh_dir
from reference import brute_force

import diffshade as ds
from diffshade import _native, _raster

BACKENDS = [
    "jax",
    pytest.param(
        "native",
        marks=pytest.mark.skipif(
            not _native.available(),
            reason="native kernel unavailable: no C++ compiler, or JAX's default device is not the CPU",
        ),
    ),
]
TIE = dict(tie_eps=1e-5, depth_eps=1e-5)


def camera(res=64, eye=(0.0, 0.0, 3.0), near=0.1, far=20.0):
    h, w = (res, res) if isinstance(res, int) else res
    return ds.Camera(
        eye=eye, target=[0.0, 0.0, 0.0], up=[0.0, 1.0, 0.0], fov_y=45.0, near=near, far=far, width=w, height=h
    )


@functools.cache
def _vis_fn(res_h, res_w, layers, backend, tile_capacity=None, pair_capacity=None, cull="none"):
    return jax.jit(
        lambda c, f: ds.visibility(c, f, (res_h, res_w), layers, backend, tile_capacity, pair_capacity, cull)
    )


def vis(clip, faces, res, layers=1, backend="jax", **kw):
    h, w = (res, res) if isinstance(res, int) else res
    return np.asarray(
        _vis_fn(h, w, layers, backend, kw.get("tile_capacity"), kw.get("pair_capacity"), kw.get("cull", "none"))(
            jnp.asarray(clip, jnp.float32), jnp.asarray(faces, jnp.int32)
        )
    )


def random_soup(rng, n, spread=1.0, size=0.4):
    centres = rng.uniform(-spread, spread, (n, 1, 3))
    v = (centres + rng.normal(0, size, (n, 3, 3))).reshape(-1, 3)
    return v, np.arange(3 * n).reshape(n, 3)


def assert_matches_reference(ids, clip, faces, res, layers, min_checked=0.9):
    h, w = (res, res) if isinstance(res, int) else res
    ref, amb, ref_depth = brute_force(np.asarray(clip), faces, h, w, layers, **TIE)
    ok = ~amb
    assert ok.mean() >= min_checked, f"too many ambiguous pixels ({1 - ok.mean():.3f})"
    for k in range(layers):
        bad = (ids[k] != ref[k]) & ok
        assert not bad.any(), f"layer {k}: {bad.sum()} pixels differ from the brute-force reference"
    # depths of the differentiable recomputation (float64 here) equal the reference's
    frags = ds.fragments(jnp.asarray(clip, jnp.float64), jnp.asarray(faces), jnp.asarray(ids))
    hit = (ids >= 0) & (ids == ref)
    np.testing.assert_allclose(np.asarray(frags.depth)[hit], ref_depth[hit], rtol=0, atol=1e-9)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("layers", [1, 3])
def test_random_soup_matches_brute_force(backend, layers, rng):
    v, f = random_soup(rng, 60)
    clip = np.asarray(camera(48).world_to_clip(jnp.asarray(v)))
    ids = vis(clip, f, 48, layers, backend)
    assert (ids[0] >= 0).mean() > 0.3
    assert_matches_reference(ids, clip, f, 48, layers)


@pytest.mark.parametrize("backend", BACKENDS)
def test_non_square_image_and_near_plane_crossing(backend, rng):
    # Triangles straddle the near plane and reach behind the eye: clipped exactly per pixel.
    v, f = random_soup(rng, 40, spread=2.5, size=1.5)
    v[:, 2] += 1.5  # many vertices now lie between the near plane and the eye, or behind it
    cam = ds.Camera(eye=[0, 0, 3.0], target=[0, 0, 0], up=[0, 1, 0], fov_y=60.0, near=0.5, far=8.0, width=40, height=28)
    clip = np.asarray(cam.world_to_clip(jnp.asarray(v)))
    w = clip[:, 3]
    assert (w < 0).any() and (w > 0.5).any() and ((w > 0) & (w < 0.5)).any()
    ids = vis(clip, f, (28, 40), 2, backend)
    assert_matches_reference(ids, clip, f, (28, 40), 2, min_checked=0.8)


def _unit(mesh):
    v = np.asarray(mesh.vertices)
    v = v - (v.max(0) + v.min(0)) / 2
    return v / np.abs(v).max(), np.asarray(mesh.faces)


@pytest.mark.parametrize("name", ["bunny.ply", "fandisk.obj", "featuretype.STL", "fuze.obj", "rabbit.obj"])
def test_shared_meshes_match_brute_force(name, meshes_dir):
    mesh = ds.load_mesh(os.path.join(meshes_dir, name))
    v, f = _unit(mesh)
    cam = ds.Camera(
        eye=[1.2, 0.9, 2.4], target=[0, 0, 0], up=[0, 1, 0], fov_y=45.0, near=0.1, far=10.0, width=40, height=40
    )
    clip = np.asarray(cam.world_to_clip(jnp.asarray(v)))
    ids = vis(clip, f, 40, 2, "jax")
    assert_matches_reference(ids, clip, f, 40, 2, min_checked=0.75)  # (the brute force once: 16k faces take 7 s)
    if _native.available():  # the native kernel: the same ids, ambiguous pixels included
        np.testing.assert_array_equal(vis(clip, f, 40, 2, "native"), ids)


@pytest.mark.skipif(
    not _native.available(), reason="native kernel unavailable: no C++ compiler, or JAX's default device is not the CPU"
)
def test_native_and_jax_agree_pixel_for_pixel(rng):
    # Bit-for-bit agreement, ties included: the bunny (which has duplicate faces, so exact depth
    # ties), a random soup, and a pixel-aligned grid whose edges and vertices pass through pixel
    # centres, in all 4 layers, square and non-square.
    v, f = _unit(trimesh.load(os.path.join(shared_mesh_dir(), "bunny.ply")))
    v2, f2 = random_soup(np.random.default_rng(7), 300)
    cases = []
    for res in ((96, 96), (61, 131)):
        cam = camera(res, eye=(0.5, 0.4, 2.5))
        for verts, faces in ((v, f), (v2, f2)):
            cases.append((np.asarray(cam.world_to_clip(jnp.asarray(verts, jnp.float32)), np.float32), faces, res))
    clip, faces, _ = _grid_plane_clip(64, 8, rng, perspective=True)
    cases.append((clip.astype(np.float32), faces, (64, 64)))
    for clip, faces, res in cases:
        a = vis(clip, faces, res, 4, "jax")
        b = vis(clip, faces, res, 4, "native")
        assert (a[0] >= 0).sum() > 500
        np.testing.assert_array_equal(a, b)


def _grid_plane_clip(res, cells, rng, perspective):
    # A quad grid whose vertices sit exactly on pixel centres: every grid edge and diagonal
    # passes through pixel centres, so the fill rule decides many pixels.
    xs = (2.0 * (np.arange(res) + 0.5)) / res - 1.0
    idx = np.linspace(2, res - 3, cells + 1).astype(int)
    gx, gy = np.meshgrid(xs[idx], -xs[idx])
    v = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size), np.ones(gx.size)], 1)
    if perspective:  # same projection, different w per vertex
        v = v * rng.uniform(0.5, 3.0, (len(v), 1))
    n = cells + 1
    faces = []
    for r in range(cells):
        for c in range(cells):
            a, b, cc, d = r * n + c, r * n + c + 1, (r + 1) * n + c, (r + 1) * n + c + 1
            faces += [[a, cc, d], [a, d, b]] if (r + c) % 2 else [[a, cc, b], [b, cc, d]]
    faces = np.array(faces)
    # A random permutation of the vertex indices and of the faces changes nothing.
    perm = rng.permutation(len(v))
    inv = np.argsort(perm)
    return v[perm], inv[faces][rng.permutation(len(faces))], idx


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("perspective", [False, True])
def test_watertight_grid_no_gaps_no_double_coverage(backend, perspective, rng):
    res = 64
    clip, faces, idx = _grid_plane_clip(res, 9, rng, perspective)
    ids = vis(clip, faces, res, 2, backend)
    inner = np.zeros((res, res), bool)
    inner[idx[0] + 1 : idx[-1], idx[0] + 1 : idx[-1]] = True
    if perspective:
        # With w != 1 a vertex lands on its pixel centre only up to float32 rounding, and the
        # edge functions through it are no longer exactly zero: the one documented exception.
        inner[np.ix_(idx, idx)] = False
    assert (ids[0][inner] >= 0).all(), "gap inside the closed grid"
    assert (ids[1][inner] < 0).all(), "a pixel covered twice by one surface"


@pytest.mark.parametrize("backend", BACKENDS)
def test_watertight_closed_mesh_two_hits(backend):
    # Every pixel inside a closed convex mesh's silhouette sees exactly one front and one back face.
    m = trimesh.creation.icosphere(subdivisions=3)
    clip = np.asarray(camera(64).world_to_clip(jnp.asarray(m.vertices)))
    ids = vis(clip, m.faces, 64, 3, backend)
    frags = ds.fragments(jnp.asarray(clip), jnp.asarray(m.faces), jnp.asarray(ids))
    covered = ids[0] >= 0
    assert covered.sum() > 1000
    assert (ids[1][covered] >= 0).all() and (ids[2] < 0).all()
    front = np.asarray(frags.front)
    assert front[0][covered].all() and not front[1][covered].any()


@pytest.mark.parametrize("backend", BACKENDS)
def test_culling_a_closed_mesh_seen_from_outside(backend):
    # cull="back" changes nothing in front and leaves no second surface; cull="front" sees the
    # far side, which is the second layer of the unculled render
    m = trimesh.creation.icosphere(subdivisions=3)
    clip = np.asarray(camera(64, eye=(0.4, 0.5, 2.8)).world_to_clip(jnp.asarray(m.vertices)))
    both = vis(clip, m.faces, 64, 2, backend)
    back = vis(clip, m.faces, 64, 2, backend, cull="back")
    front = vis(clip, m.faces, 64, 2, backend, cull="front")
    assert (both[0] >= 0).sum() > 1000
    np.testing.assert_array_equal(back[0], both[0])
    np.testing.assert_array_equal(front[0], both[1])
    assert (back[1] < 0).all() and (front[1] < 0).all()


def _edge_on_views(size, count=3, seed=11, target=0.0):
    """A 5,120-face sphere's float32 clip coordinates from ``count`` random views, eye 2.2-4 from
    its centre, looking at a point ``target``-scaled normal noise from it (each image has faces
    seen nearly edge-on along its outline)."""
    m = trimesh.creation.icosphere(subdivisions=4)
    rng = np.random.default_rng(seed)
    for _ in range(count):
        eye = rng.normal(size=3)
        eye *= rng.uniform(2.2, 4.0) / np.linalg.norm(eye)
        at = rng.normal(size=3) * target if target else np.zeros(3)
        cam = ds.Camera(eye=eye, target=at, up=[0, 1, 0], fov_y=45.0, near=0.1, far=10.0, width=size, height=size)
        yield m, cam, np.asarray(cam.world_to_clip(jnp.asarray(m.vertices, jnp.float32)), np.float32)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_silhouette_shows_the_front_face(backend):
    # A closed convex mesh seen from outside shows front faces only, so culling the back faces
    # changes no pixel. At a silhouette the back face that shares an edge with a front face is
    # behind it by little: a pixel 2 % into the two triangles sees them 6e-5 apart in depth, and
    # depths from planes summed once per triangle (off by up to 3e-3 for the back face, seen nearly
    # edge-on) showed it in front at 1-4 pixels of each of these images.
    for m, _, clip in _edge_on_views(512, seed=7, target=0.2):
        both = vis(clip, m.faces, 512, 1, backend)
        back = vis(clip, m.faces, 512, 1, backend, cull="back")
        assert (both[0] >= 0).sum() > 40000
        differ = np.argwhere(both[0] != back[0])
        assert len(differ) == 0, f"a back face in front at {len(differ)} pixels, e.g. {differ[:3].tolist()}"


def test_fragments_keep_w_and_depth_precise_at_faces_seen_edge_on():
    # w and z are the corners' means weighted by the barycentrics, so in float32 they are off by
    # no more than the barycentrics' own error times the corners' spread (plus rounding); the
    # closed forms D / sum E and sum E z / D, small differences of large terms at an edge-on face,
    # were off by up to 2.2e-3 (w, relative) here, 10 % at 81,920 faces and 1024²
    size = 256
    for m, _, clip in _edge_on_views(size):
        ids = vis(clip, m.faces, size, 1, "native" if _native.available() else "jax")
        ok = ids >= 0
        f32 = ds.fragments(jnp.asarray(clip), m.faces, ids)
        f64 = ds.fragments(jnp.asarray(clip, jnp.float64), m.faces, ids)
        b32, b64 = (np.asarray(f.bary, np.float64)[ok] for f in (f32, f64))
        corners = np.asarray(clip, np.float64)[np.asarray(m.faces)[ids[ok]]]  # [N, 3, 4]
        w64 = np.asarray(f64.w)[ok]
        for got, want, c in ((f32.w, w64, 3), (f32.depth, np.asarray(f64.depth)[ok], 2)):
            values = corners[..., 3] if c == 3 else corners[..., 2] / w64[:, None]
            spread = np.abs(values - want[:, None]).max(axis=1)
            bound = np.abs(b32 - b64).sum(axis=1) * spread + 4e-7 * np.maximum(np.abs(want), 1.0)
            err = np.abs(np.asarray(got, np.float64)[ok] - want)
            assert np.all(err <= bound), (c, float(err.max()), int((err > bound).sum()))


def test_the_kernel_w_is_the_fragments_w():
    # the shading kernel's w, seen through linear fog by eye depth on an unlit black sphere (the
    # pixel is the fog's colour times (w - start) / (end - start)), is the JAX stages' (their
    # fragments', held to float64 above): at faces seen edge-on too, where the kernel's D / sum E
    # was off by up to 1.4e-3 (in the pixel: 1e-3)
    if not _native.available():
        pytest.skip("native kernel unavailable")
    size = 256
    opts = ds.RenderOptions.from_keys(shading="phong", fog="linear", fog_distance="depth")
    stages = opts.replace(raster=dataclasses.replace(opts.raster, backend="jax"))
    for m, cam, clip in _edge_on_views(size):
        scene = ds.Scene(
            mesh=ds.Mesh(vertices=m.vertices, faces=m.faces),
            camera=cam,
            material=ds.Material(ambient=0.0, diffuse=0.0, specular=0.0, emission=0.0),
            ambient_light=0.0,
            fog=ds.Fog(color=1.0, start=0.5, end=6.0),
        )
        scene = float32(scene)
        ids = vis(clip, m.faces, size, 1, "native")
        images = []
        for o, kernel in ((opts, True), (stages, False)):
            assert ("diffshade_shade" in str(jax.make_jaxpr(lambda s: ds.render(s, o, ids=ids))(scene))) == kernel
            images.append(np.asarray(ds.render(scene, o, ids=ids), np.float64))
        assert images[1][ids[0] >= 0].min() > 0.1  # (every pixel of the sphere within the fog's range)
        # float32 rounding of the edge functions at faces seen edge-on: 1.07e-6 at most since an
        # eager render is the compiled program (whose sums XLA contracts into fused multiply-adds),
        # 1.0e-6 op by op; the bug this holds was 1e-3
        assert np.abs(images[0] - images[1]).max() <= 2e-6


@pytest.mark.parametrize("shading", ["gouraud", "phong"])
def test_culled_render_of_a_closed_mesh_is_the_same_image(shading):
    # two-sided lighting with a back material: culled, the render lights only the front side
    # (statically), and the image is the unculled one's
    m = trimesh.creation.icosphere(subdivisions=2)
    mat = ds.Material(ambient=0.1, diffuse=[0.7, 0.4, 0.2], specular=0.4, shininess=20.0)
    scene = ds.Scene(
        mesh=ds.Mesh(vertices=m.vertices, faces=m.faces),
        camera=camera(24, eye=(0.4, 0.5, 2.8)),
        material=mat,
        back_material=ds.Material(ambient=0.3, diffuse=[0.1, 0.8, 0.1]),
        point=ds.PointLights(
            color=[[1.0, 1.0, 1.0]],
            position=[[2.0, 2.0, 3.0]],
            attenuation=[[1.0, 0.1, 0.0]],
            ambient=[[0.0, 0.0, 0.0]],
        ),
    )
    opts = ds.RenderOptions(raster=ds.Raster(shading=shading), lighting=ds.Lighting(two_sided=True))
    culled = opts.replace(raster=ds.Raster(shading=shading, cull="back"))
    a = np.asarray(ds.render(scene, opts))
    b = np.asarray(ds.render(scene, culled))
    assert (ds.scene_visibility(scene, culled)[0] >= 0).sum() > 200
    np.testing.assert_allclose(b, a, rtol=0, atol=1e-6)


@pytest.mark.parametrize("backend", BACKENDS)
def test_culling_keeps_the_triangles_of_one_orientation(backend, rng):
    # A soup that crosses the near plane: the culled visibility is the visibility of the
    # triangles of the kept orientation alone (det [x y w] in float64 here: > 0 front, < 0 back),
    # in every layer, with their ids
    v, f = random_soup(rng, 60, spread=1.5, size=0.8)
    v[:, 2] += 1.2
    clip = np.asarray(camera(40, near=0.5).world_to_clip(jnp.asarray(v)), np.float32)
    assert (clip[:, 3] < 0.5).any()
    det = np.linalg.det(clip[f][..., [0, 1, 3]].astype(np.float64))
    for cull, kept in (("back", det > 0), ("front", det < 0)):
        sub = np.flatnonzero(kept)
        assert 10 < len(sub) < len(f) - 10
        ids = vis(clip, f, 40, 2, backend, cull=cull)
        alone = vis(clip, f[sub], 40, 2, backend)
        assert (ids[0] >= 0).sum() > 200
        np.testing.assert_array_equal(ids, np.where(alone >= 0, sub[np.maximum(alone, 0)], -1))


@pytest.mark.parametrize("backend", BACKENDS)
def test_empty_and_culled_scenes(backend):
    assert (vis(np.zeros((0, 4)), np.zeros((0, 3), int), 16, 2, backend) == -1).all()
    v = np.array([[0, 0, 5.0], [1, 0, 5.0], [0, 1, 5.0]])  # behind the eye
    clip = np.asarray(camera(16).world_to_clip(jnp.asarray(v)))
    assert (vis(clip, [[0, 1, 2]], 16, 1, backend) == -1).all()
    v = np.array([[0, 0, -50.0], [1, 0, -50.0], [0, 1, -50.0]])  # beyond the far plane
    clip = np.asarray(camera(16).world_to_clip(jnp.asarray(v)))
    assert (vis(clip, [[0, 1, 2]], 16, 1, backend) == -1).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_triangle_larger_than_screen(backend):
    v = np.array([[-100, -100, 0.0], [100, -100, 0.0], [0, 100, 0.0]])
    clip = np.asarray(camera(32).world_to_clip(jnp.asarray(v)))
    ids = vis(clip, [[0, 1, 2]], 32, 2, backend)
    assert (ids[0] == 0).all() and (ids[1] == -1).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_degenerate_triangles_cover_nothing(backend, rng):
    v, f = random_soup(rng, 30)
    degenerate_v = np.array(
        [[0, 0, 0.5], [0, 0, 0.5], [0.3, 0.3, 0.5], [0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [0.3, 0.3, 0.3]]
    )
    v2 = np.concatenate([degenerate_v, v])
    f2 = np.concatenate([[[0, 1, 2], [3, 4, 5], [0, 0, 0]], f + len(degenerate_v)])
    cam = camera(48)
    ids = vis(np.asarray(cam.world_to_clip(jnp.asarray(v))), f, 48, 2, backend)
    ids2 = vis(np.asarray(cam.world_to_clip(jnp.asarray(v2))), f2, 48, 2, backend)
    np.testing.assert_array_equal(np.where(ids2 >= 3, ids2 - 3, ids2), ids)
    frags = ds.fragments(cam.world_to_clip(jnp.asarray(v2)), jnp.asarray(f2), jnp.asarray(ids2))
    assert np.isfinite(np.asarray(frags.bary)).all() and np.isfinite(np.asarray(frags.depth)).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_duplicate_faces_tie_exactly_and_the_smaller_id_wins(backend, rng):
    """A scanned mesh's duplicate faces (the same corners, either winding; coincident corners of
    other vertices; the copy before or after the original) have bit-identical depths wherever
    they cover a pixel: the smaller id is seen, with any camera, jitted or not, on both backends
    (rounding decided it when each face's depth was summed in its own corner order). Two layers:
    the pair is the pixel's two nearest."""
    tm = trimesh.creation.icosphere(2)
    v, f = np.asarray(tm.vertices), np.asarray(tm.faces)
    n = len(f)
    soup = np.arange(3 * n).reshape(n, 3) + len(v)  # coincident vertices of the same points
    perms = [[0, 2, 1], [2, 1, 0], [1, 0, 2], [1, 2, 0], [0, 1, 2]]
    copies = []
    for i in range(n):
        kind = rng.integers(3)
        if kind == 0:
            copies.append(f[i][perms[rng.integers(3)]])  # the other winding, shared vertices
        elif kind == 1:
            copies.append(f[i][perms[3 + rng.integers(2)]])  # the same winding, rotated
        else:
            copies.append(soup[i][perms[rng.integers(5)]])  # over coincident vertices
    copies = np.asarray(copies)
    first = rng.uniform(size=n) < 0.5  # the copy drawn before its original, or after
    faces = np.concatenate([np.where(first[:, None], copies, f), np.where(first[:, None], f, copies)])
    verts = np.concatenate([v, v[f].reshape(-1, 3)])
    group = np.concatenate([np.arange(n), np.arange(n)])
    for _ in range(3):
        eye = rng.normal(size=3)
        cam = camera(48, eye=tuple(3.0 * eye / np.linalg.norm(eye)))
        clip = np.asarray(cam.world_to_clip(jnp.asarray(verts, jnp.float32)))
        clip = clip * np.float32(rng.uniform(0.5, 2.0))  # (the same points, other rounding)
        ids = vis(clip, faces, 48, 2, backend)
        eager = np.asarray(ds.visibility(jnp.asarray(clip, jnp.float32), jnp.asarray(faces), (48, 48), 2, backend))
        np.testing.assert_array_equal(ids, eager)
        seen = ids[0] >= 0
        assert seen.mean() > 0.2
        # the nearest two fragments are one face and its copy, the smaller id first
        assert (group[ids[0][seen]] == group[ids[1][seen]]).all()
        assert (ids[0][seen] < ids[1][seen]).all()


def test_bin_overflow_is_never_silent():
    # Tiny static capacities: tiles overflow and the pair buffer overflows; the chunked path must
    # still give exactly the same result, with more passes and no recompilation.
    m = trimesh.creation.icosphere(subdivisions=3)
    clip = jnp.asarray(camera(48).world_to_clip(jnp.asarray(m.vertices)), jnp.float32)
    f = jnp.asarray(m.faces, jnp.int32)
    ref = vis(clip, f, 48, 2, "jax")
    ids, passes = jax.jit(lambda c: ds.visibility_passes(c, f, (48, 48), 2, tile_capacity=2, pair_capacity=64))(clip)
    np.testing.assert_array_equal(np.asarray(ids), ref)
    ids1, passes1 = jax.jit(lambda c: ds.visibility_passes(c, f, (48, 48), 2))(clip)
    assert int(passes1) == 1 and int(passes) > 50
    np.testing.assert_array_equal(np.asarray(ids1), ref)


def _interior(frags, margin=0.05):
    return np.asarray((frags.tri_id[0] >= 0) & (jnp.min(frags.bary[0], -1) > margin))


def test_per_face_and_per_pixel_fragments_agree(monkeypatch):
    # Fragments and interpolation through per-face tables gathered by triangle id (faces no more
    # than pixels) or from each pixel's own vertices (more faces than pixels): the same values.
    m = trimesh.creation.icosphere(subdivisions=2)
    v = jnp.asarray(m.vertices, jnp.float64)
    f = jnp.asarray(m.faces)
    clip = camera(32).world_to_clip(v)
    ids = ds.visibility(clip, f, (32, 32), 2)
    out = {}
    for per_face in (True, False):
        monkeypatch.setattr(_raster, "_per_face", lambda faces, t, pf=per_face: pf)
        fr = ds.fragments(clip, f, ids)
        out[per_face] = (fr.bary, fr.depth, fr.w, fr.front, ds.interpolate(v, f, fr))
    assert (np.asarray(ids[1]) >= 0).sum() > 100
    for a, b in zip(out[True], out[False]):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-10, atol=1e-12)


def test_the_stages_called_eagerly_compile_nothing_the_second_time():
    # `keep` (the fusion boundary: a conditional) is the identity outside a trace: a conditional
    # built eagerly from new branches was compiled anew at every call (an eager float64 render
    # of the default scene at 64²: 6 compiles and 0.79 s a call, then none and 0.16 s). Under
    # jit it is still the conditional.
    from conftest import small_default_scene

    from diffshade._util import keep

    scene, opts = small_default_scene(16, 16, shading="phong")
    scene = float64(scene)
    clip = scene.camera.world_to_clip(scene.mesh.vertices)
    ids = ds.scene_visibility(scene, opts)

    def stages():
        frags = ds.fragments(clip, scene.mesh.faces, ids[:1])
        return ds.surface_points(scene, frags, opts.raster, ds.needs(opts), clip)

    first = stages()
    with compiles() as compiled:
        again = stages()
    assert compiled == [], f"an eager call compiled {compiled}"
    # Equal to the bit on a CPU. A GPU sums the vertex normals' scatter-add with atomics in no
    # fixed order: on an H200 two calls differed by 1 ulp at 9 of 256 entries.
    tol = 0.0 if jax.default_backend() == "cpu" else 8 * np.finfo(np.float64).eps
    for a, b in zip(
        first.normal + first.position + (first.frags.bary,), again.normal + again.position + (again.frags.bary,)
    ):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=tol, atol=tol)
    x = jnp.arange(3.0)
    assert np.array_equal(keep(x, 2 * x)[1], 2 * x)
    assert "cond" in str(jax.make_jaxpr(lambda y: keep(y, 2 * y))(x))


def test_take_is_the_indexing_it_replaces_without_wrapping_negative_indices(rng):
    # diffshade._util.take: x[index] along the first axis as one gather (the renders' gathers by
    # a triangle's, vertex's or texel's index), without the comparison, addition and select that
    # jnp's indexing adds to wrap negative indices
    from diffshade._util import take

    for shape, index_shape in (((7,), (5,)), ((7,), (2, 3)), ((7, 4), (5,)), ((7, 3, 2), (2, 3))):
        x = jnp.asarray(rng.normal(size=shape))
        index = jnp.asarray(rng.integers(0, shape[0], index_shape), jnp.int32)
        assert np.array_equal(take(x, index), x[index])
        assert np.array_equal(jax.jit(take)(x, index), x[index])
        jaxpr = str(jax.make_jaxpr(take)(x, index))
        assert jaxpr.count("gather") == 1 and "select" not in jaxpr and "lt " not in jaxpr
        # a gather is linear: its derivatives are the gather of the tangent, forward and reverse
        check_grads(lambda y: take(y, index), (float64(x),))
    assert "select_n" in str(jax.make_jaxpr(lambda y, i: y[i])(x, index))  # (what it leaves out)


def test_the_images_along_one_tangent_are_the_batched_ones():
    # fitting._problem.tangent_images takes one tangent without vmap (the trace then does not go
    # through the batching of every primitive): the same numbers as the batched path
    from fitting._problem import tangent_images

    f = lambda t: jnp.stack([jnp.sin(t[0]) * t[1], t[0] ** 2, jnp.exp(t[1])])  # noqa: E731
    x, e = jnp.asarray([0.3, -1.2]), jnp.asarray([[0.7, 0.2]])
    y1, t1 = tangent_images(f, x, e)
    y2, t2 = tangent_images(f, x, jnp.concatenate([e, e]))
    assert t1.shape == (1, 3) and np.array_equal(y1, y2) and np.array_equal(t1[0], t2[0])
    assert np.array_equal(t1[0], jax.jvp(f, (x,), (e[0],))[1])


def test_the_jax_visibility_called_eagerly_compiles_nothing_the_second_time():
    # Its while loops, called eagerly, were compiled anew at every call (0.6 s a call at 64²);
    # the backend is now one jitted program per size. Two eager calls: the second compiles
    # nothing and gives the same ids, which are the native backend's where it is available.
    from conftest import small_default_scene

    scene, opts = small_default_scene(16, 16, shading="phong")
    opts = opts.replace(raster=dataclasses.replace(opts.raster, backend="jax"))
    first = ds.scene_visibility(scene, opts)
    with compiles() as compiled:
        again = ds.scene_visibility(scene, opts)
    assert compiled == [], f"an eager call compiled {compiled}"
    np.testing.assert_array_equal(np.asarray(first), np.asarray(again))
    assert (np.asarray(first) >= 0).sum() > 50
    if _native.available():
        native = ds.scene_visibility(scene, opts.replace(raster=dataclasses.replace(opts.raster, backend="native")))
        np.testing.assert_array_equal(np.asarray(first), np.asarray(native))


@pytest.mark.parametrize("per_face", [True, False])
def test_fragments_gradients_match_finite_differences(per_face, monkeypatch):
    # d(barycentrics, depth)/d(vertices, camera) at interior pixels, forward and reverse mode,
    # through per-face tables and from each pixel's vertices.
    monkeypatch.setattr(_raster, "_per_face", lambda faces, t: per_face)
    m = trimesh.creation.icosphere(subdivisions=1)
    v0 = jnp.asarray(m.vertices, jnp.float64)
    f = jnp.asarray(m.faces)
    cam = camera(24)
    ids = ds.visibility(cam.world_to_clip(v0), f, (24, 24), 1)
    mask = _interior(ds.fragments(cam.world_to_clip(v0), f, ids))
    w = jnp.asarray(np.random.default_rng(0).normal(size=(24, 24, 3)))

    def loss(v, eye):
        c = eqx.tree_at(lambda c: c.eye, cam, eye)
        fr = ds.rasterize(c.world_to_clip(v), f, (24, 24), 1)
        return jnp.where(mask, jnp.sum(fr.bary[0] * w, -1) + fr.depth[0] + 0.1 * fr.w[0], 0.0)

    assert mask.sum() > 50
    check_grads(loss, (v0, cam.eye), order=1, modes=("fwd", "rev"), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_fragments_jvp_and_linearize_run_under_jit():
    m = trimesh.creation.icosphere(subdivisions=2)
    v0 = jnp.asarray(m.vertices)
    f = jnp.asarray(m.faces)
    cam = camera(32)
    fn = jax.jit(lambda v: ds.rasterize(cam.world_to_clip(v), f, (32, 32), 2).bary)
    out, tan = jax.jvp(fn, (v0,), (jnp.ones_like(v0),))
    _, lin = jax.linearize(fn, v0)
    np.testing.assert_allclose(np.asarray(lin(jnp.ones_like(v0))), np.asarray(tan), rtol=1e-10, atol=1e-12)
    assert np.isfinite(np.asarray(tan)).all()
    g = jax.grad(lambda v: jnp.sum(fn(v) ** 2))(v0)
    assert np.isfinite(np.asarray(g)).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_vmap_over_vertices(backend, rng):
    m = trimesh.creation.icosphere(subdivisions=2)
    f = jnp.asarray(m.faces)
    cam = camera(32)
    vs = jnp.stack([jnp.asarray(m.vertices) * s + o for s, o in [(1.0, 0.0), (0.7, 0.2), (1.2, -0.1)]])

    def fn(v):
        return ds.rasterize(cam.world_to_clip(v), f, (32, 32), 2, backend)

    batched = jax.jit(jax.vmap(fn))(vs)
    for i in range(3):
        single = fn(vs[i])
        np.testing.assert_array_equal(np.asarray(batched.tri_id[i]), np.asarray(single.tri_id))
        np.testing.assert_allclose(np.asarray(batched.bary[i]), np.asarray(single.bary), atol=1e-12)


def test_bary_reproduce_pixel_position():
    # Perspective-correct: interpolating clip coordinates with the barycentrics lands on the pixel centre.
    m = trimesh.creation.icosphere(subdivisions=2)
    cam = camera(32)
    clip = cam.world_to_clip(jnp.asarray(m.vertices))
    fr = ds.rasterize(clip, jnp.asarray(m.faces), (32, 32), 1)
    c = ds.interpolate(clip, jnp.asarray(m.faces), fr)[0]
    xs, ys = ds.pixel_centres(32, 32, jnp.float64)
    mask = np.asarray(fr.tri_id[0] >= 0)
    np.testing.assert_allclose(
        np.asarray(c[..., 0] / c[..., 3])[mask], np.broadcast_to(np.asarray(xs), (32, 32))[mask], atol=1e-9
    )
    np.testing.assert_allclose(
        np.asarray(c[..., 1] / c[..., 3])[mask], np.broadcast_to(np.asarray(ys)[:, None], (32, 32))[mask], atol=1e-9
    )
    np.testing.assert_allclose(np.asarray(c[..., 2] / c[..., 3])[mask], np.asarray(fr.depth[0])[mask], atol=1e-9)


def test_bad_arguments_raise_clear_errors():
    with pytest.raises(ValueError, match="clip must have shape"):
        ds.visibility(jnp.zeros((3, 3)), jnp.zeros((1, 3), int), (8, 8))
    with pytest.raises(ValueError, match="faces must be an integer"):
        ds.visibility(jnp.zeros((3, 4)), jnp.zeros((1, 3)), (8, 8))
    with pytest.raises(ValueError, match="layers"):
        ds.visibility(jnp.zeros((3, 4)), jnp.zeros((1, 3), int), (8, 8), layers=0)
    with pytest.raises(ValueError, match="backend"):
        ds.visibility(jnp.zeros((3, 4)), jnp.zeros((1, 3), int), (8, 8), backend="gpu")
    with pytest.raises(ValueError, match="cull must be one of"):
        ds.visibility(jnp.zeros((3, 4)), jnp.zeros((1, 3), int), (8, 8), cull="backs")
    with pytest.raises(ValueError, match="Raster.cull must be one of"):
        ds.Raster(cull=True)


def test_a_kernel_that_does_not_build_is_said_once(monkeypatch):
    # the renderer then takes the JAX stages (the same images, slower): the user is told why, once
    def fails():
        raise _native.NativeUnavailable("compiling raster.cc and shade.cc failed: (a compiler's error)")

    monkeypatch.setattr(_native, "_state", {})
    monkeypatch.setattr(_native, "_build", fails)
    monkeypatch.setattr(jax, "default_backend", lambda: "cpu")
    with pytest.warns(RuntimeWarning, match="native CPU kernels are unavailable.*a compiler's error"):
        assert not _native.available()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert not _native.available()


def test_native_backend_off_the_cpu_is_a_clear_error(monkeypatch):
    # the native kernel is registered for the CPU only: with a GPU as JAX's default device, asking
    # for it names the problem (not XLA's "no FFI handler registered"), and "auto" picks JAX
    from diffshade import _raster

    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    with pytest.raises(ValueError, match="CPU kernel.*'gpu'"):
        _raster.resolve_backend("native")
    assert _raster.resolve_backend("auto") == "jax"
    assert not _native.available()
