import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from conftest import check_grads, float32, float64

import diffshade as ds


def _native_ok():
    from diffshade import _native

    return _native.available()


@pytest.mark.parametrize(
    "name,faces",
    [("bunny.ply", 16301), ("fandisk.obj", 5750), ("featuretype.STL", 3476), ("fuze.obj", 1000), ("rabbit.obj", 1252)],
)
def test_shared_meshes_load(name, faces, meshes_dir):
    path = os.path.join(meshes_dir, name)
    m = ds.load_mesh(path)
    assert m.faces.shape == (faces, 3)
    assert np.isfinite(np.asarray(m.vertices)).all()
    # as authored: the file's vertices, in its order
    tm = trimesh.load(path, process=False)
    np.testing.assert_array_equal(np.asarray(m.vertices), np.asarray(tm.vertices))
    # merged: duplicated vertices (STL facets, OBJ seams) become one
    mm = ds.load_mesh(path, vertices="merged")
    assert mm.faces.shape == (faces, 3) and mm.normals is None
    assert len(np.unique(np.asarray(mm.vertices), axis=0)) == mm.vertices.shape[0]


def test_stl_is_closed_after_merging(meshes_dir):
    m = ds.load_mesh(os.path.join(meshes_dir, "featuretype.STL"), vertices="merged")
    assert trimesh.Trimesh(np.asarray(m.vertices), np.asarray(m.faces), process=False).is_watertight


@pytest.mark.parametrize(
    "name,msg",
    [
        ("empty.obj", "no triangles"),
        ("obj_points.obj", "no triangles"),
        ("notenoughindices.obj", r"line \d+: a face needs at least 3"),
    ],
)
def test_bad_meshes_are_rejected_clearly(name, msg, meshes_dir):
    path = os.path.join(meshes_dir, "bad", name)
    with pytest.raises(ds.MeshError, match=msg) as exc:
        ds.load_mesh(path)
    assert name in str(exc.value)


def test_negative_indices_load_as_a_cube(meshes_dir):
    m = ds.load_mesh(os.path.join(meshes_dir, "bad", "negative_indices.obj"), vertices="merged")
    assert m.vertices.shape == (8, 3) and m.faces.shape == (12, 3)
    assert trimesh.Trimesh(np.asarray(m.vertices), np.asarray(m.faces), process=False).is_watertight


_CUBE_OBJ = """# a unit cube, one normal per face (hard edges), vertices shared between faces by position
v -1 -1 -1
v 1 -1 -1
v 1 1 -1
v -1 1 -1
v -1 -1 1
v 1 -1 1
v 1 1 1
v -1 1 1
vn 0 0 -1
vn 0 0 1
vn 0 -1 0
vn 0 1 0
vn -1 0 0
vn 1 0 0
f 1//1 3//1 2//1
f 1//1 4//1 3//1
f 5//2 6//2 7//2
f 5//2 7//2 8//2
f 1//3 2//3 6//3
f 1//3 6//3 5//3
f 4//4 8//4 7//4
f 4//4 7//4 3//4
f 1//5 5//5 8//5
f 1//5 8//5 4//5
f 2//6 3//6 7//6
f 2//6 7//6 6//6
"""


