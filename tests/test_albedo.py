"""Per-vertex albedo as a sparse linear block: the compressed design matrix against the dense
Jacobian, exact recovery with the other parameters, vertices no view sees, the smoothness prior,
noisy targets' standard errors, and the CLI."""

from __future__ import annotations

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

import diffshade as ds
from fitting import Observations, fit
from fitting._albedo import AlbedoProblem, vertex_colouring
from fitting._problem import Problem
from fitting.cli import EXIT_OK, main

SIZE = 40
EYES = [(0.0, 0.0, 3.0), (2.5, 0.6, 1.5), (-2.5, 0.6, 1.5)]


def _albedo(v):
    return np.clip(0.5 + 0.3 * np.sin(3 * v) + 0.05 * np.cos(7 * v[:, [1, 2, 0]]), 0.02, 0.98)


@pytest.fixture(scope="module")
def setup():
    d = {k: v for k, v in ds.DEFAULT_SCENE.items() if k != "fog"}
    d["camera"] = dict(d["camera"], width=SIZE, height=SIZE)
    d["render"] = dict(d["render"], fog="none", vertex_color="diffuse")
    tm = trimesh.creation.icosphere(2)
    truth = _albedo(np.asarray(tm.vertices))
    scene, opts = ds.scene_from_dict({**d, "mesh": {"icosphere": 0}, "render": {**d["render"], "vertex_color": "none"}})
    opts = opts.with_keys(vertex_color="diffuse")
    scene = eqx.tree_at(lambda s: s.mesh, scene, ds.Mesh(vertices=tm.vertices, faces=tm.faces, colors=truth))
    views = []
    for eye in EYES:
        c = scene.camera
        cam = ds.Camera(
            eye=eye, target=c.target, up=c.up, fov_y=c.fov_y, near=c.near, far=c.far, width=SIZE, height=SIZE
        )
        views.append(eqx.tree_at(lambda s: s.camera, scene, cam))
    render = jax.jit(ds.render, static_argnames="opts")
    targets = [np.asarray(render(v, opts)) for v in views]
    return views, opts, targets, truth


def _start(views, colors=0.5, a=(1.0, 0.1, 0.05)):
    out = []
    for v in views:
        m = v.mesh
        out.append(
            eqx.tree_at(
                lambda s: (s.mesh.colors, s.point.attenuation), v, (jnp.full(m.colors.shape, colors), jnp.asarray([a]))
            )
        )
    return out


def test_the_colouring_separates_every_triangle():
    for sub in (1, 3):
        tm = trimesh.creation.icosphere(sub)
        c = vertex_colouring(tm.faces, len(tm.vertices))
        f = c[tm.faces]
        assert (f[:, 0] != f[:, 1]).all() and (f[:, 1] != f[:, 2]).all() and (f[:, 0] != f[:, 2]).all()
        degree = np.bincount(np.asarray(tm.edges_unique).reshape(-1))
        assert c.max() + 1 <= degree.max() + 1


