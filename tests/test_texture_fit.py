"""Texture maps in a fit (fitting._maps): the sampling as a sparse matrix against the renderer's
sampler, the linear model against renders, recovery of every determined texel from noise-free
views (bilinear and trilinear maps, with another parameter beside them), the texels no pixel
samples kept at their start and named, and what a map fit refuses."""

import dataclasses
import types

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp
from conftest import float32

import diffshade as ds
import fitting
from fitting._maps import MapProblem
from fitting._problem import FitError, Problem
from fitting._sparse import Orderings


@pytest.mark.parametrize("filt", ["trilinear", "bilinear"])
@pytest.mark.parametrize("wrap", ["repeat", "clamp"])
def test_sample_weights_is_the_sampler_as_a_matrix(filt, wrap):
    """The sparse weights built in numpy with an integer remainder or clip per tap, against the
    renderer's sampler (which reads a one-texel border instead, and clamps far coordinates before
    converting them to integers): odd sizes (whose pyramid repeats rows), coordinates on, within
    a hair of and far beyond the edges, every level of detail."""
    rng = np.random.default_rng(3)
    edges = [0.0, 1.0, -1e-9, 1 + 1e-9, 0.05, 0.97, -0.3, 1.3, -2.9, 3.01]
    far = [-1e6, 1e6, -1e9, 4e9] if wrap == "clamp" else [-7.25, 12.5]
    for h, w in [(13, 7), (16, 16), (1, 5)]:
        t = ds.Texture(rng.random((h, w, 3)), wrap=wrap, filter=filt)
        coords = np.concatenate([edges, far, rng.uniform(-1, 2, 16)])
        u, v = (c.ravel() for c in np.meshgrid(coords, coords[::-1]))
        lod = rng.uniform(-1, 6, u.shape)
        ref = np.asarray(ds.sample(t, jnp.asarray(u), jnp.asarray(v), jnp.asarray(lod)))
        W = ds.sample_weights(t, u, v, lod)
        np.testing.assert_allclose(W @ np.asarray(t.texels).reshape(-1, 3), ref, atol=1e-14)
        np.testing.assert_allclose(np.asarray(W.sum(axis=1)).ravel(), 1.0, atol=1e-14)  # the rows sum to one


def _views(res, filt, size=48, azimuths=(0, 120, 240), seed=1):
    """The default scene's sphere with a random diffuse map (coordinates from longitude and
    height), seen from around it; the same scenes with a grey start map."""
    rng = np.random.default_rng(seed)
    scene, opts = ds.default_scene()
    m = scene.mesh
    v = np.asarray(m.vertices)
    uv = np.stack([np.arctan2(v[:, 1], v[:, 0]) / (2 * np.pi) + 0.5, 0.5 + 0.5 * v[:, 2]], 1)
    mesh = ds.Mesh(m.vertices, m.faces, normals=m.normals, uv=uv)
    truth = rng.uniform(0.1, 0.9, (res, res, 3))
    cam = dataclasses.replace(scene.camera, width=size, height=size)
    scene = dataclasses.replace(scene, mesh=mesh, camera=cam)
    opts = opts.with_keys(shading="phong")
    true_mat = dataclasses.replace(scene.material, diffuse_map=ds.Texture(truth, filter=filt))
    start_mat = dataclasses.replace(scene.material, diffuse_map=ds.Texture(np.full((res, res, 3), 0.5), filter=filt))
    views, starts, targets = [], [], []
    for az in azimuths:
        a = np.deg2rad(az)
        c = dataclasses.replace(cam, eye=jnp.asarray([3 * np.cos(a), 3 * np.sin(a), 1.0]), target=jnp.zeros(3))
        views.append(dataclasses.replace(scene, camera=c, material=true_mat))
        starts.append(dataclasses.replace(scene, camera=c, material=start_mat))
        targets.append(np.asarray(ds.render(views[-1], opts)))
    return starts, targets, truth, opts


def test_the_linear_model_is_the_render():
    """A x + b (the assembled design matrix) equals the render at random texels."""
    starts, targets, truth, opts = _views(16, "trilinear")  # the recovery test's views: their programs shared
    prob = Problem.build(starts[0], opts, fitting.Observations(targets, views=starts), ["material.diffuse_map"])
    mp = MapProblem(prob)
    x0 = np.full(truth.size, 0.5)
    mp._compile(x0)
    img, A, _, w = mp.evaluate(x0)
    b = img * w - A @ x0
    x = np.random.default_rng(0).uniform(0, 1, truth.size)
    np.testing.assert_allclose(A @ x + b, mp.evaluate(x)[0] * w, atol=1e-13)