def test_meshes_load_as_authored_with_their_normals(tmp_path):
    p = tmp_path / "cube.obj"
    p.write_text(_CUBE_OBJ)
    m = ds.load_mesh(p)
    assert m.faces.shape == (12, 3) and m.vertices.shape == (24, 3) and m.normals is not None
    # every corner carries its face's normal: hard edges
    tri = np.asarray(m.vertices)[np.asarray(m.faces)]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    vn = np.asarray(m.vertex_normals())[np.asarray(m.faces)]
    np.testing.assert_allclose(vn, np.repeat(fn[:, None], 3, axis=1), atol=1e-12)
    merged = ds.load_mesh(p, vertices="merged")
    assert merged.vertices.shape == (8, 3) and merged.normals is None
    assert abs(float(np.linalg.norm(merged.vertex_normals()[0])) - 1) < 1e-12
    # Gouraud on the authored cube: each face one colour (a directional light, no specular),
    # k_d (n·l)⁺ + k_a I_a exactly; merged, the faces blend
    cam = ds.Camera(
        eye=[2.5, 2.0, 3.0], target=[0, 0, 0], up=[0, 1, 0], fov_y=45.0, near=0.5, far=20.0, width=32, height=32
    )
    light = ds.DirectionalLights(color=[[1.0, 1.0, 1.0]], direction=[[-0.3, -1.0, -0.6]], ambient=[[0, 0, 0]])
    mat = ds.Material(ambient=0.1, diffuse=0.7, specular=0.0)
    opts = ds.RenderOptions(raster=ds.Raster(shading="gouraud"), lighting=ds.Lighting(specular="none"))
    out = []
    for mesh in (m, merged):
        scene = ds.Scene(mesh=mesh, camera=cam, material=mat, directional=light, ambient_light=[0.2, 0.2, 0.2])
        ids = np.asarray(ds.scene_visibility(scene, opts)[0])
        img = np.asarray(ds.render(scene, opts, jnp.asarray(ids[None])))
        out.append((img, ids))
    (img, ids), (img_m, _) = out
    l = -np.array([-0.3, -1.0, -0.6]) / np.linalg.norm([-0.3, -1.0, -0.6])
    expect = 0.7 * np.maximum(fn @ l, 0.0) + 0.02
    seen = ids >= 0
    np.testing.assert_allclose(img[seen][:, 0], expect[ids[seen]], atol=1e-6)
    assert np.abs(img_m[seen][:, 0] - expect[ids[seen]]).max() > 0.05


def test_file_normals_from_ply_scene_files_and_errors(tmp_path):
    ply = tmp_path / "tri.ply"
    ply.write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty float ny\nproperty float nz\nelement face 1\n"
        "property list uchar int vertex_indices\nend_header\n"
        "0 0 0 0 0 2\n1 0 0 0 0.6 0.8\n0 1 0 0 0 1\n3 0 1 2\n"
    )
    m = ds.load_mesh(ply)
    np.testing.assert_allclose(m.vertex_normals(), [[0, 0, 1], [0, 0.6, 0.8], [0, 0, 1]], atol=1e-7)
    d = dict(ds.DEFAULT_SCENE)
    d.pop("fog", None)
    scene, _ = ds.scene_from_dict({**d, "mesh": {"path": str(ply)}})
    assert scene.mesh.normals is not None
    scene, _ = ds.scene_from_dict({**d, "mesh": {"path": str(ply), "vertices": "merged"}})
    assert scene.mesh.normals is None
    # an object scaled along z: its normals transform by the inverse scale
    mat = {"diffuse": 0.5}
    bare = {k: x for k, x in d.items() if k not in ("mesh", "material")}
    scene, _ = ds.scene_from_dict(
        {
            **bare,
            "object": [
                {"path": str(ply), "scale": [1, 1, 4], "material": mat},
                {"icosphere": 0, "translate": [3, 0, 0], "material": mat},
            ],
        }
    )
    n = np.asarray(scene.mesh.vertex_normals())
    np.testing.assert_allclose(n[1], np.array([0, 0.6, 0.2]) / np.linalg.norm([0, 0.6, 0.2]), atol=1e-7)
    for mesh, msg in [
        ({"path": str(ply), "vertices": "welded"}, "mesh.vertices"),
        ({"icosphere": 1, "vertices": "merged"}, "only applies"),
    ]:
        with pytest.raises(ds.SceneError, match=msg):
            ds.scene_from_dict({**d, "mesh": mesh})
    bad = tmp_path / "nan_normal.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 nan\nf 1//1 2//1 3//1\n")
    with pytest.raises(ds.MeshError, match="normal"):
        ds.load_mesh(bad)


