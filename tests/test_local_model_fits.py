"""The other local models in the renderer and in fits (docs/model.md §2, "The other local
models"): every model renders in every shading mode, with two-sided lighting, shadows and the
ray-traced mode, finite; a render's gradients in the models' parameters agree with finite
differences (float64, forward and reverse); noise-free fits recover k_d, k_s and the roughness
(k's linear, the roughness a nonlinear scalar of the variable projection) to 1e-4; a new
roughness does not recompile; scene files and bad values."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import float64
from jax.test_util import check_grads

import diffshade as ds
from fitting import Observations, fit

MODELS = [  # (diffuse_model, specular, the truth's fields, the fit's free roughness names)
    ("oren_nayar", "blinn", dict(diffuse_roughness=0.6, shininess=60.0), ["material.diffuse_roughness"]),
    ("lambert", "ggx", dict(roughness=0.25), ["material.roughness"]),
    ("lambert", "beckmann", dict(roughness=0.3), ["material.roughness"]),
    ("lambert", "ward", dict(roughness=0.15, roughness_y=0.4), ["material.roughness", "material.roughness_y"]),
]


def _scene(size=40, **render):
    """The default scene on a 320-face icosphere, without its fog."""
    d = {k: v for k, v in ds.DEFAULT_SCENE.items() if k != "fog"}
    d["camera"] = dict(d["camera"], width=size, height=size)
    d["mesh"] = {"icosphere": 2}
    d["render"] = dict(d["render"], fog="none", **render)
    return ds.scene_from_dict(d)


@pytest.mark.parametrize("shading", ["phong", "gouraud", "flat"])
def test_every_model_renders_finite_in_every_shading_mode(shading):
    for dm, spec, fields, _ in MODELS:
        scene, opts = _scene(24, shading=shading, specular=spec, diffuse_model=dm)
        scene = eqx.tree_at(lambda s: [getattr(s.material, k) for k in fields], scene, list(fields.values()))
        img = np.asarray(ds.render(scene, opts))
        assert np.isfinite(img).all() and img.max() > 0.1, (dm, spec, shading)


def test_the_models_with_shadows_rays_and_one_sided_lighting():
    for dm, spec, _, _ in MODELS:
        for keys in (dict(shadows=True), dict(ray_depth=1), dict(two_sided=False)):
            scene, opts = _scene(16, specular=spec, diffuse_model=dm, **keys)
            scene = eqx.tree_at(lambda s: s.material.mirror, scene, jnp.full(3, 0.2))
            img = np.asarray(ds.render(scene, opts))
            assert np.isfinite(img).all() and img.max() > 0.1, (dm, spec, keys)


def test_oren_nayar_at_zero_is_lambert_in_the_renderer():
    scene, opts = _scene(24, specular="ggx")
    on = opts.with_keys(diffuse_model="oren_nayar")
    flat = eqx.tree_at(lambda s: s.material.diffuse_roughness, scene, jnp.zeros_like(scene.material.diffuse_roughness))
    np.testing.assert_allclose(
        np.asarray(ds.render(flat, on)), np.asarray(ds.render(scene, opts)), rtol=1e-12, atol=1e-15
    )
    assert np.abs(np.asarray(ds.render(scene, on)) - np.asarray(ds.render(scene, opts))).max() > 0.01


def test_render_gradients_in_the_roughnesses_against_finite_differences():
    """float64 (the JAX stages), forward and reverse mode, at an 8² render."""
    for dm, spec, fields, _ in MODELS:
        scene, opts = _scene(8, specular=spec, diffuse_model=dm, backend="jax")
        scene = float64(scene)
        names = [k for k in fields if k != "shininess"]

        def f(*vals):
            s = eqx.tree_at(lambda s: [getattr(s.material, k) for k in names], scene, list(vals))
            return ds.render(s, opts)

        vals = tuple(jnp.asarray(fields[k], jnp.float64) for k in names)
        check_grads(f, vals, order=1, modes=("fwd", "rev"), atol=1e-5, rtol=1e-4)
        _, t = jax.jvp(f, vals, tuple(jnp.ones_like(x) for x in vals))
        assert float(jnp.abs(t).max()) > 1e-3, (dm, spec)  # (the 8² image sees the lobe change)


@pytest.mark.parametrize("dm,spec,fields,free", MODELS, ids=[f"{m[0]}-{m[1]}" for m in MODELS])
def test_noise_free_fits_recover_the_roughness(dm, spec, fields, free):
    """Targets from the truth; the fit starts at k_d 0.5, k_s 0.2 and each roughness off by a
    factor (0.5 for α, σ from 0.2); k_d and k_s are the linear block, the roughness nonlinear."""
    scene, opts = _scene(40, specular=spec, diffuse_model=dm)
    truth = eqx.tree_at(lambda s: [getattr(s.material, k) for k in fields], scene, list(fields.values()))
    target = np.asarray(ds.render(truth, opts))
    starts = {k: (0.2 if k == "diffuse_roughness" else 0.5 * v if k != "shininess" else v) for k, v in fields.items()}
    start = eqx.tree_at(
        lambda s: [s.material.diffuse, s.material.specular, *[getattr(s.material, k) for k in starts]],
        truth,
        [jnp.full(3, 0.5), jnp.full(3, 0.2), *starts.values()],
    )
    params = ["material.diffuse", "material.specular", *free]
    r = fit(start, opts, Observations(target), params)
    assert r.successful, (r.result, r.notes)
    want = np.r_[
        np.asarray(truth.material.diffuse), np.asarray(truth.material.specular), [fields[n.split(".")[1]] for n in free]
    ]
    np.testing.assert_allclose(np.asarray(r.values), want, rtol=1e-4)


def test_a_new_roughness_does_not_recompile():
    scene, opts = _scene(16, specular="ggx", diffuse_model="oren_nayar")
    f = jax.jit(lambda s: ds.render(s, opts))
    f(scene)
    n, dt = f._cache_size(), scene.material.roughness.dtype
    for a, s in ((0.1, 0.9), (0.7, 0.0)):
        f(
            eqx.tree_at(
                lambda x: (x.material.roughness, x.material.diffuse_roughness),
                scene,
                (jnp.asarray(a, dt), jnp.asarray(s, dt)),
            )
        )
    assert f._cache_size() == n


def test_scene_files_and_bad_values():
    d = {k: v for k, v in ds.DEFAULT_SCENE.items() if k != "fog"}
    d["render"] = dict(d["render"], fog="none", specular="ward", diffuse_model="oren_nayar", masking="v_cavity")
    d["material"] = dict(d["material"], roughness=0.2, roughness_y=0.5, diffuse_roughness=0.4, tangent=[0, 1, 0])
    scene, opts = ds.scene_from_dict(d)
    assert opts.lighting.specular == "ward" and opts.lighting.masking == "v_cavity"
    assert float(scene.material.roughness_y) == 0.5 and np.asarray(scene.material.tangent).tolist() == [0, 1, 0]
    for key, val, msg in (
        ("roughness", 0.0, "material.roughness"),
        ("roughness", 1.5, "material.roughness"),
        ("diffuse_roughness", -0.1, "material.diffuse_roughness"),
        ("tangent", [0, 0, 0], "material.tangent"),
    ):
        bad = dict(d, material=dict(d["material"], **{key: val}))
        with pytest.raises(ds.SceneError, match=msg):
            ds.scene_from_dict(bad)
    with pytest.raises(ds.SceneError, match="specular"):
        ds.scene_from_dict(dict(d, render=dict(d["render"], specular="cook")))
    with pytest.raises(ValueError, match="roughness"):
        ds.check_scene(eqx.tree_at(lambda s: s.material.roughness, scene, jnp.asarray(-0.2)))


def test_compare_models_ranks_the_ladder_and_picks_the_truth():
    """A GGX highlight (α 0.3) in an 8-bit image, fitted from the usual guess (Blinn–Phong,
    m' 40): the ladder's variants each with their lobe's start converted and parameters free,
    GGX the supported model by ΔBIC > 10 over Blinn–Phong and Phong, each with its time."""
    from fitting import compare_models, model_variants

    scene, opts = _scene(32, specular="ggx")
    truth = eqx.tree_at(lambda s: s.material.roughness, scene, jnp.asarray(0.3, scene.material.roughness.dtype))
    rng = np.random.default_rng(3)
    clean = np.asarray(ds.render(truth, opts))
    target = np.round(np.clip(clean + rng.normal(0, 2 / 255, clean.shape), 0, 1) * 255) / 255
    obs = Observations(target, saturation=1.0, quantum=1 / 255)
    guess = opts.with_keys(specular="blinn")
    start = eqx.tree_at(lambda s: s.material.shininess, truth, jnp.asarray(40.0, truth.material.shininess.dtype))
    free = ["material.diffuse", "material.specular", "material.shininess"]
    assert [v[0] for v in model_variants(start, guess, free)] == [
        "as given",
        "no specular",
        "phong",
        "beckmann",
        "ggx",
        "ward",
        *[f"oren_nayar + {m}" for m in ("phong", "blinn", "beckmann", "ggx", "ward")],
    ]
    variants = model_variants(start, guess, free, diffuse=("lambert",), specular=("phong", "blinn", "ggx"))
    assert [v[0] for v in variants] == ["as given", "no specular", "phong", "ggx"]
    ggx = dict((v[0], v) for v in variants)["ggx"]
    assert ggx[2] == ["material.diffuse", "material.specular", "material.roughness"]
    assert float(ggx[3].material.roughness) == pytest.approx(np.sqrt(2 / 42))  # m' = 2/α² − 2
    scores = compare_models(start, guess, obs, free, variants=variants, intervals=False)
    by = {m.name: m for m in scores}
    assert scores[0].name == "ggx", [(m.name, m.bic) for m in scores]
    assert by["as given"].bic - by["ggx"].bic > 10 and by["phong"].bic - by["ggx"].bic > 10
    assert by["ggx"].fit.successful and abs(by["ggx"].fit.values[-1] - 0.3) < 3 * by["ggx"].fit.stderr[-1]
    assert all(m.seconds > 0 for m in scores)


def test_a_roughness_map_multiplies_the_roughness_per_pixel():
    """A constant roughness map c renders as the roughness α·c; a varying one differs from it;
    Gouraud and flat shading refuse it (they light vertices or faces); MTL's map_Pr round trips."""
    import dataclasses

    scene, opts = _scene(24, specular="ggx")
    v = np.asarray(scene.mesh.vertices)
    uv = np.stack([np.arctan2(v[:, 1], v[:, 0]) / (2 * np.pi) + 0.5, 0.5 + 0.5 * v[:, 2]], 1)
    mesh = ds.Mesh(scene.mesh.vertices, scene.mesh.faces, normals=scene.mesh.normals, uv=uv)
    a = 0.4
    flat = ds.Texture(np.full((4, 4, 1), 0.5))
    mapped = dataclasses.replace(
        scene, mesh=mesh, material=dataclasses.replace(scene.material, roughness=a, roughness_map=flat)
    )
    plain = dataclasses.replace(scene, mesh=mesh, material=dataclasses.replace(scene.material, roughness=a * 0.5))
    np.testing.assert_allclose(
        np.asarray(ds.render(mapped, opts)), np.asarray(ds.render(plain, opts)), rtol=1e-12, atol=1e-15
    )
    ramp = ds.Texture(np.linspace(0.2, 1.0, 16).reshape(4, 4, 1))
    varied = dataclasses.replace(mapped, material=dataclasses.replace(mapped.material, roughness_map=ramp))
    assert np.abs(np.asarray(ds.render(varied, opts)) - np.asarray(ds.render(plain, opts))).max() > 0.01
    with pytest.raises(ValueError, match="a roughness map needs Phong shading"):
        ds.render(varied, opts.with_keys(shading="gouraud"))
    # not read by a model without a roughness: Blinn-Phong renders as without the map
    blinn = opts.with_keys(specular="blinn")
    np.testing.assert_array_equal(np.asarray(ds.render(varied, blinn)), np.asarray(ds.render(plain, blinn)))


def test_a_roughness_map_round_trips_through_mtl(tmp_path):
    ramp = ds.Texture(np.linspace(0.2, 1.0, 16).reshape(4, 4, 1))
    m = ds.Material(roughness=0.5, roughness_map=ramp)
    out = ds.save_material(tmp_path / "r.mtl", m, ds.RenderOptions.from_keys(specular="beckmann"))
    assert "map_Pr r_material_roughness.png" in out.read_text()
    back = ds.load_material(out)
    np.testing.assert_allclose(np.asarray(back.roughness_map.texels), np.asarray(ramp.texels), atol=2e-5)


def test_wards_tangent_from_the_texture_coordinates():
    """Lighting.tangent = "uv": ∂P/∂u of the mesh's coordinates. On a sphere whose u is the
    longitude, ∂P/∂u is the east direction at every vertex (away from the poles and the seam);
    isotropic Ward renders the same with either frame, anisotropic it does not; every shading
    mode renders finite; a mesh without coordinates is refused by name."""
    import dataclasses

    from diffshade._surface import uv_tangents

    scene, opts = _scene(24, specular="ward")
    v = np.asarray(scene.mesh.vertices)
    uv = np.stack([np.arctan2(v[:, 1], v[:, 0]) / (2 * np.pi) + 0.5, 0.5 + 0.5 * v[:, 2]], 1)
    mesh = ds.Mesh(scene.mesh.vertices, scene.mesh.faces, normals=scene.mesh.normals, uv=uv)
    t = np.asarray(uv_tangents(mesh))
    east = np.stack([-v[:, 1], v[:, 0], np.zeros(len(v))], 1)
    east /= np.maximum(np.linalg.norm(east, axis=1, keepdims=True), 1e-12)
    away = np.abs(v[:, 2]) < 0.9  # (not at the poles, nor on the seam where u wraps)
    seam = np.abs(np.arctan2(v[:, 1], v[:, 0])) > 2.8
    cos = np.sum(t * east, 1)[away & ~seam]
    assert np.median(cos) > 0.99 and cos.min() > 0.9, np.sort(cos)[:5]
    mat = dataclasses.replace(scene.material, roughness=0.1, roughness_y=0.4)
    s = dataclasses.replace(scene, mesh=mesh, material=mat)
    uvo = opts.with_keys(tangent="uv")
    for shading in ("phong", "gouraud", "flat"):
        img = np.asarray(ds.render(s, uvo.with_keys(shading=shading)))
        assert np.isfinite(img).all() and img.max() > 0.1
    # isotropic (α_x = α_y) no frame matters: the two images agree; anisotropic they differ
    a, b = np.asarray(ds.render(s, uvo)), np.asarray(ds.render(s, opts))  # (the tangent +x everywhere)
    assert np.abs(a - b).max() > 1e-3
    iso = dataclasses.replace(s, material=dataclasses.replace(mat, roughness_y=0.1))
    np.testing.assert_allclose(
        np.asarray(ds.render(iso, uvo)), np.asarray(ds.render(iso, opts)), rtol=1e-10, atol=1e-12
    )
    with pytest.raises(ValueError, match="needs Mesh.uv"):
        ds.render(scene, uvo)


def test_not_told_apart_names_the_models_within_two_of_the_lowest_bic():
    from fitting import ModelScore, not_told_apart
    from fitting._models import ranked

    def score(name, bic, k):
        return ModelScore(name, None, ["x"] * k, None, 100, k, 1.0, bic, bic)

    scores = ranked(
        [score("ggx", 10.0, 3), score("beckmann", 11.5, 3), score("blinn", 30.0, 3), score("ward", 10.5, 4)]
    )
    assert scores[0].name == "ggx"
    assert [m.name for m in not_told_apart(scores)] == ["ward", "beckmann"]
    # the simplest within 2 is the one named, even if another is lower
    scores = ranked([score("ward", 9.0, 4), score("ggx", 10.0, 3)])
    assert scores[0].name == "ggx" and [m.name for m in not_told_apart(scores)] == ["ward"]


def test_wards_tangent_direction_is_fitted_by_name():
    """material.tangent is a direction (two tilt angles, as a light's): a brushed sphere's
    anisotropic highlight gives it back, with both roughnesses, noise-free to 1e-4 (its angle)."""
    import dataclasses

    scene, opts = _scene(40, specular="ward")
    t_true = np.array([1.0, 0.4, -0.2]) / np.linalg.norm([1.0, 0.4, -0.2])
    truth = dataclasses.replace(
        scene, material=dataclasses.replace(scene.material, roughness=0.12, roughness_y=0.35, tangent=t_true)
    )
    target = np.asarray(ds.render(truth, opts))
    start = dataclasses.replace(
        truth, material=dataclasses.replace(truth.material, roughness=0.2, roughness_y=0.25, tangent=[1.0, 0.0, 0.0])
    )
    free = ["material.diffuse", "material.specular", "material.roughness", "material.roughness_y", "material.tangent"]
    r = fit(start, opts, Observations(target), free)
    assert r.successful, (r.result, r.notes)
    from fitting import ParamSet

    fitted = ParamSet(free, start).apply(start, jnp.asarray(r.values, start.mesh.vertices.dtype))
    t = np.asarray(fitted.material.tangent, np.float64)
    t = t / np.linalg.norm(t)
    assert np.degrees(np.arccos(min(1.0, abs(float(t @ t_true))))) < 1e-2
    np.testing.assert_allclose(np.asarray(r.values)[6:8], [0.12, 0.35], rtol=1e-4)
