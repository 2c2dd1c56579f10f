"""Transparency, Kay's opacity, Bouguer absorption, directed transmission and shadow maps
(docs/model.md §2, §5; issue 5): closed forms, an independent numpy z-buffer with transparency
buffers (the seeds' algorithm), gradients against finite differences, hard cases."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffshade as ds
from diffshade import _shade as S

F64 = jnp.float64


def camera(eye, target, size, fov=30.0, up=(0.0, 1.0, 0.0)):
    return ds.Camera(eye=eye, target=target, up=up, fov_y=fov, near=0.5, far=50.0, width=size, height=size)


def rays(cam: ds.Camera):
    """World-space unit directions ``[H, W, 3]`` through the pixel centres (written from the
    OpenGL conventions, not from the rasterizer)."""
    eye, target, up = (np.asarray(x, np.float64) for x in (cam.eye, cam.target, cam.up))
    f = (target - eye) / np.linalg.norm(target - eye)
    s = np.cross(f, up)
    s /= np.linalg.norm(s)
    u = np.cross(s, f)
    th = np.tan(np.deg2rad(float(cam.fov_y)) / 2)
    W, H = cam.width, cam.height
    x = (2 * (np.arange(W) + 0.5) / W - 1) * th * W / H
    y = (1 - 2 * (np.arange(H) + 0.5) / H) * th
    d = f + x[None, :, None] * s + y[:, None, None] * u
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


@functools.cache
def _jit_render(opts):
    return jax.jit(lambda s: ds.render(s, opts))


def with_(scene, **kw):
    """``scene`` with some fields replaced."""
    return dataclasses.replace(scene, **kw)


def render(scene, opts):
    return np.asarray(_jit_render(opts)(scene))


def dlight(direction, color=1.0):
    return ds.DirectionalLights(
        color=jnp.broadcast_to(jnp.asarray(color, F64), (3,)), direction=direction, ambient=[0.0, 0.0, 0.0]
    )


# --- closed forms ----------------------------------------------------------------------------


def test_plane_with_opacity_over_background():
    cam = camera([0, 0, 3], [0, 0, 0], 24, fov=50)
    mat = ds.Material(ambient=(0.1, 0.2, 0.3), diffuse=(0.6, 0.3, 0.1), specular=0.0, opacity=0.35)
    bg = np.array([0.2, 0.4, 0.9])
    scene = ds.Scene(
        mesh=ds.quad((2, 2)), camera=cam, material=mat, directional=dlight([0, 0, -1]), ambient_light=0.5, background=bg
    )
    opts = ds.RenderOptions(lighting=ds.Lighting(specular="none"), transparency=ds.Transparency(layers=2))
    img = render(scene, opts)
    d = rays(cam)
    hit = 3.0 * d / -d[..., 2:3]  # ray to the plane z = 0
    inside = (np.abs(hit[..., 0]) < 0.95) & (np.abs(hit[..., 1]) < 0.95)
    outside = (np.abs(hit[..., 0]) > 1.05) | (np.abs(hit[..., 1]) > 1.05)
    C = np.array([0.1, 0.2, 0.3]) * 0.5 + np.array([0.6, 0.3, 0.1])
    np.testing.assert_allclose(img[inside], np.broadcast_to(0.35 * C + 0.65 * bg, img[inside].shape), atol=1e-12)
    np.testing.assert_allclose(img[outside], np.broadcast_to(bg, img[outside].shape), atol=0)
    assert inside.sum() > 100 and outside.sum() > 50
    # t = 1 is the opaque render; t = 0 shows the background alone.
    for t, want in ((1.0, C), (0.0, bg)):
        s = ds.Scene(
            mesh=scene.mesh,
            camera=cam,
            material=ds.Material(ambient=(0.1, 0.2, 0.3), diffuse=(0.6, 0.3, 0.1), specular=0.0, opacity=t),
            directional=scene.directional,
            ambient_light=0.5,
            background=bg,
        )
        np.testing.assert_allclose(render(s, opts)[inside], np.broadcast_to(want, img[inside].shape), atol=1e-12)


def slab_scene(mu, size=24, thickness=0.6, opacity=0.0):
    slab = ds.box((1.6, 1.6, thickness), (0, 0, 0.5))
    plane = ds.quad((6, 6), (0, 0, -1))
    mats = (
        ds.Material(ambient=0.2, diffuse=(0.9, 0.8, 0.7), specular=0.0),
        ds.Material(diffuse=(0.1, 0.9, 0.1), specular=0.0, opacity=opacity, absorption=mu),
    )
    cam = camera([0.3, 0.2, 4], [0, 0, 0], size, fov=25)
    return ds.Scene(
        mesh=ds.combine(plane, slab),
        camera=cam,
        material=mats[0],
        materials=mats[1:],
        directional=dlight([0, 0, -1]),
        ambient_light=1.0,
        background=0.0,
    )


def test_slab_absorption_bouguer():
    mu = np.array([0.3, 0.8, 1.5])
    scene = slab_scene(mu)
    opts = ds.RenderOptions(
        lighting=ds.Lighting(specular="none"), transparency=ds.Transparency(layers=3, absorption=True)
    )
    img = render(scene, opts)
    cam = scene.camera
    d = rays(cam)
    eye = np.asarray(cam.eye)
    # Where the ray enters the slab's front face z = 0.8 and leaves through its back z = 0.2,
    # well inside the faces' square:
    front = eye + d * ((0.8 - eye[2]) / d[..., 2:3])
    back = eye + d * ((0.2 - eye[2]) / d[..., 2:3])
    inside = np.all(np.abs(front[..., :2]) < 0.75, -1) & np.all(np.abs(back[..., :2]) < 0.75, -1)
    ell = 0.6 / np.abs(d[..., 2])
    C = 0.2 + np.array([0.9, 0.8, 0.7])
    want = np.exp(-mu * ell[..., None]) * C
    np.testing.assert_allclose(img[inside], want[inside], rtol=1e-10)
    assert inside.sum() > 100
    # Elsewhere the plane is seen directly.
    plane_only = np.all(np.abs(front[..., :2]) > 0.85, -1) & np.all(np.abs(back[..., :2]) > 0.85, -1)
    np.testing.assert_allclose(img[plane_only], np.broadcast_to(C, img[plane_only].shape), rtol=1e-12)
    # mu = 0: the slab is invisible.
    img0 = render(slab_scene(np.zeros(3)), opts)
    np.testing.assert_allclose(img0[inside], np.broadcast_to(C, img0[inside].shape), rtol=1e-12)


@pytest.mark.parametrize("shading", ["phong", "gouraud"])
def test_kay_opacity_on_sphere_centre_and_silhouette(shading):
    # A distant camera (nearly orthographic), so that |n_z| reaches close to 0 at the silhouette.
    cam = camera([0, 0, 40], [0, 0, 0], 48, fov=3.4)
    mat = ds.Material(emission=1.0, kay=True, kay_min=0.9, kay_max=0.2, kay_power=2.0)
    scene = ds.Scene(mesh=ds.icosphere(5), camera=cam, material=mat, background=0.0)
    opts = ds.RenderOptions(
        raster=ds.Raster(shading=shading),
        lighting=ds.Lighting(ambient=False, diffuse=False, specular="none", emission=True),
        transparency=ds.Transparency(layers=1),
    )
    t = render(scene, opts)[..., 0]
    d = rays(cam)
    eye = np.asarray(cam.eye)
    b = np.einsum("hwc,c->hw", d, eye)
    disc = b * b - (eye @ eye - 1.0)
    hitp = disc > 0.005  # |n_z| > 0.07
    X = eye + d * (-b - np.sqrt(np.where(hitp, disc, 0)))[..., None]
    nz = np.abs(X[..., 2])  # the view axis is world z here
    want = 0.9 + (0.2 - 0.9) * (1 - (1 - nz) ** 2)
    # Vertex normals of a 10,242-vertex icosphere, interpolated: within 2e-3 of the sphere's.
    # The mesh is a 20,480-face icosphere. Its area-weighted vertex normals (docs/model.md §4) are up
    # to 2.8e-3 off the radial direction (measured below), which moves t by |dt/dn_z| = 1.4 (1 - n_z)
    # times that; and near the silhouette the ray meets the faceted surface up to
    # sagitta/|n_z| (1.5e-4 / |n_z|) away from the sphere's point.
    mesh = scene.mesh
    off = np.abs(np.asarray(mesh.vertex_normals()) - np.asarray(mesh.vertices)).max()
    assert off < 2.8e-3
    tol = 1.4 * (1 - nz) * off + 3e-4 / nz + 1e-4
    assert np.all(np.abs(t - want)[hitp] < tol[hitp])
    centre = np.unravel_index(np.argmax(np.where(hitp, nz, 0)), nz.shape)
    assert abs(t[centre] - 0.2) < 1e-3  # face-on: t_max
    rim = hitp & (nz < 0.2)  # there t > 0.9 - 0.7 (1 - 0.8^2) = 0.648, rising to t_min = 0.9
    assert rim.sum() > 20 and np.all(t[rim] > 0.64) and t[hitp].max() > 0.7
    # The function itself at the ends of |n_z|.
    np.testing.assert_allclose(S.kay_opacity(jnp.array([0.0, 1.0, -1.0]), 0.9, 0.2, 2.0), [0.9, 0.2, 0.2], atol=1e-15)


def transmission_scene(light_dir, fresnel="none", m=20.0, ior=1.5, size=16):
    cam = camera([0, 0, 3], [0, 0, 0], size, fov=20)
    mat = ds.Material(ambient=0.0, diffuse=0.0, specular=0.0, shininess=m, ior=ior, transmission=(0.5, 0.7, 0.9))
    scene = ds.Scene(mesh=ds.quad((3, 3)), camera=cam, material=mat, directional=dlight(light_dir, (1.0, 0.8, 0.6)))
    opts = ds.RenderOptions(
        lighting=ds.Lighting(transmission=True, ambient=False, diffuse=False, specular="none", fresnel=fresnel)
    )
    return scene, opts


@pytest.mark.parametrize("fresnel", ["none", "dielectric", "schlick"])
def test_transmission_at_normal_incidence(fresnel):
    scene, opts = transmission_scene([0, 0, 1], fresnel)  # light behind the plane, shining at the eye
    img = render(scene, opts)
    d = rays(scene.camera)
    v = -d
    weight = 1.0 if fresnel == "none" else 1.0 - ((1.5 - 1) / (1.5 + 1)) ** 2  # 1 - F(0) = 0.96
    want = weight * np.array([0.5, 0.7, 0.9]) * np.array([1.0, 0.8, 0.6]) * v[..., 2:3] ** 20  # f = n
    np.testing.assert_allclose(img, want, rtol=1e-10)


def test_transmission_at_the_critical_angle():
    eta = 1.5
    crit = np.arcsin(1 / eta)
    for theta, total_internal in ((crit - 0.02, False), (crit + 0.002, True)):
        l = np.array([np.sin(theta), 0.0, -np.cos(theta)])  # to the light, behind the plane
        scene, opts = transmission_scene(-l, m=1.0)
        img = render(scene, opts)
        if total_internal:
            assert np.all(img == 0)
            continue
        # Snell from inside (eta) to the eye's side: f = (-eta sin theta, 0, cos theta_out).
        f = np.array([-eta * np.sin(theta), 0.0, np.sqrt(1 - (eta * np.sin(theta)) ** 2)])
        v = -rays(scene.camera)
        want = np.array([0.5, 0.7, 0.9]) * np.array([1.0, 0.8, 0.6]) * np.maximum(v @ f, 0)[..., None]
        np.testing.assert_allclose(img, want, rtol=1e-9, atol=1e-15)
        assert img.max() > 0.1
    # With the Fresnel split the transmitted fraction falls continuously to 0 at the critical angle.
    n = S.vec(jnp.array([[0.0, 0.0, 1.0]]))
    v = S.vec(jnp.array([[-1.0, 0.0, 0.0]]))  # along the grazing refracted ray
    vals = []
    for dt in (1e-2, 1e-4, 1e-6):
        l = S.vec(jnp.array([[np.sin(crit - dt), 0.0, -np.cos(crit - dt)]]))
        vals.append(float(S.directed_transmission(n, l, v, 1.0, eta, False, "dielectric")[0]))
    assert vals[0] > vals[1] > vals[2] >= 0 and vals[2] < 1e-2


def test_transmission_back_face_uses_inverse_index():
    # Seen from inside (a back face), light from outside enters a denser medium: no critical angle.
    n = S.vec(jnp.array([[0.0, 0.0, 1.0]]))
    l = S.vec(jnp.array([[np.sin(1.2), 0.0, -np.cos(1.2)]]))  # 69 degrees, beyond 41.8 from inside
    v = S.vec(jnp.array([[0.0, 0.0, 1.0]]))
    assert float(S.directed_transmission(n, l, v, 1.0, 1.5, False)[0]) == 0.0
    got = float(S.directed_transmission(n, l, v, 1.0, 1.5, True)[0])
    np.testing.assert_allclose(got, np.sqrt(1 - (np.sin(1.2) / 1.5) ** 2), rtol=1e-12)


# --- shadows ---------------------------------------------------------------------------------

SPHERE_C, SPHERE_R = np.array([0.1, 0.8, 0.0]), 0.5


def shadow_scene(kind, size=48, pcf=1, shading="phong"):
    plane = ds.quad((5, 5), (0, 0, 0), (0, 1, 0))
    sph = ds.icosphere(3, SPHERE_R)
    sph = ds.Mesh(vertices=sph.vertices + SPHERE_C, faces=sph.faces)
    cam = camera([0, 3.5, 3.0], [0, 0, 0], size, fov=45)
    mats = (ds.Material(ambient=0.3, diffuse=0.6, specular=0.0), ds.Material(ambient=0.3, diffuse=0.6, specular=0.0))
    lights = {}
    if kind == "directional":
        lights["directional"] = dlight([0.3, -1.0, 0.2])
    elif kind == "point":
        lights["point"] = ds.PointLights(
            color=[1.0, 1.0, 1.0], position=[-0.4, 2.6, 0.5], attenuation=[1, 0, 0], ambient=[0, 0, 0]
        )
    else:
        lights["spot"] = ds.SpotLights(
            color=[1.0, 1.0, 1.0],
            position=[0.6, 2.8, -0.4],
            attenuation=[1, 0, 0],
            ambient=[0, 0, 0],
            axis=[-0.2, -1, 0.1],
            cutoff=60.0,
            exponent=0.0,
            edge=0.0,
        )
    scene = ds.Scene(
        mesh=ds.combine(plane, sph),
        camera=cam,
        material=mats[0],
        materials=mats[1:],
        ambient_light=1.0,
        background=0.0,
        **lights,
    )
    opts = ds.RenderOptions(
        raster=ds.Raster(shading=shading), lighting=ds.Lighting(specular="none"), shadows=ds.ShadowMaps(pcf=pcf)
    )
    return scene, opts


def _to_light(kind, scene, X):
    """Unit vectors from plane points ``X`` to the light, and the distance to it (inf for a
    directional light)."""
    if kind == "directional":
        l = -np.asarray(scene.directional.direction[0])
        l = l / np.linalg.norm(l)
        return np.broadcast_to(l, X.shape), np.full(X.shape[:-1], np.inf)
    pos = np.asarray((scene.point if kind == "point" else scene.spot).position[0])
    L = pos - X
    dist = np.linalg.norm(L, axis=-1)
    return L / dist[..., None], dist


@pytest.mark.parametrize(
    "kind,pcf,shading",
    [
        ("directional", 1, "phong"),
        ("directional", 3, "phong"),
        ("point", 1, "phong"),
        ("point", 3, "phong"),
        ("spot", 1, "phong"),
        ("spot", 3, "phong"),
        ("directional", 1, "gouraud"),
        ("directional", 1, "flat"),
    ],
)
def test_sphere_shadow_on_plane(kind, pcf, shading):
    """Shadowed exactly where the segment to the light meets the sphere (away from the edge);
    Gouraud and flat shading multiply each light's interpolated (per-face) terms by S per pixel."""
    scene, opts = shadow_scene(kind, pcf=pcf, shading=shading)
    img = render(scene, opts)[..., 0]
    cam = scene.camera
    d = rays(cam)
    eye = np.asarray(cam.eye)
    X = eye + d * (-eye[1] / d[..., 1])[..., None]  # hit on the plane y = 0
    # Pixels whose camera ray passes the sphere (well clear of it) see the plane.
    oc = SPHERE_C - eye
    cam_clear = np.linalg.norm(np.cross(d, oc), axis=-1) > SPHERE_R + 0.08
    on_plane = cam_clear & np.all(np.abs(X[..., [0, 2]]) < 2.3, -1)
    # The analytic shadow: does the segment from X to the light meet the sphere?
    l, dist = _to_light(kind, scene, X)
    cx = SPHERE_C - X
    along = np.einsum("hwc,hwc->hw", cx, l)
    miss = np.linalg.norm(cx - along[..., None] * l, axis=-1)
    shadowed = (along > 0) & (along < dist) & (miss < SPHERE_R - 0.06)
    lit = (miss > SPHERE_R + 0.06) | (along < 0)
    ndl = np.maximum(l[..., 1], 0)
    att = 1.0
    if kind == "spot":
        axis = np.array([-0.2, -1, 0.1]) / np.linalg.norm([-0.2, -1, 0.1])
        inside_cone = np.einsum("hwc,c->hw", -l, axis) > np.cos(np.deg2rad(60.0)) + 0.02
        on_plane &= inside_cone
    ambient = 0.3
    full = ambient + 0.6 * ndl * att
    sel_s, sel_l = on_plane & shadowed, on_plane & lit & (ndl > 0.05)
    assert sel_s.sum() > 15 and sel_l.sum() > 200
    np.testing.assert_allclose(img[sel_s], ambient, atol=1e-6)
    np.testing.assert_allclose(img[sel_l], full[sel_l], rtol=1e-5)