def test_nan_colours_do_not_matter(meshes_dir):
    # colours are not used; positions are fine, so the mesh loads and renders without NaN
    m = ds.load_mesh(os.path.join(meshes_dir, "bad", "nancolor.obj"))
    assert m.faces.shape == (12, 3) and np.isfinite(np.asarray(m.vertices)).all()


def test_missing_file_and_nan_vertices(tmp_path):
    with pytest.raises(ds.MeshError, match="not found"):
        ds.load_mesh(tmp_path / "nope.obj")
    p = tmp_path / "nan.obj"
    p.write_text("v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(ds.MeshError, match="NaN or infinite"):
        ds.load_mesh(p)
    with pytest.raises(ds.MeshError, match="face indices"):
        ds.mesh_from_arrays(np.zeros((3, 3)), [[0, 1, 3]])


def test_vertex_normals_of_faces_that_cancel_are_zero_in_every_precision(meshes_dir):
    """Where a vertex's faces cancel (opposite duplicate faces: the bunny has 22 such vertices,
    beside 25 that no face uses; a fin of two opposite faces), the sum is float rounding: the normal is the zero vector in
    float32 and float64, in JAX and on the host (float32 gave the bunny unit vectors of noise
    where the host gave zero, and a fit's image differed by 0.07). Everywhere else the two agree
    to rounding; the derivatives through the rule are finite, forward and reverse."""
    bunny = ds.load_mesh(os.path.join(meshes_dir, "bunny.ply"))
    fin_v = np.array([[0, 0, 0], [1, 0, 0], [0.4, 0.7, 0.1], [0.5, -0.6, 0.2]])
    fin = ds.Mesh(vertices=fin_v, faces=[[0, 1, 2], [1, 0, 2], [0, 3, 1]])  # vertex 2: a fin
    for mesh, zero in ((bunny, 22 + 25), (fin, 1)):
        for dtype in (np.float32, np.float64):
            m = float32(mesh) if dtype == np.float32 else float64(mesh)
            jx, host = np.asarray(m.vertex_normals()), np.asarray(m.with_vertex_normals().normals)
            assert jx.dtype == host.dtype == dtype
            nz = np.linalg.norm(jx, axis=1) == 0
            np.testing.assert_array_equal(nz, np.linalg.norm(host, axis=1) == 0)
            assert nz.sum() == zero
            np.testing.assert_allclose(jx, host, atol=1e-5 if dtype == np.float32 else 1e-12)
    assert (np.asarray(fin.vertex_normals())[2] == 0).all()
    check_grads(lambda v: ds.Mesh(vertices=v, faces=fin.faces).vertex_normals(), (jnp.asarray(fin_v),), 1)
    g = jax.grad(lambda v: ds.Mesh(vertices=v, faces=[[0, 0, 1], [0, 1, 2]]).vertex_normals().sum())(
        jnp.asarray(fin_v[:3])
    )
    assert np.isfinite(np.asarray(g)).all()  # (a degenerate face: zero edges)


@pytest.mark.skipif(not _native_ok(), reason="the native kernels are unavailable (no C++ compiler, or not the CPU)")
def test_the_native_normals_are_the_same_bits_in_every_program(meshes_dir):
    """In float32 on the CPU the vertex normals come from one C++ function, so a render's
    (eager, jitted, batched) and a fit's host-side ones (``with_vertex_normals``, used as they
    are) are the same bits: the fit's model was off the render's by 0.036× a noise-free target's
    float floor with float64 host normals, and a DEODR-scene fit took twice the evaluations.
    They agree with the JAX implementation to rounding, zero where it is zero, and their
    derivatives are the JAX implementation's."""
    from diffshade._mesh import _normals_jax

    mesh = float32(ds.load_mesh(os.path.join(meshes_dir, "bunny.ply")))
    n = np.asarray(mesh.vertex_normals())
    host = mesh.with_vertex_normals()
    assert host.unit_normals and np.array_equal(np.asarray(host.vertex_normals()), n)
    assert np.array_equal(np.asarray(jax.jit(lambda m: m.vertex_normals())(mesh)), n)
    both = jax.vmap(lambda v: ds.Mesh(vertices=v, faces=mesh.faces).vertex_normals())(
        jnp.stack([mesh.vertices, 2.0 * mesh.vertices])
    )
    assert np.array_equal(np.asarray(both[0]), n)
    ref = np.asarray(_normals_jax(mesh.vertices, mesh.faces))
    np.testing.assert_allclose(n, ref, atol=1e-6)
    np.testing.assert_array_equal(np.linalg.norm(n, axis=1) == 0, np.linalg.norm(ref, axis=1) == 0)
    dv = jnp.asarray(np.random.default_rng(0).normal(size=mesh.vertices.shape), jnp.float32)
    f = lambda v: ds.Mesh(vertices=v, faces=mesh.faces).vertex_normals()  # noqa: E731
    _, t = jax.jvp(f, (mesh.vertices,), (dv,))
    _, t_ref = jax.jvp(lambda v: _normals_jax(v, mesh.faces), (mesh.vertices,), (dv,))
    np.testing.assert_array_equal(np.asarray(t), np.asarray(t_ref))
    g = jax.grad(lambda v: jnp.sum(f(v) * dv))(mesh.vertices)
    assert np.isfinite(np.asarray(g)).all() and float(jnp.sum(g * dv)) == pytest.approx(
        float(jnp.sum(t * dv)), rel=1e-3
    )


def test_vertex_normals_area_weighted():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 2.0]])
    f = np.array([[0, 1, 2], [0, 3, 1]])  # areas 0.5 (normal +z) and 1.0 (normal +y)
    n = np.asarray(ds.Mesh(vertices=v, faces=f).vertex_normals())
    expected = np.array([0, 2.0, 1.0]) / np.sqrt(5)
    np.testing.assert_allclose(n[0], expected, atol=1e-12)
    np.testing.assert_allclose(n[2], [0, 0, 1], atol=1e-12)
    sphere = ds.icosphere(3)
    vn = np.asarray(sphere.vertex_normals())
    np.testing.assert_allclose(vn, np.asarray(sphere.vertices), atol=2e-2)
    # computed once on the host (what a fit gives its program): the same normals, and data after
    for mesh in (ds.Mesh(vertices=v, faces=f), sphere):
        host = mesh.with_vertex_normals()
        assert host.normals is not None and host.normals.dtype == mesh.vertices.dtype
        np.testing.assert_allclose(np.asarray(host.vertex_normals()), np.asarray(mesh.vertex_normals()), atol=1e-6)
        assert host.with_vertex_normals() is host