def test_the_lighting_from_the_kernel_is_the_texels_tangent():
    """Float32 Phong: the design matrix's S of a diffuse map (its fields: the diffuse and the
    ambient term it carries) and of a specular map, from the shading kernel's partials along their
    fields' constants with the maps at ones, against the JAX stages' jvp along each map's texels
    all +1."""
    import jax

    starts, targets, _, opts = _views(8, "bilinear", size=24, azimuths=(0,))  # (test_what_a_map_fit_refuses' views)
    spec = ds.Texture(np.random.default_rng(5).uniform(0.2, 1.0, (8, 8, 1)), filter="bilinear")
    start = dataclasses.replace(starts[0], material=dataclasses.replace(starts[0].material, specular_map=spec))
    start = float32(start)
    obs = fitting.Observations([targets[0].astype(np.float32)], views=[start])
    prob = Problem.build(start, opts, obs, ["material.diffuse_map", "material.specular_map"])
    mp = MapProblem(prob)
    vd = prob.data[0]
    th = prob.pset.theta_of(start)
    scene = prob.pset.apply(vd.scene, th, vd.index)
    assert mp._by_kernel(scene, vd)
    S = jax.jit(mp._lighting)(scene, vd)  # (the fit's program around it: the same, with the image and coordinates)
    stages = jax.jit(jax.vmap(lambda e: jax.jvp(lambda t: prob.image(vd, t), (th,), (e,))[1]))  # the stages
    refs = stages(jnp.asarray(mp.E[:2], jnp.float32))
    for j, ref in enumerate(refs):
        scale = float(jnp.abs(ref).max())
        assert scale > 0.05
        np.testing.assert_allclose(S[j], ref, atol=2e-5 * scale)  # (test_fast.py: the partials against the stages)


@pytest.mark.parametrize("filt", ["bilinear", "trilinear"])
def test_determined_texels_are_recovered_and_the_others_named(filt):
    starts, targets, truth, opts = _views(16, filt)
    free = ["material.diffuse_map", "point[0].color"]
    true_colour = np.asarray(starts[0].point.color[0])
    starts = [dataclasses.replace(s, point=dataclasses.replace(s.point, color=s.point.color * 1.3)) for s in starts]
    r = fitting.fit(starts[0], opts, fitting.Observations(targets, views=starts), free, intervals=False)
    x = r.values[: truth.size].reshape(truth.shape)
    se = r.stderr[: truth.size].reshape(truth.shape)
    det = np.isfinite(se)
    assert 0.5 < det.mean() < 1.0  # the poles are not seen: some texels undetermined, most determined
    # the light colour and the map are a gauge (only their product shows): the map up to that scale
    scale = r.values[truth.size :] / true_colour
    np.testing.assert_allclose(x[det] * np.broadcast_to(scale, truth.shape)[det], truth[det], atol=1e-6)
    undetermined = set(r.diagnostics.undetermined)
    assert {f"material.diffuse_map[{i},{j}][{'rgb'[c]}]" for i, j, c in zip(*np.nonzero(~det))} <= undetermined
    if filt == "bilinear":  # (a trilinear map's coarse levels reach every texel)
        assert (~det & (x == 0.5)).any()  # no pixel samples these: kept at their start


def test_what_a_map_fit_refuses():
    starts, targets, truth, opts = _views(8, "bilinear", size=24, azimuths=(0,))
    obs = fitting.Observations(targets, views=starts)
    with pytest.raises(FitError, match="clamp"):
        fitting.fit(starts[0], opts.with_keys(clamp=True), obs, ["material.diffuse_map"])
    with pytest.raises(fitting.ParamError, match="no specular map"):
        fitting.fit(starts[0], opts, obs, ["material.specular_map"])
    with pytest.raises(FitError, match="shared by every view"):
        fitting.fit(starts[0], opts, obs, ["view[0].material.diffuse_map"])
    # one Texture on two fields is one map, named by its first field
    tex = starts[0].material.diffuse_map
    one = dataclasses.replace(starts[0], material=dataclasses.replace(starts[0].material, specular_map=tex))
    with pytest.raises(fitting.ParamError, match=r"same Texture as material.diffuse_map .*free material.diffuse_map"):
        fitting.ParamSet(["material.specular_map"], one)
    assert fitting.ParamSet(["material.diffuse_map"], one).sizes == [tex.texels.size]