def test_material_that_casts_no_shadow():
    scene, opts = shadow_scene("directional", size=24)
    glass = ds.Material(ambient=0.3, diffuse=0.6, specular=0.0, casts_shadow=False)
    lit_all = with_(scene, materials=(glass,))
    plane = np.asarray(_jit_render(opts.replace(shadows=None))(scene))
    a, b = render(scene, opts), render(lit_all, opts)
    assert (np.abs(a - plane).max(-1) > 0.05).sum() > 10  # the sphere's shadow
    np.testing.assert_allclose(b, plane, atol=1e-12)  # no shadow without its faces in the map


def test_shadows_off_cost_nothing_and_bias_changes_do_not_recompile():
    scene, opts = shadow_scene("directional", size=16)
    f = jax.jit(lambda s: ds.render(s, opts))
    f(scene)
    n = f._cache_size()
    for bias in (0.0, 0.01, 0.1):
        s = with_(scene, shadow_bias=bias)
        assert np.all(np.isfinite(np.asarray(f(s))))
    assert f._cache_size() == n
    plain = jax.jit(lambda s: ds.render(s, opts.replace(shadows=None))).lower(scene).as_text()
    with_shadows = jax.jit(f).lower(scene).as_text()
    # Off, the program rasterizes once (the camera); on, once more per light (the native kernel
    # is a custom call; the portable backend would show as a loop instead).
    if ds._raster.resolve_backend("auto") == "native":
        assert plain.count("custom_call") == 1 and with_shadows.count("custom_call") == 2
    assert len(plain) < 0.7 * len(with_shadows)