def scene_dict(**over):
    d = {
        "mesh": {"icosphere": 2},
        "camera": {"eye": [0, 0, 3.0], "width": 32, "height": 32},
        "render": {"fog": "linear"},
        "light": [{"type": "point", "position": [1, 1, 3.0], "attenuation": [1, 0.1, 0.0]}],
        "fog": {"start": 1.0, "end": 6.0, "color": [0.2, 0.3, 0.4]},
    }
    for k, v in over.items():
        d[k] = v
    return d


@pytest.mark.parametrize(
    "patch,msg",
    [
        (
            {"light": [{"type": "point", "position": [0, 0, 1], "attenuation": [-1, 0, 0]}]},
            r"light\[0\].attenuation: each entry must be >= 0",
        ),
        (
            {"light": [{"type": "spot", "position": [0, 0, 1], "axis": [0, 0, -1], "cutoff": 120}]},
            r"light\[0\].cutoff: must lie in \[0.0, 90.0\]",
        ),
        ({"light": [{"type": "laser"}]}, r"light\[0\].type: must be one of"),
        ({"camera": {"eye": [0, 0, 3.0], "width": 0}}, r"camera.width: must be an integer in \[1, 8192\]"),
        ({"camera": {"eye": [0, 0, 3.0], "fov_y": "wide"}}, r"camera.fov_y: must be a number"),
        ({"fog": {"start": 5.0, "end": 1.0}}, r"fog.end: must lie in \[5.0, inf\]"),
        ({"material": {"diffuse": [0.5, 2.0, 0.5]}}, r"material.diffuse: each entry must be <= 1.0"),
        ({"material": {"shininess": 0}}, r"material.shininess: must lie in \(0.0, inf\]"),
        ({"material": {"colour": 1}}, r"material: unknown field"),
        ({"render": {"shading": "toon"}}, r"render: shading \(Raster.shading must be one of"),
        ({"mesh": {"path": "missing.obj"}}, r"mesh.path: .*missing.obj: mesh file not found"),
        ({"material": {"opacity": 1.5}}, r"material.opacity: must lie in \[0.0, 1.0\]"),
        ({"material": {"kay": 1}}, r"material.kay: must be true or false"),
        ({"material": {"absorption": [0, -1, 0]}}, r"material.absorption: each entry must be >= 0"),
        (
            {"render": {"absorption": True, "transparency": True}},
            r"render: absorption \(Transparency.absorption needs layers >= 2",
        ),
        # (shadow_pcf is read with shadows on: ShadowMaps holds it)
        (
            {"render": {"fog": "linear", "shadows": True, "shadow_pcf": 2}},
            r"render: shadow_pcf \(ShadowMaps.pcf must be odd",
        ),
        # a key whose group is off is still checked (scene files may carry it)
        ({"render": {"shadow_pcf": 2}}, r"render: shadow_pcf \(ShadowMaps.pcf must be odd"),
        ({"render": {"clamp_at": "face"}}, r"render: clamp_at \(Output.clamp must be one of .*'face'"),
        ({"shadow": {"bias": 0.01}}, r"render.shadows: a \[shadow\] section is given but render.shadows is false"),
        ({"object": [{"box": [1, 0, 1]}]}, r"object\[0\].box: extents must be > 0"),
        ({"object": [{"quad": 2, "icosphere": 1}]}, r"object\[0\]: give exactly one of"),
        ({"object": [{"icosphere": 1, "normal": [0, 0, 1]}]}, r"object\[0\].normal: only applies to 'quad'"),
        ({"object": [{"quad": 1, "scale": 0}]}, r"object\[0\].scale: must not be 0"),
        ({"object": [{"quad": 1, "material": {"opacity": -0.1}}]}, r"object\[0\].material.opacity: must lie in"),
        ({"object": "box"}, r"object: must be an array of tables"),
    ],
)
def test_scene_validation_names_the_field(patch, msg):
    with pytest.raises(ds.SceneError, match=msg):
        ds.scene_from_dict(scene_dict(**patch), "test.toml")