def test_fitted_maps_export_as_png_and_mtl_and_load_back(tmp_path):
    """save_material writes each map as a 16-bit PNG named by a map_* line; load_material reads the
    same material back (sRGB colour codes, linear grey ones, a shininess map's scale in Ns)."""
    rng = np.random.default_rng(5)
    scene, opts = ds.default_scene()
    maps = {
        "diffuse_map": ds.Texture(rng.uniform(0, 1, (9, 7, 3)), wrap="clamp"),
        "specular_map": ds.Texture(rng.uniform(0, 1, (4, 4, 1))),
        "shininess_map": ds.Texture(rng.uniform(0.5, 3.0, (3, 5, 1))),
    }
    mat = dataclasses.replace(scene.material, **maps)
    ds.save_material(tmp_path / "material.mtl", dataclasses.replace(scene, material=mat), opts, header="test")
    text = (tmp_path / "material.mtl").read_text()
    assert "map_Kd -clamp on material_material_diffuse.png" in text
    back = ds.load_material(tmp_path / "material.mtl")
    for f, t in maps.items():
        got = getattr(back, f)
        assert got.wrap == t.wrap and got.texels.shape == t.texels.shape
        want = np.asarray(t.texels)
        if f == "shininess_map":  # the map's scale moved into Ns
            np.testing.assert_allclose(float(back.shininess), float(mat.shininess) * want.max(), rtol=1e-6)
            want = want / want.max()
        np.testing.assert_allclose(np.asarray(got.texels), want, atol=2e-5)  # 16-bit codes


def test_a_fine_map_is_recovered_where_the_views_determine_it():
    """A 96² map from four views of 96² (beyond the dense limit: the inverse's diagonal by
    selected inversion): many texels are seen only through averages with their neighbours, some
    pushed out of [0, 1] by the first step (an active set that fixed each step's violators at once
    cycled here). Noise-free, every texel reported determined is recovered to 1e-4. Where the
    diagonal is probed (no Cholesky factorisation here), a texel may be off by more only where the
    probe underestimated its variance inflation: its exact inflation (a solve on its own) exceeds
    1e4, so the solve is right and the probe's known weakness is what it shows (docs/model.md §15)."""
    from scipy.sparse.linalg import splu

    from fitting import _sparse

    starts, targets, truth, opts = _views(96, "trilinear", size=96, azimuths=(0, 90, 180, 270))
    obs = fitting.Observations(targets, views=starts)
    r = fitting.fit(starts[0], opts, obs, ["material.diffuse_map"], intervals=False)
    x, se, t = r.values, r.stderr, truth.reshape(-1)
    det = np.isfinite(se)
    assert 0.3 < det.mean() < 0.9
    assert (se[det] > 0).all() and ((x >= 0) & (x <= 1)).all()
    off = np.flatnonzero(det & (np.abs(x - t) > 1e-4))
    if _sparse.use_cholesky() and _sparse.HAVE_METIS:
        assert not len(off), (len(off), np.abs(x - t)[off].max())
    assert len(off) <= 1e-3 * det.sum()
    if len(off):
        mp = MapProblem(Problem.build(starts[0], opts, obs, ["material.diffuse_map"]))
        mp._compile(x)
        A = mp.evaluate(x)[1]
        seen = np.flatnonzero(np.asarray(abs(A).sum(axis=0)).ravel() > 0)
        G = (A.T @ A).tocsc()[seen][:, seen]
        d = 1 / np.sqrt(G.diagonal())
        lu = splu((sp.diags(d) @ G @ sp.diags(d) + sp.identity(len(seen)) * 1e-13).tocsc())
        E = np.zeros((len(seen), len(off)))
        E[np.searchsorted(seen, off), np.arange(len(off))] = 1.0
        assert (np.sum(lu.solve(E) * E, axis=0) > 1e4).all()