def test_fragment_exactly_at_shadow_map_depth():
    # Zero bias: the lit plane is its own occluder in the map (receiver depth = stored depth up to
    # rounding). Values and gradients stay finite, and it is lit nearly everywhere. Which pixels
    # are lit is decided by rounding, so two separately fused evaluations of the primal may light
    # different pixels (measured: jacfwd and grad in one program under the suite's XLA flags,
    # 773.6 against 774.3); forward and reverse mode are compared on one linearisation, whose
    # primal both share.
    scene, opts = shadow_scene("directional", size=24)
    scene = with_(scene, shadow_bias=0.0, shadow_slope_bias=0.0)

    def f(c):
        s = with_(scene, directional=dlight([0.3, -1.0, 0.2], c))
        return ds.render(s, opts).sum()

    @jax.jit
    def both(c):
        y, f_jvp = jax.linearize(f, c)
        return y, f_jvp(1.0), jax.linear_transpose(f_jvp, c)(1.0)[0]

    y, g, gr = both(1.0)
    assert np.isfinite(y) and np.isfinite(g) and np.isfinite(gr)
    np.testing.assert_allclose(g, gr, rtol=1e-10)
    total = jax.jit(f)
    lit, unlit = float(total(1.0)), float(total(0.0))
    assert 0.9 * (lit - unlit) < g < 1.1 * (lit - unlit)  # linear in c, lit nearly everywhere (by any rounding)