def test_objects_scene_file_example():
    path = os.path.join(os.path.dirname(__file__), "..", "examples", "glass_and_shadows.toml")
    scene, opts = ds.load_scene(path)
    mats = scene.all_materials()
    assert len(mats) == 3 and mats[2].kay and not mats[1].kay
    ids = np.asarray(scene.mesh.material_ids)
    assert ids.shape == (scene.mesh.faces.shape[0],) and set(ids.tolist()) == {0, 1, 2}
    assert (ids == 1).sum() == 12 and (ids == 0).sum() == 2  # the box and the floor quad
    assert opts.transparency == ds.Transparency(layers=5, absorption=True) and opts.layers == 5
    assert opts.lighting.transmission and isinstance(opts.shadows, ds.ShadowMaps)
    np.testing.assert_allclose(np.asarray(mats[1].absorption), [0.3, 0.7, 1.6])
    V = np.asarray(scene.mesh.vertices)[np.unique(np.asarray(scene.mesh.faces)[ids == 2])]
    np.testing.assert_allclose(np.linalg.norm(V - [0.4, 0.0, -0.4], axis=1), 0.7, rtol=1e-12)  # radius, translate
    # With [mesh] + [material] and objects, the mesh is object 0.
    d = scene_dict(object=[{"quad": [2, 2], "translate": [0, 0, -2], "material": {"diffuse": 0.3}}])
    s2, _ = ds.scene_from_dict(d)
    assert len(s2.all_materials()) == 2 and float(s2.materials[0].diffuse[0]) == 0.3
    s3, _ = ds.scene_from_dict(scene_dict(render={"fog": "linear", "shadows": True}, shadow={"slope_bias": 2.0}))
    assert float(s3.shadow_slope_bias) == 2.0 and float(s3.shadow_bias) == float(
        ds.Scene(s3.mesh, s3.camera).shadow_bias
    )