def test_the_compressed_design_matrix_is_the_jacobian(setup):
    """A handful of tangents (one per colour class) give every column of the albedo Jacobian:
    equal to the dense one from forward mode, one tangent per scalar."""
    views, opts, targets, truth = setup
    free = ["mesh.colors", "material.shininess"]
    prob = Problem.build(views[0], opts, Observations(targets[:2], views=views[:2]), free)
    ap = AlbedoProblem(prob)
    theta = np.asarray(prob.pset.theta_of(views[0], views[:2]), np.float64)
    ap._compile(theta)
    img, A, Jo, w = ap.evaluate(theta)
    assert ap.n_col <= 7 and A.shape == (len(img), 3 * truth.shape[0])

    def weighted(th):
        return jnp.concatenate([(prob.image(vd, th) * vd.weight * ~(vd.hi | vd.lo)).reshape(-1) for vd in prob.data])

    J = np.asarray(jax.jacfwd(weighted)(jnp.asarray(theta)))
    np.testing.assert_allclose(A.toarray(), J[:, ap.sl], rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(Jo, J[:, ap.other], rtol=1e-10, atol=1e-13)
    assert A.nnz <= 3 * len(img)  # three vertices per pixel at most


def test_albedo_and_the_other_parameters_are_recovered_and_unseen_vertices_named(setup):
    views, opts, targets, truth = setup
    free = ["mesh.colors", "material.shininess", "material.specular", "point[0].a1", "point[0].a2"]
    r = fit(_start(views)[0], opts, Observations(targets, views=_start(views)), free)
    assert r.successful, r.result
    assert "sparse linear block" in r.method
    n = truth.size
    seen = np.isfinite(r.stderr[:n])
    assert 0.5 < seen.mean() < 1.0  # three views leave the poles unseen
    np.testing.assert_allclose(r.values[:n][seen], truth.reshape(-1)[seen], atol=1e-8)
    np.testing.assert_allclose(r.values[n:], [30.0, 0.5, 0.5, 0.5, 0.05, 0.02], rtol=1e-7)
    unseen_v = np.flatnonzero(~seen.reshape(-1, 3).any(axis=1))
    assert sorted(r.diagnostics.undetermined) == sorted(f"mesh.colors[{v}]" for v in unseen_v)
    np.testing.assert_array_equal(r.values[:n][~seen], 0.5)  # kept at the start: not an estimate
    # every vertex no view sees is among them; the others are seen only where no light reaches
    # (their column of the Jacobian is 0: tested above against the dense one)
    faces_seen = set()
    for v in views:
        ids = np.asarray(ds.scene_visibility(v, opts))[0]
        faces_seen |= set(ids[ids >= 0].tolist())
    verts_seen = set(np.asarray(v.mesh.faces)[sorted(faces_seen)].reshape(-1).tolist())
    assert set(range(truth.shape[0])) - verts_seen <= set(unseen_v.tolist())


def test_the_smoothness_prior_fills_unseen_vertices(setup):
    views, opts, targets, truth = setup
    # a weak prior: where no data is, its harmonic interpolation of the neighbours, whatever λ is;
    # the attenuation at the truth (only the albedo is free)
    starts = _start(views, a=(1.0, 0.05, 0.02))
    r = fit(starts[0], opts, Observations(targets, views=starts), ["mesh.colors"], albedo_smoothness=1e-6)
    n = truth.size
    assert not r.diagnostics.undetermined and np.isfinite(r.stderr[:n]).all()
    assert any("smoothness prior alone" in note for note in r.notes)
    # the prior pulls the unseen caps toward their neighbours, away from the flat 0.5 start
    r0 = fit(starts[0], opts, Observations(targets, views=starts), ["mesh.colors"])
    assert r0.successful, r0.result
    assert (
        r.residual.rms < 1e-5
    )  # the prior's pull on the seen vertices: far below any real noise, above float rounding
    unseen = ~np.isfinite(r0.stderr[:n])
    err_prior = np.abs(r.values[:n][unseen] - truth.reshape(-1)[unseen]).mean()
    err_start = np.abs(0.5 - truth.reshape(-1)[unseen]).mean()
    assert err_prior < err_start
    # on most seen vertices a weak prior changes little (a vertex seen in a few grazing pixels has
    # so little data that even a weak prior moves it)
    seen = ~unseen
    assert np.quantile(np.abs(r.values[:n][seen] - truth.reshape(-1)[seen]), 0.95) < 1e-3


def test_noisy_8bit_albedo_errors_are_covered_by_their_standard_errors(setup):
    views, opts, targets, truth = setup
    rng = np.random.default_rng(11)
    noisy = [np.round(np.clip(t + rng.normal(0, 2 / 255, t.shape), 0, 1) * 255) / 255 for t in targets]
    starts = _start(views, a=(1.0, 0.1, 0.02))  # a1 free (from twice its truth), a0 and a2 at theirs
    r = fit(
        starts[0],
        opts,
        Observations(noisy, views=starts, saturation=1.0, quantum=1 / 255),
        ["mesh.colors", "point[0].a1"],
    )
    assert r.successful, r.result
    n = truth.size
    seen = np.isfinite(r.stderr[:n])
    z = (r.values[:n][seen] - truth.reshape(-1)[seen]) / r.stderr[:n][seen]
    # marginal standard errors (a1 and the albedo trade: both are in the covariance): 1σ coverage
    # near 68 %, 3σ near all
    assert 0.55 < np.mean(np.abs(z) < 1) < 0.85, np.mean(np.abs(z) < 1)
    assert np.mean(np.abs(z) < 3) > 0.97


def test_cli_fits_the_albedo_and_writes_it_on_the_mesh(tmp_path, setup, capsys):
    views, opts, targets, truth = setup
    tm = trimesh.Trimesh(
        np.asarray(views[0].mesh.vertices),
        np.asarray(views[0].mesh.faces),
        vertex_colors=np.full((truth.shape[0], 4), [128, 128, 128, 255], np.uint8),
        process=False,
    )
    tm.export(tmp_path / "grey.ply")
    scene_toml = f"""
ambient_light = [0.3, 0.3, 0.3]
[mesh]
path = "{tmp_path / "grey.ply"}"
[camera]
eye = [0, 0, 3]
width = {SIZE}
height = {SIZE}
near = 0.5
far = 10.0
[render]
shading = "phong"
vertex_color = "diffuse"
[material]
ambient = [0.15, 0.12, 0.1]
specular = 0.5
shininess = 30
[[light]]
type = "point"
color = [1, 1, 1]
position = [2, 2, 3]
attenuation = [1, 0.05, 0.02]
[[light]]
type = "directional"
color = [0.3, 0.3, 0.35]
direction = [1.0, -0.5, -1.0]
"""
    (tmp_path / "s.toml").write_text(scene_toml)
    # the target from the file's own geometry (a PLY stores float32 vertices)
    scene, sopts = ds.load_scene(tmp_path / "s.toml")
    scene = eqx.tree_at(lambda s: s.mesh.colors, scene, jnp.asarray(truth))
    np.save(tmp_path / "t.npy", np.asarray(ds.render(scene, sopts)))
    rc = main(
        ["fit", str(tmp_path / "s.toml"), str(tmp_path / "t.npy"), "-p", "mesh.colors", "-o", str(tmp_path / "out")]
    )
    out = capsys.readouterr().out
    assert rc == EXIT_OK, out
    assert "vertices undetermined" in out and "albedo.ply" in out
    fitted = ds.load_mesh(tmp_path / "out" / "albedo.ply")  # sRGB 8-bit colours
    doc = json.loads((tmp_path / "out" / "fit.json").read_text())
    vals = np.array(
        [doc["parameters"][f"mesh.colors[{v}][{c}]"]["value"] for v in range(truth.shape[0]) for c in "rgb"]
    )
    seen = np.isfinite([doc["parameters"][f"mesh.colors[{v}][r]"]["stderr"] for v in range(truth.shape[0])])
    np.testing.assert_allclose(vals.reshape(-1, 3)[seen], truth[seen], atol=1e-6)
    np.testing.assert_allclose(np.asarray(fitted.colors)[seen], truth[seen], atol=0.01)  # 8-bit sRGB


@pytest.mark.parametrize("exact", [True, False])
def test_the_standard_errors_of_a_large_mesh_are_exact(exact, monkeypatch):
    """Past 4,000 vertices a channel's diag(G⁻¹) is taken by the sparse Cholesky factor's selected
    inversion: 64 of its entries, each by a sparse solve of its own, to 1e-9 (a mesh's normal matrix: each vertex coupled to its
    neighbours through the pixels they share); without the factorisation, the diagonal
    approximation 1/G_ii, which is below the exact variance."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    from fitting import _sparse
    from fitting._albedo import _channel_inverse_diagonal

    if not exact:
        monkeypatch.setattr(_sparse, "use_cholesky", lambda: False)
    elif not (_sparse.use_cholesky() and _sparse.HAVE_METIS):
        pytest.skip("no Cholesky factorisation or METIS here")
    rng = np.random.default_rng(8)
    n = 70 * 70  # vertices
    T = sp.diags([1.0, 1.0], [-1, 1], (70, 70))
    pairs = sp.triu(sp.kron(sp.identity(70), T) + sp.kron(T, sp.identity(70)) + sp.kron(T, T)).tocoo()
    rows = np.concatenate([np.arange(len(pairs.row))] * 2)
    A = sp.csr_matrix((rng.uniform(0.2, 1.0, 2 * len(pairs.row)), (rows, np.r_[pairs.row, pairs.col])))
    Gv = (A.T @ A).tocsc()  # one channel's
    G = sp.kron(Gv, sp.identity(3)).tocsc()  # scalars 3v + c
    idx = np.arange(3 * n)
    got = _channel_inverse_diagonal(G, idx)
    some = rng.choice(n, 64, replace=False)  # the reference: a sparse solve of those unit vectors
    E = np.zeros((n, len(some)))
    E[some, np.arange(len(some))] = 1.0
    want = splu(Gv).solve(E)[some, np.arange(len(some))]
    for c in range(3):
        if exact:
            np.testing.assert_allclose(got[c::3][some], want, rtol=1e-9)
        else:
            np.testing.assert_allclose(got[c::3], 1 / Gv.diagonal())
            assert (got[c::3][some] < want).all()


def test_the_backtracks_residuals_are_the_products_with_a():
    """The projected Newton steps' backtrack (fitting._block_solver._Backtrack) takes the residual at
    each clipped point x(a) = clip(x + a p) from r(x), A p and the clipped scalars' columns: equal
    to A x(a) + b - y to rounding at every halving, and None (a product with A instead) where the
    clip moved more than an eighth of the scalars."""
    import scipy.sparse as sp

    from fitting._block_solver import _Backtrack

    rng = np.random.default_rng(7)
    A = sp.random(400, 120, density=0.05, random_state=rng, format="csr")
    b, y = rng.normal(size=400), rng.normal(size=400)
    x = rng.uniform(0, 1, 120)
    x[:30] = 0.1
    p = rng.normal(size=120) * 0.02
    p[:30] = -np.linspace(0.15, 3.0, 30)  # through the bound 0: the longer the step, the more of them
    trials = _Backtrack(A @ x + b - y, x, p, A, A.tocsc())
    seen = set()
    for a in 0.5 ** np.arange(12):
        x_new = np.clip(x + a * p, 0.0, 1.0)
        r = trials.at(a, x + a * p, x_new)
        moved = int(np.count_nonzero(x + a * p - x_new))
        if moved > 120 // 8:
            assert r is None
        else:
            np.testing.assert_allclose(r, A @ x_new + b - y, rtol=0, atol=1e-13)
        seen.add(r is None)
    assert seen == {True, False}  # (both ways taken)
    big = np.full(120, 5.0)  # a step that clips every scalar
    assert _Backtrack(A @ x + b - y, x, big, A, A.tocsc()).at(1.0, x + big, np.clip(x + big, 0, 1)) is None