# --- the seeds' z-buffer with transparency buffers, plainly in numpy -----------------------------


def _ray_hits(V, F, eye, d):
    """Möller–Trumbore for every pixel ray and triangle: distances ``[T, H, W]`` (inf = miss)."""
    out = np.full((len(F),) + d.shape[:2], np.inf)
    for k, f in enumerate(F):
        a, b, c = V[f]
        e1, e2 = b - a, c - a
        p = np.cross(d, e2)
        det = p @ e1
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1 / np.where(ok, det, 1), 0)
        s = eye - a
        u = (p @ s) * inv
        q = np.cross(s, e1)
        v = np.einsum("hwc,c->hw", d, q) * inv
        t = (q @ e2) * inv
        hit = ok & (u > 0) & (v > 0) & (u + v < 1) & (t > 0)
        out[k] = np.where(hit, t, np.inf)
    return out


def seed_zbuffer_with_transparency(V, F, face_color, face_t, eye, d, background, sort_transparent=False):
    """The seeds' algorithm (004): an opaque frame buffer with its z-buffer; transparent polygons
    nearer than the opaque one accumulate into a transparency-weight buffer and a
    transparency-intensity buffer; the two are combined at the end.

    Read literally, the seed weights the intensity twice (``I_bn = I_b0 t_b0 + I_c t_c``, then
    ``t_b0 I_b0`` again when combining); the buffers below keep the weighted intensity and the
    accumulated weight once each, which is the recursion ``I = t I_1 + (1 - t) I_2`` for one
    transparent surface per pixel. ``sort_transparent`` processes the transparent list front to
    back with the recursive weights, which is exact for any number of them.
    """
    depth = _ray_hits(V, F, eye, d)
    H, W = d.shape[:2]
    zbuf = np.full((H, W), np.inf)
    frame = np.broadcast_to(background, (H, W, 3)).copy()
    for k in range(len(F)):
        if face_t[k] >= 1.0:
            closer = depth[k] < zbuf
            zbuf = np.where(closer, depth[k], zbuf)
            frame[closer] = face_color[k]
    t_buf = np.zeros((H, W))
    i_buf = np.zeros((H, W, 3))
    order = [k for k in range(len(F)) if face_t[k] < 1.0]
    for j in range(H):
        for i in range(W):
            ks = [k for k in order if depth[k, j, i] < zbuf[j, i]]
            if sort_transparent:
                ks.sort(key=lambda k: depth[k, j, i])
            for k in ks:
                i_buf[j, i] += (
                    (1 - t_buf[j, i]) * face_t[k] * face_color[k] if sort_transparent else face_t[k] * face_color[k]
                )
                t_buf[j, i] = (
                    t_buf[j, i] + (1 - t_buf[j, i]) * face_t[k] if sort_transparent else t_buf[j, i] + face_t[k]
                )
    return i_buf + (1 - t_buf)[..., None] * frame