@pytest.mark.parametrize("large", ["selected inversion", "probing"])
def test_the_inverse_diagonal_of_small_and_large_blocks(large, monkeypatch):
    """diag(G⁻¹) of a block-diagonal G, its blocks in shuffled order: small blocks of several sizes
    (inverted as stacks, one per size; from 128 scalars by their Cholesky factors) exact; a chain
    of 3,500 scalars (beyond the dense limit) whose inverse decays tenfold per neighbour, by the Cholesky factor's selected inversion, or
    by probing where SuperLU factorises (to the probe's error at 8 texels); and, by selected
    inversion only, a 60² grid whose inverse reaches far (probing gives 1.05-4.5× its diagonal):
    exact to 1e-9."""
    from fitting import _sparse

    if large == "probing":
        monkeypatch.setattr(_sparse, "use_cholesky", lambda: False)
    elif not (_sparse.use_cholesky() and _sparse.HAVE_METIS):
        pytest.skip("no Cholesky factorisation or METIS here")
    rng = np.random.default_rng(4)
    blocks = []
    for n in [1, 1, 2, 5, 5, 5, 7, 200, 3500]:
        off = rng.uniform(-0.1, 0.1, n - 1) if n > 1 else np.zeros(0)
        B = sp.diags([off, rng.uniform(0.5, 2.0, n), off], [-1, 0, 1]) * rng.uniform(0.1, 10)
        blocks.append(B.toarray() if n < 100 else B)
    place = [np.zeros(226, int), np.arange(3500)]  # a texel's place in its block's grid of 64 columns
    if large == "selected inversion":
        T = sp.diags([-0.5, 1.0, -0.5], [-1, 0, 1], (60, 60))
        blocks.append((sp.kron(sp.identity(60), T) + sp.kron(T, sp.identity(60)) + 1e-3 * sp.identity(3600)).tocsc())
        place.append(np.arange(3600) // 60 * 64 + np.arange(3600) % 60)
    G = sp.block_diag(blocks).tocsr()
    perm = rng.permutation(G.shape[0])
    G = G[perm][:, perm].tocsc()
    exact = np.concatenate([np.diag(np.linalg.inv(b.toarray() if sp.issparse(b) else b)) for b in blocks])[perm]
    i = np.arange(G.shape[0])
    spot = np.concatenate(place)[perm]
    grid = np.stack([np.zeros_like(i), spot // 64, spot % 64, np.zeros_like(i)], -1)
    fake = types.SimpleNamespace(sp=sp, _grid=lambda: grid, orders=Orderings())
    got = MapProblem.inverse_diagonal(fake, G, i)
    np.testing.assert_allclose(got, exact, rtol=1e-9 if large == "selected inversion" else 1e-7)


def test_the_nested_dissection_ordering_solves_as_superlus_own():
    """A block past ORDERED scalars (a 2-D grid's normal matrix, as a map's channel) factorised in
    METIS's ordering, and in that ordering restricted to a random face, solves as SuperLU in its
    own ordering; two blocks of one pattern share one ordering; the ordering has fewer non-zeros
    in its factors (the reason it is used)."""
    from scipy.sparse.linalg import splu

    from fitting import _sparse

    n = 110  # 12,100 scalars
    rng = np.random.default_rng(2)
    T = sp.diags([-0.3, 1.0, -0.3], [-1, 0, 1], (n, n))
    M = (sp.kron(T, T) + sp.diags(rng.uniform(0.01, 0.1, n * n))).tocsc()  # a 9-point stencil on the grid
    assert M.shape[0] >= _sparse.ORDERED
    orders = Orderings()
    order = orders.of(M)
    assert sorted(order) == list(range(n * n))
    assert orders.of((2 * M).tocsc()) is order  # the same pattern: the same ordering
    b = rng.normal(size=(n * n, 3))
    own, ours = _sparse.Factor(M), _sparse.Factor(M, order)
    assert ours.chol is not None or not _sparse.use_cholesky()  # the supernodal Cholesky where it builds
    np.testing.assert_allclose(ours.solve(b), own.solve(b), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(M @ ours.solve(b[:, 0]), b[:, 0], atol=1e-9)
    ordered = splu(
        M[order][:, order].tocsc(), permc_spec="NATURAL", diag_pivot_thresh=0.0, options=dict(SymmetricMode=True)
    )
    assert ordered.L.nnz + ordered.U.nnz < own.lu.L.nnz + own.lu.U.nnz
    keep = rng.uniform(size=n * n) < 0.9
    sub = M[keep][:, keep].tocsc()
    np.testing.assert_allclose(
        _sparse.Factor(sub, _sparse.restrict(order, keep)).solve(b[keep]),
        _sparse.Factor(sub).solve(b[keep]),
        rtol=1e-9,
        atol=1e-12,
    )


def test_the_bounded_solve_is_the_bounded_least_squares_optimum():
    """The block's bounded solve against SciPy's bounded least squares (BVLS) on random sparse
    problems whose unbounded optimum leaves [0, 1] in many scalars."""
    from scipy.optimize import lsq_linear

    from fitting._block_solver import _BlockSolver

    for seed in range(3):
        rng = np.random.default_rng(seed)
        A = sp.random(300, 80, density=0.05, random_state=rng, format="csr") + sp.eye(300, 80, format="csr")
        y = A @ rng.uniform(-0.5, 1.5, 80) + rng.normal(0, 0.05, 300)
        solver = _BlockSolver.__new__(_BlockSolver)
        solver.ap, solver.Lp, solver.y = types.SimpleNamespace(sp=sp, orders=Orderings()), None, y
        solver._gram = solver._residual = None
        seen = np.ones(80, bool)
        x, free, _ = solver.bounded(np.full(80, 0.5), A, np.zeros(300), seen)
        ref = lsq_linear(A.toarray(), y, bounds=(0, 1), method="bvls", tol=1e-14).x
        assert ((ref <= 0) | (ref >= 1)).sum() > 10
        np.testing.assert_allclose(x, ref, atol=1e-7)
        np.testing.assert_array_equal(free, (ref > 0) & (ref < 1))


def test_faces_under_another_ridge_solve_as_ones_built_for_it():
    """The noise ridge's faces are the first step's blocks with their diagonals moved
    (:meth:`_Faces.with_ridge`): a solve on a face, held scalars and all, is the one faces built
    for that ridge give, and the first step's faces are left as they were."""
    from fitting._block_solver import _Faces

    rng = np.random.default_rng(3)
    parts = []
    for k in (1200, 1100, 200):  # two blocks of BLOCK scalars or more, and a small one
        Ak = sp.random(3 * k, k, density=4 / k, random_state=rng, format="csr") + sp.eye(3 * k, k, format="csr")
        parts.append(Ak.T @ Ak)
    G = sp.block_diag(parts).tocsc()
    n = G.shape[0]
    seen = rng.uniform(size=n) < 0.95
    weak, ridge = rng.uniform(0.01, 0.1, n), rng.uniform(0.1, 1.0, n)
    first = _Faces(sp, G, weak, seen, Orderings())
    assert sorted(len(g) for g in first.groups)[-2] >= 1000
    r, free = rng.normal(size=n), seen & (rng.uniform(size=n) < 0.9)
    before = first.step(r, free)
    moved, built = first.with_ridge(ridge), _Faces(sp, G, ridge, seen, Orderings())
    np.testing.assert_allclose(moved.step(r, free), built.step(r, free), rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(first.step(r, free), before)


def test_a_large_blocks_faces_share_its_analysis_and_solve_on_the_face():
    """A block past ORDERED scalars (a map channel's grid) and one of another pattern: their
    faces factorise the whole block with the held scalars' rows and columns the identity's, by the
    block's one symbolic analysis, also under another ridge; a step on a face, and on faces that
    differ from it by a few scalars (the border solves), is SuperLU's solve of the face's own
    system to 1e-9, zero on the held scalars."""
    from scipy.sparse.linalg import splu

    from fitting import _sparse
    from fitting._block_solver import _Faces

    if not _sparse.use_cholesky() or not _sparse.HAVE_METIS:
        pytest.skip("no Cholesky factorisation or METIS here")
    rng = np.random.default_rng(6)
    n = 105
    T = sp.diags([-0.3, 1.0, -0.3], [-1, 0, 1], (n, n))
    grid = sp.kron(T, T) + sp.diags(rng.uniform(0.01, 0.1, n * n))
    G = sp.block_diag([grid, sp.kron(sp.identity(n), T) + sp.kron(T, sp.identity(n))]).tocsc()
    N = G.shape[0]
    seen = np.ones(N, bool)
    first = _Faces(sp, G, np.full(N, 1e-3), seen, Orderings())
    assert [len(g) for g in first.groups] == [n * n, n * n]
    assert all(p is not None for p in first.patterns) and first.patterns[0].analysis is not first.patterns[1].analysis
    for faces in (first, first.with_ridge(np.full(N, 0.5))):
        M = (G + sp.diags(faces.rho)).tocsc()
        free = rng.uniform(size=N) < 0.85
        for moved in (0, 7):
            free = free.copy()
            free[rng.choice(N, moved, replace=False)] ^= True
            r = rng.normal(size=N)
            s = faces.step(r, free)
            F = np.flatnonzero(free)
            want = splu(M[F][:, F].tocsc()).solve(r[F])
            np.testing.assert_allclose(s[F], want, rtol=0, atol=1e-9 * np.abs(want).max())
            assert not s[~free].any()
        assert all(f.whole and f.lu.chol.analysis is p.analysis for f, p in zip(faces.faces, faces.patterns))


def test_a_noise_free_bounded_solve_with_many_bounds_is_the_optimum():
    """A consistent problem (no noise: the conjugate-gradient path) whose columns are seen from
    strongly to barely (scales 1e-3 to 1) and a few of whose true values lie outside [0, 1]: the
    clamped ones pull tens of neighbours onto the bounds. Against BVLS. Conjugate gradients alone
    hold one bound per step and ran out 0.5-1 off the optimum here; a proximal round of projected
    Newton settles the bounds first."""
    from scipy.optimize import lsq_linear

    from fitting._block_solver import _BlockSolver

    for seed in range(2):
        rng = np.random.default_rng(seed)
        n, m = 400, 1000
        A = sp.random(m, n, density=3 / n, random_state=rng, format="csr") + sp.eye(m, n, format="csr")
        A = (A @ sp.diags(10 ** rng.uniform(-3, 0, n))).tocsr()
        truth = rng.uniform(0.05, 0.95, n)
        truth[rng.choice(n, 8, replace=False)] = rng.choice([-0.3, 1.3], 8)
        y = A @ truth
        solver = _BlockSolver.__new__(_BlockSolver)
        solver.ap, solver.Lp, solver.y = types.SimpleNamespace(sp=sp, orders=Orderings()), None, y
        solver._gram = solver._residual = None
        x, free, _ = solver.bounded(np.full(n, 0.5), A, np.zeros(m), np.ones(n, bool))
        ref = lsq_linear(A.toarray(), y, bounds=(0, 1), method="bvls", tol=1e-14).x
        assert ((ref <= 0) | (ref >= 1)).sum() > 40
        assert solver.unsettled is None
        np.testing.assert_allclose(x, ref, atol=1e-7)


def test_a_coarse_shininess_map_is_fitted_as_nonlinear_parameters():
    """A shininess map is not linear in the image: its texels are fitted like any nonlinear
    parameter (Levenberg–Marquardt beside the linear block), so at a coarse resolution: here a
    2×2 map (four regions of the sphere, clamped), with k_d and k_s free beside it, from four
    noise-free views."""
    starts, _, _, opts = _views(2, "bilinear", size=48, azimuths=(0, 90, 180, 270))
    m_true = np.random.default_rng(4).uniform(8.0, 60.0, (2, 2, 1))

    def with_material(s, shininess, diffuse, specular):
        tex = ds.Texture(shininess, filter="bilinear", wrap="clamp")
        mat = dataclasses.replace(
            s.material, diffuse_map=None, shininess_map=tex, shininess=1.0, diffuse=diffuse, specular=specular
        )
        return dataclasses.replace(s, material=mat)

    views = [with_material(s, m_true, jnp.asarray([0.6, 0.4, 0.3]), jnp.asarray(0.35)) for s in starts]
    targets = [np.asarray(ds.render(v, opts)) for v in views]
    starts = [with_material(s, np.full((2, 2, 1), 20.0), jnp.asarray([0.5] * 3), jnp.asarray(0.5)) for s in starts]
    free = ["material.shininess_map", "material.diffuse", "material.specular"]
    r = fitting.fit(starts[0], opts, fitting.Observations(targets, views=starts), free, intervals=False)
    assert r.successful, r.result
    truth = np.concatenate([m_true.ravel(), [0.6, 0.4, 0.3], [0.35] * 3])  # k_s per channel
    assert np.all(np.isfinite(r.stderr))
    np.testing.assert_allclose(r.values, truth, rtol=1e-3)
    assert np.all(np.abs(r.values - truth) <= 3 * r.stderr + 1e-6 * truth), (r.values, truth, r.stderr)


def test_the_verdicts_noise_level_counts_the_noise_the_texels_fit():
    """A map fits a share of the noise, so the white part of its residual lies below the noise;
    the verdict divides it by √κ, κ (difference_leverage: Hutchinson's estimate of a trace)
    against a simulation: noise drawn 200 times, projected out by the dense hat matrix, and the
    white-noise estimate of each residual averaged."""
    from fitting._block_solver import _BlockSolver, difference_leverage
    from fitting._report import white_noise

    starts, targets, truth, opts = _views(8, "bilinear", size=24)
    prob = Problem.build(starts[0], opts, fitting.Observations(targets, views=starts), ["material.diffuse_map"])
    mp = MapProblem(prob)
    theta = np.full(truth.size, 0.5)
    mp._compile(theta)
    red = _BlockSolver(mp, 0.0, 1e-10, False).reduced(theta)
    kappa = difference_leverage(prob, red)
    Af = red.A[:, red.free].toarray()
    Q = np.linalg.qr(Af)[0][:, : np.linalg.matrix_rank(Af)]  # H = Q Qᵀ
    rng = np.random.default_rng(0)
    used = prob.used_masks()
    sims = []
    for _ in range(200):
        e = rng.normal(0.0, 1.0, Af.shape[0])
        sims.append(white_noise(prob.images_of(e - Q @ (Q.T @ e)), used)[2] ** 2)
    kappa_mc = float(np.mean(sims))
    assert 0.0 < 1.0 - kappa_mc  # the texels took a share
    assert abs(kappa - kappa_mc) <= 0.25 * (1.0 - kappa_mc)


def test_the_degrees_of_freedom_of_a_block_stopped_by_its_rounds():
    """k proximal rounds with a ridge R fit a direction of information λ by the factor
    1 - (R/(λ+R))ᵏ: the block takes 2 tr H - tr H² degrees of freedom from the residual, where H is
    that filtered hat matrix (here dense, against effective_dof's estimate)."""
    from fitting._block_solver import effective_dof

    rng = np.random.default_rng(2)
    A = sp.random(3000, 120, density=0.03, random_state=rng, format="csr")
    A = sp.csr_matrix(A.toarray() * np.logspace(-3, 0, 120))  # columns from barely to well seen
    G = (A.T @ A).toarray()
    ridge, rounds = np.full(120, 1e-3), 3
    M_inv = np.linalg.inv(G + np.diag(ridge))

    def solve(w):
        return M_inv @ w

    solve.ridge, solve.rounds = ridge, rounds
    red = types.SimpleNamespace(A=A, free=np.ones(120, bool), solve=solve)
    F = np.linalg.solve(G, np.eye(120) - np.linalg.matrix_power(np.diag(ridge) @ M_inv, rounds).T)
    H = A.toarray() @ F @ A.T.toarray()
    exact = 2 * np.trace(H) - np.trace(H @ H)
    assert exact < 110  # the rounds left some directions unfitted
    assert abs(effective_dof(red, probes=64) - exact) < 0.05 * exact


def test_a_round_is_skipped_only_where_its_gain_extrapolated_is_far_under_the_floor():
    """The proximal rounds' gains, extrapolated geometrically from the two before, fall short of
    the next one's (iterated Tikhonov on a fixed face: a sum of geometric sequences, whose ratio
    only grows), so the rounds skip one only where the extrapolation is under the floor by
    ROUND_MARGIN. Measured gains: the 256² floor case's seed 0 (8.4e-2, 1.05e-2; the next one
    gained 3.6e-3 under its floor 5.9e-3) stops; the 128² sphere's seed 1 (3.0e-2, 4.7e-3; the
    next one gained 1.6e-3 over its floor 1.08e-3) goes on."""
    from fitting._block_solver import ROUND_MARGIN, _next_round_pays

    assert not _next_round_pays([8.37e-2, 1.054e-2], 5.89e-3)
    assert _next_round_pays([2.97e-2, 4.68e-3], 1.08e-3)
    assert _next_round_pays([1.0e-2], 1.0)  # one gain: no ratio yet
    assert _next_round_pays([1.0e-3, 2.0e-3], 1.0)  # not falling
    # the premise, on a dense problem: k rounds x_k = argmin |Ax - y|² + R |x - x_{k-1}|²
    rng = np.random.default_rng(3)
    A = rng.normal(size=(400, 60)) * np.logspace(-2.5, 0, 60)
    y = A @ rng.uniform(0, 1, 60) + rng.normal(0, 0.05, 400)
    G, R = A.T @ A, 1e-2 * np.eye(60)
    x, cost, gains = np.zeros(60), float(y @ y), []
    for _ in range(8):
        x = np.linalg.solve(G + R, A.T @ y + R @ x)
        r = A @ x - y
        cost, last = float(r @ r), cost
        gains.append(last - cost)
    gains = gains[1:]  # (the first round's began at the start)
    for k in range(2, len(gains)):
        assert gains[k] >= gains[k - 1] ** 2 / gains[k - 2] * (1 - 1e-9)  # the extrapolation falls short
    assert any(gains[k] < ROUND_MARGIN * gains[k - 1] ** 2 / gains[k - 2] for k in range(2, len(gains)))


def test_a_solve_whose_steps_ran_out_says_so(monkeypatch):
    """Noise-free targets, a ridge of a hundredth of each texel's information and a single
    conjugate-gradient step to remove its pull: the residual is still far above float rounding.
    The verdict names the steps that ran out with the cost still falling, not a local minimum or
    a model that cannot explain the images (with the default ridge and steps this fit settles
    and is successful: test_determined_texels_are_recovered_and_the_others_named)."""
    import fitting._block_solver as block_solver

    starts, targets, truth, opts = _views(16, "bilinear")
    for name, value in (("RIDGE", 1e-2), ("MAX_CONJUGATE", 1)):
        monkeypatch.setattr(block_solver, name, value)
    r = fitting.fit(starts[0], opts, fitting.Observations(targets, views=starts), ["material.diffuse_map"])
    assert not r.successful and not r.converged
    assert "1 conjugate-gradient steps ended with the cost still falling" in r.result
    assert "local minimum" not in r.result


def test_a_map_that_takes_every_degree_of_freedom_cannot_be_judged():
    """One 24² view of a 64² map: the texels it samples are as many as its residuals, so the
    residual says nothing about misfit against noise. The verdict says that. Before, it rested on
    the one degree of freedom it counted as left: this fit was called successful, and an 8-bit
    fit of a rabbit (bench_map_fit.py) a local minimum at 129× the noise."""
    starts, targets, truth, opts = _views(64, "bilinear", size=24, azimuths=(0,))
    r = fitting.fit(starts[0], opts, fitting.Observations(targets, views=starts), ["material.diffuse_map"])
    assert not r.successful
    assert "cannot be judged" in r.result and "degrees of freedom" in r.result and "local minimum" not in r.result


def test_the_host_solve_holds_blas_at_one_thread_and_its_standard_errors_begun_beside(monkeypatch):
    """A map fit's host solve runs with every BLAS at one thread (their spinning workers took the
    cores from the factorisations) and gives them back after; the standard errors' inverse
    diagonal begun beside the solve is the one made after it, to the bit."""
    from threadpoolctl import threadpool_info

    from fitting._block_solver import _BlockSolver, block_stderr

    starts, targets, truth, opts = _views(8, "bilinear", size=24)
    obs = fitting.Observations(targets, views=starts)
    blas = lambda: [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]  # noqa: E731
    before, during = blas(), []
    lm = _BlockSolver.lm

    def watched(self, *a, **k):
        during.append(blas())
        return lm(self, *a, **k)

    monkeypatch.setattr(_BlockSolver, "lm", watched)
    fitting.fit(starts[0], opts, obs, ["material.diffuse_map"], intervals=False)
    assert before and during and all(n == 1 for n in during[0])
    assert blas() == before
    monkeypatch.setattr(_BlockSolver, "lm", lm)

    prob = Problem.build(starts[0], opts, obs, ["material.diffuse_map"])
    mp = MapProblem(prob)
    theta = np.full(truth.size, 0.5)
    mp._compile(theta)
    solver = _BlockSolver(mp, 0.0, 1e-10, False)
    red = solver.reduced(theta)
    assert solver._beside is not None and solver._beside.serves(red.A, np.flatnonzero(red.seen))
    beside = block_stderr(mp, solver, red, 1.0)
    solver._beside = None
    after = block_stderr(mp, solver, red, 1.0)
    assert np.isfinite(after).any()
    np.testing.assert_array_equal(beside, after)