def test_scene_file_roundtrip_and_fog_background(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text(
        '[mesh]\nicosphere = 2\n[camera]\neye = [0, 0, 3]\nwidth = 24\nheight = 16\n[render]\nfog = "exp"\n'
        '[fog]\ncolor = [0.2, 0.3, 0.4]\ndensity = 0.3\n[[light]]\ntype = "directional"\ndirection = [0, 0, -1]\n'
    )
    scene, opts = ds.load_scene(p)
    assert opts.fog == ds.FogModel("exp") and scene.camera.resolution == (16, 24)
    np.testing.assert_allclose(np.asarray(scene.background), [0.2, 0.3, 0.4])  # defaults to the fog colour
    img = np.asarray(jax.jit(ds.render, static_argnames="opts")(scene, opts))
    assert img.shape == (16, 24, 3) and np.isfinite(img).all()
    np.testing.assert_allclose(img[0, 0], [0.2, 0.3, 0.4])
    (tmp_path / "bad.toml").write_text("[mesh\n")
    with pytest.raises(ds.SceneError, match="not valid TOML"):
        ds.load_scene(tmp_path / "bad.toml")


def test_changing_numbers_never_recompiles():
    import equinox as eqx

    scene, opts = ds.scene_from_dict(scene_dict())

    @jax.jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def f(s):
        return ds.render(s, opts)

    f(scene)
    s2 = eqx.tree_at(
        lambda s: (s.material.diffuse, s.camera.eye, s.point.attenuation, s.fog.end),
        scene,
        (
            jnp.array([0.1, 0.2, 0.3]),
            jnp.array([0.3, 0.2, 2.5]),
            jnp.array([[1.0, 0.3, 0.1]]),
            jnp.asarray(9.0, jnp.float64),
        ),
    )
    out = f(s2)
    assert np.isfinite(np.asarray(out)).all()


def test_lambert_sphere_centre_closed_form():
    # Directional light along the view axis: the pixel at the image centre sees n = (0, 0, 1).
    d = scene_dict(
        render={"shading": "phong", "specular": "none"},
        light=[{"type": "directional", "direction": [0, 0, -1.0], "color": [0.8, 0.6, 0.4]}],
    )
    d.pop("fog")
    d["mesh"] = {"icosphere": 5}
    d["camera"] = {"eye": [0, 0, 3.0], "width": 33, "height": 33}
    d["material"] = {"ambient": 0.1, "diffuse": [0.5, 0.7, 0.9]}
    d["ambient_light"] = [0.2, 0.2, 0.2]
    scene, opts = ds.scene_from_dict(d)
    img = np.asarray(ds.render(scene, opts))
    expected = 0.1 * 0.2 + np.array([0.5, 0.7, 0.9]) * np.array([0.8, 0.6, 0.4]) * 1.0
    np.testing.assert_allclose(img[16, 16], expected, rtol=2e-3)


def test_cli_demo_and_errors(tmp_path):
    exe = [sys.executable, "-m", "fitting.cli"]
    out = tmp_path / "demo.png"
    r = subprocess.run(exe + ["demo", "--size", "48", "-o", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert out.exists() and "wrote" in r.stdout
    # The demo recovers all 13 parameters (k_a, k_d, k_s RGB, m, a1, a2, fog density).
    max_err = float(r.stdout.split("max rel. error ")[1].split(";")[0])
    assert max_err < 1e-4, r.stdout
    bad = tmp_path / "bad.toml"
    bad.write_text("[mesh]\nicosphere = 2\n")
    r = subprocess.run(exe + ["render", str(bad), "-o", str(tmp_path / "x.png")], capture_output=True, text=True)
    assert r.returncode == 3 and "camera: missing section" in r.stderr and "Traceback" not in r.stderr
    good = tmp_path / "good.toml"
    good.write_text("[mesh]\nicosphere = 1\n[camera]\neye = [0, 0, 3]\nwidth = 8\nheight = 8\n")
    before = out.read_bytes()
    r = subprocess.run(exe + ["render", str(good), "-o", str(out)], capture_output=True, text=True)
    assert r.returncode == 3 and "exists" in r.stderr and out.read_bytes() == before


def test_vertex_colours_are_read_decoded_and_merged(tmp_path):
    import trimesh

    from diffshade.color import decode

    tm = trimesh.creation.icosphere(subdivisions=1)
    codes = np.random.default_rng(2).integers(0, 256, (len(tm.vertices), 3))
    rgba = np.concatenate([codes, np.full((len(codes), 1), 255)], axis=1).astype(np.uint8)
    coloured = trimesh.Trimesh(tm.vertices, tm.faces, vertex_colors=rgba, process=False)
    coloured.export(tmp_path / "c.ply")
    m = ds.load_mesh(tmp_path / "c.ply")
    np.testing.assert_allclose(np.asarray(m.colors), decode(codes / 255.0, "srgb"), atol=1e-12)
    lin = ds.load_mesh(tmp_path / "c.ply", colors="linear")
    np.testing.assert_allclose(np.asarray(lin.colors), codes / 255.0, atol=1e-12)
    assert ds.load_mesh(tmp_path / "c.ply", colors="ignore").colors is None
    # a triangle soup (every face its own vertices, with its corners' colours): merged, each vertex
    # gets the mean colour of the copies it replaces, here all equal
    soup = trimesh.Trimesh(
        tm.vertices[tm.faces.reshape(-1)],
        np.arange(3 * len(tm.faces)).reshape(-1, 3),
        vertex_colors=rgba[tm.faces.reshape(-1)],
        process=False,
    )
    soup.export(tmp_path / "soup.ply")
    mm = ds.load_mesh(tmp_path / "soup.ply", "merged", colors="linear")
    assert mm.vertices.shape[0] == len(tm.vertices)
    # match merged vertices to the originals by position
    d = np.linalg.norm(np.asarray(mm.vertices)[:, None] - tm.vertices[None], axis=-1)
    np.testing.assert_allclose(np.asarray(mm.colors), codes[np.argmin(d, axis=1)] / 255.0, atol=1e-12)
    # a scene asking for vertex colours from a mesh without them is told so
    (tmp_path / "plain.ply").write_bytes(trimesh.Trimesh(tm.vertices, tm.faces).export(file_type="ply"))
    d = dict(
        ds.DEFAULT_SCENE,
        mesh={"path": str(tmp_path / "plain.ply")},
        render=dict(ds.DEFAULT_SCENE["render"], vertex_color="diffuse"),
    )
    with pytest.raises(ds.SceneError, match="render.vertex_color.*has no vertex colours"):
        ds.scene_from_dict(d)
    d["mesh"] = {"path": str(tmp_path / "c.ply"), "colors": "linear"}
    scene, opts = ds.scene_from_dict(d)
    assert opts.raster.vertex_color == "diffuse"
    np.testing.assert_allclose(np.asarray(scene.mesh.colors), codes / 255.0, atol=1e-12)
    d["mesh"] = {"path": str(tmp_path / "c.ply"), "colors": "cmyk"}
    with pytest.raises(ds.SceneError, match="mesh.colors"):
        ds.scene_from_dict(d)