def _panes_scene(size, n_panes, opaque_sphere=True):
    rng = np.random.default_rng(5)
    meshes, mats = [], []
    if opaque_sphere:
        sph = ds.icosphere(2, 0.7)
        meshes.append(ds.Mesh(vertices=sph.vertices + np.array([0.1, -0.1, -1.5]), faces=sph.faces))
        mats.append(ds.Material(ambient=0.3, diffuse=(0.8, 0.3, 0.2), specular=0.0))
    for p in range(n_panes):
        normal = np.array([0.15 * (p - 1), 0.1, 1.0])
        meshes.append(ds.quad((2.0 - 0.3 * p, 1.6), (0.2 * p - 0.2, 0.1 * p, -0.3 + 0.45 * p), normal))
        mats.append(ds.Material(ambient=0.3, diffuse=rng.uniform(0.2, 0.9, 3), specular=0.0, opacity=0.25 + 0.2 * p))
    cam = camera([0.2, 0.3, 4.0], [0, 0, -0.5], size, fov=40)
    return ds.Scene(
        mesh=ds.combine(*meshes),
        camera=cam,
        material=mats[0],
        materials=tuple(mats[1:]),
        directional=dlight([-0.3, -0.4, -1.0]),
        ambient_light=0.6,
        background=(0.1, 0.2, 0.3),
    )


def _face_data(scene):
    V = np.asarray(scene.mesh.vertices)
    F = np.asarray(scene.mesh.faces)
    mats = scene.all_materials()
    mid = np.asarray(scene.mesh.material_ids)
    l = -np.asarray(scene.directional.direction[0])
    l /= np.linalg.norm(l)
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    eye = np.asarray(scene.camera.eye)
    cen = V[F].mean(1)
    towards = np.einsum("fc,fc->f", n, eye - cen) > 0
    n = np.where(towards[:, None], n, -n)  # two-sided: lit on the side the eye sees (flat shading)
    color = np.stack(
        [np.asarray(mats[m].ambient) * 0.6 + np.asarray(mats[m].diffuse) * max(n[k] @ l, 0) for k, m in enumerate(mid)]
    )
    t = np.array([float(mats[m].opacity) for m in mid])
    return V, F, color, t


@pytest.mark.parametrize("n_panes,layers,sort", [(1, 2, False), (3, 5, True)])
def test_compositing_matches_seed_zbuffer_with_transparency_buffers(n_panes, layers, sort):
    scene = _panes_scene(32, n_panes)
    opts = ds.RenderOptions(
        raster=ds.Raster(shading="flat"),
        lighting=ds.Lighting(specular="none"),
        transparency=ds.Transparency(layers=layers),
    )
    img = render(scene, opts)
    V, F, color, t = _face_data(scene)
    d = rays(scene.camera)
    ref = seed_zbuffer_with_transparency(
        V, F, color, t, np.asarray(scene.camera.eye), d, np.asarray(scene.background), sort_transparent=sort
    )
    # Compare away from triangle edges (ray casting and rasterization may disagree exactly there).
    depth = _ray_hits(V, F, np.asarray(scene.camera.eye), d)
    hits = np.isfinite(depth).sum(0)
    err = np.abs(img - ref).max(-1)
    assert np.mean(err < 1e-9) > 0.97, np.mean(err < 1e-9)
    assert (hits >= n_panes).sum() > 100


def test_more_surfaces_than_layers_fall_back_to_background():
    scene = _panes_scene(24, 3, opaque_sphere=False)
    full = ds.RenderOptions(
        raster=ds.Raster(shading="flat"), lighting=ds.Lighting(specular="none"), transparency=ds.Transparency(layers=3)
    )
    cut = full.replace(transparency=ds.Transparency(layers=2))
    a, b = render(scene, full), render(scene, cut)
    assert ds.truncated_pixels(scene, full) == 0
    n_cut = ds.truncated_pixels(scene, cut)
    assert n_cut > 50
    # Where three panes overlap, K = 2 composites the first two and lets the rest of the light
    # come from the background: I_2 = t0 C0 + (1-t0)(t1 C1 + (1-t1) bg).
    V, F, color, t = _face_data(scene)
    d = rays(scene.camera)
    depth = _ray_hits(V, F, np.asarray(scene.camera.eye), d)
    order = np.argsort(depth, axis=0)
    three = np.isfinite(depth).sum(0) == 3
    bg = np.asarray(scene.background)
    j, i = np.nonzero(three)
    k0, k1 = order[0, j, i], order[1, j, i]
    want = t[k0, None] * color[k0] + (1 - t[k0, None]) * (t[k1, None] * color[k1] + (1 - t[k1, None]) * bg)
    close = np.abs(b[j, i] - want).max(-1) < 1e-9
    assert close.mean() > 0.95 and three.sum() > 50
    assert np.abs(a[three] - b[three]).max() > 1e-3  # the third pane matters where it is there


# --- gradients and hard cases ---------------------------------------------------------------------

GRAD_OPTS = ds.RenderOptions(
    lighting=ds.Lighting(transmission=True, fresnel="dielectric"),
    transparency=ds.Transparency(layers=3, absorption=True),
    shadows=ds.ShadowMaps(resolution=64),
)


def grad_scene(size=12):
    slab = ds.box((1.4, 1.4, 0.5), (0, 0, 0.6))
    ball = ds.icosphere(1, 0.5)
    ball = ds.Mesh(vertices=ball.vertices + np.array([0.5, 0.3, -0.6]), faces=ball.faces)
    plane = ds.quad((5, 5), (0, 0, -1.2))
    mats = (
        ds.Material(ambient=0.3, diffuse=(0.8, 0.7, 0.6), specular=0.2, shininess=10.0),
        ds.Material(
            ambient=0.1,
            diffuse=(0.2, 0.3, 0.5),
            specular=0.3,
            opacity=0.4,
            absorption=(0.4, 0.7, 1.1),
            transmission=(0.3, 0.4, 0.5),
            ior=1.4,
            shininess=8.0,
            casts_shadow=False,
        ),
        ds.Material(
            ambient=0.2, diffuse=(0.7, 0.2, 0.2), specular=0.1, kay=True, kay_min=0.9, kay_max=0.3, kay_power=1.7
        ),
    )
    cam = camera([0.4, 0.5, 4], [0, 0, -0.3], size, fov=40)
    return ds.Scene(
        mesh=ds.combine(plane, slab, ball),
        camera=cam,
        material=mats[0],
        materials=mats[1:],
        point=ds.PointLights(
            color=(0.9, 0.8, 0.7), position=[-0.5, -0.4, -0.5], attenuation=[1, 0.1, 0.05], ambient=[0, 0, 0]
        ),
        directional=dlight([0.2, -0.3, -1.0], 0.5),
        ambient_light=0.4,
        background=(0.1, 0.1, 0.2),
    )


NEW_PARAMS = {  # name: (where in the scene, value, size)
    "opacity": (lambda s: s.materials[0].opacity, 0.4),
    "absorption": (lambda s: s.materials[0].absorption, np.array([0.4, 0.7, 1.1])),
    "transmission": (lambda s: s.materials[0].transmission, np.array([0.3, 0.4, 0.5])),
    "ior": (lambda s: s.materials[0].ior, 1.4),
    "kay_min": (lambda s: s.materials[1].kay_min, 0.9),
    "kay_max": (lambda s: s.materials[1].kay_max, 0.3),
    "kay_power": (lambda s: s.materials[1].kay_power, 1.7),
    "point_color": (lambda s: s.point.color, np.array([[0.9, 0.8, 0.7]])),
    "point_attenuation": (lambda s: s.point.attenuation, np.array([[1.0, 0.1, 0.05]])),
}
_SIZES = [int(np.size(v)) for _, v in NEW_PARAMS.values()]
_OFFSETS = np.cumsum([0] + _SIZES)
_LABELS = [f"{n}[{i}]" for n, sz in zip(NEW_PARAMS, _SIZES) for i in range(sz)]


@pytest.fixture(scope="module")
def grad_fn():
    """The image as a function of every new parameter at once (one compile for all checks)."""
    import equinox as eqx

    scene = grad_scene()
    ids = ds.scene_visibility(scene, GRAD_OPTS)
    x0 = jnp.concatenate([jnp.ravel(jnp.asarray(v, F64)) for _, v in NEW_PARAMS.values()])

    def f(x):
        s = scene
        for (where, value), a, b in zip(NEW_PARAMS.values(), _OFFSETS[:-1], _OFFSETS[1:]):
            s = eqx.tree_at(where, s, x[a:b].reshape(np.shape(value)))
        return ds.shade(s, ids, GRAD_OPTS)

    return jax.jit(f), x0


def test_gradients_new_parameters(grad_fn):
    """Every column of the forward-mode Jacobian (t, μ, k_t, η, t_min, t_max, p, light colour and
    attenuation) against central differences, and the reverse-mode Jacobian against it (so both
    modes against finite differences, every direction)."""
    f, x0 = grad_fn
    img = f(x0)
    assert np.all(np.isfinite(np.asarray(img)))
    J = np.asarray(jax.jit(jax.jacfwd(f))(x0)).reshape(-1, x0.size)
    JT = np.asarray(jax.jit(jax.jacrev(f))(x0)).reshape(-1, x0.size)
    np.testing.assert_allclose(JT, J, rtol=1e-9, atol=1e-12)
    eps = 1e-6
    for k, label in enumerate(_LABELS):
        e = jnp.zeros_like(x0).at[k].set(eps)
        fd = (np.asarray(f(x0 + e)) - np.asarray(f(x0 - e))).reshape(-1) / (2 * eps)
        assert np.abs(J[:, k]).max() > 1e-4, f"{label} has no effect on the test image"
        np.testing.assert_allclose(J[:, k], fd, rtol=1e-5, atol=1e-7, err_msg=label)


_HARD = {}


def _hard_fn(opts):
    """(value, forward and reverse derivative of the image sum) in the scalar/vector ``x`` placed
    by ``where``; compiled once per options and shape."""
    import equinox as eqx

    if opts not in _HARD:

        def run(scene, x, where_id):
            where = _WHERES[where_id]
            f = lambda x: ds.render(eqx.tree_at(where, scene, x), opts)  # noqa: E731
            return f(x), jax.jacfwd(lambda x: f(x).sum())(x), jax.grad(lambda x: f(x).sum())(x)

        _HARD[opts] = jax.jit(run, static_argnums=2)
    return _HARD[opts]


_WHERES = {
    "opacity": lambda s: s.materials[0].opacity,
    "absorption": lambda s: s.materials[0].absorption,
    "ior": lambda s: s.material.ior,
}


@pytest.mark.parametrize("case", ["t=0", "t=1", "mu=0", "kay |n_z|=0", "tir"])
def test_hard_cases_finite(case):
    if case == "kay |n_z|=0":
        # A face exactly edge-on to the view is not rasterized, so the end point is tested on the
        # function: values at |n_z| = 0 and 1, and finite derivatives in n_z and p, also p < 1.
        for nz in (0.0, 1.0):
            assert np.isfinite(jax.grad(lambda z: S.kay_opacity(z, 0.9, 0.2, 0.5))(nz))
            assert np.isfinite(jax.grad(lambda p: S.kay_opacity(nz, 0.9, 0.2, p))(0.5))
            assert np.isfinite(jax.jvp(lambda z: S.kay_opacity(z, 0.9, 0.2, 0.5), (nz,), (1.0,))[1])
        return
    if case == "tir":  # every pixel beyond the critical angle
        scene, opts = transmission_scene([np.sin(1.2), 0.0, np.cos(1.2)], "dielectric", size=8)
        where, x = "ior", jnp.asarray(1.5, F64)
    else:
        scene, opts = grad_scene(size=8), GRAD_OPTS
        where, x = {
            "t=0": ("opacity", jnp.asarray(0.0, F64)),
            "t=1": ("opacity", jnp.asarray(1.0, F64)),
            "mu=0": ("absorption", jnp.zeros(3, F64)),
        }[case]
    val, jf, jr = _hard_fn(opts)(scene, x, where)
    assert np.all(np.isfinite(np.asarray(val))) and np.all(np.isfinite(np.asarray(jf)))
    np.testing.assert_allclose(np.asarray(jf), np.asarray(jr), rtol=1e-9, atol=1e-12)
    if case == "tir":
        assert np.all(np.asarray(val) == 0) and np.all(np.asarray(jf) == 0)
