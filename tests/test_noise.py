"""The targets' own noise (fitting._noise): second differences of the image, a robust spread, and
a variance that grows with the signal, against images with known noise."""

import numpy as np
import pytest

from fitting._noise import details, robust_variance, variance_model

H, W = 120, 160
yy, xx = np.mgrid[0:H, 0:W] / np.array([H, W])[:, None, None]
# a smooth shaded surface: a gradient, a curved falloff and a soft highlight
SMOOTH = np.clip(
    0.15 + 0.5 * xx + 0.2 * np.cos(3 * yy) + 0.3 * np.exp(-((xx - 0.6) ** 2 + (yy - 0.4) ** 2) / 0.02), 0, 1
)
SMOOTH = SMOOTH[..., None] * np.array([1.0, 0.8, 0.6])
USED = np.ones((H, W, 3), bool)


def _estimate(img, used=USED, floor=0.0):
    d, m = details(img, used)
    out = []
    for c in range(3):
        a, b = variance_model(d[c], m[c], floor)
        t = img[..., c][used[..., c]]
        out.append(np.mean(a + b * t))
    return float(np.sqrt(np.mean(out)))


@pytest.mark.parametrize("sigma", [0.001, 0.004, 0.02])
@pytest.mark.parametrize("bits", [8, 16, None])
def test_gaussian_noise_is_measured_within_ten_percent(sigma, bits):
    rng = np.random.default_rng(int(sigma * 1e4) + (bits or 0))
    noisy = SMOOTH + rng.normal(0, sigma, SMOOTH.shape)
    q = 0.0 if bits is None else 1 / (2**bits - 1)
    target = noisy if bits is None else np.round(noisy / q) * q
    true = float(np.sqrt(np.mean((target - SMOOTH) ** 2)))  # quantisation included: the residual has it too
    assert abs(_estimate(target, floor=2 * q) / true - 1) < 0.1


@pytest.mark.parametrize("gain", [0.0005, 0.004])
def test_photon_noise_that_grows_with_the_signal_is_measured_on_average(gain):
    # variance = read² + gain·signal: the mean over the pixels is what RSS/n is at the truth
    rng = np.random.default_rng(11)
    var = 0.001**2 + gain * SMOOTH
    target = SMOOTH + rng.normal(0, 1, SMOOTH.shape) * np.sqrt(var)
    true = float(np.sqrt(np.mean((target - SMOOTH) ** 2)))
    assert abs(_estimate(target) / true - 1) < 0.1
    d, m = details(target, USED)
    a, b = variance_model(d[0], m[0], 0.0)
    assert abs(b / gain - 1) < 0.2 and a < 0.5 * gain * float(SMOOTH[..., 0].mean())


def test_a_few_windows_still_measure_the_photon_term():
    # a small object (a 64² bunny's views: ~350 windows a channel): two bins of levels still give
    # the line's slope, so a view brighter than the mean is not read as misfit; one bin said b = 0
    a0, b0 = 0.004**2, 4 * 0.004**2
    rng = np.random.default_rng(3)
    bright = []
    for _ in range(40):
        m = rng.uniform(0.05, 1.0, 350)
        d = rng.normal(0, 1, 350) * np.sqrt(a0 + b0 * m)
        a, b = variance_model(d, m, 0.0)
        assert b > 0 or a > 0
        bright.append((a + b * 0.9) / (a0 + b0 * 0.9))  # the variance predicted at a bright level
    assert abs(np.median(bright) - 1) < 0.1 and np.mean(np.abs(np.asarray(bright) - 1) < 0.3) > 0.8


def test_edges_and_a_few_jumps_do_not_count_as_noise():
    rng = np.random.default_rng(5)
    sigma = 0.004
    target = SMOOTH + rng.normal(0, sigma, SMOOTH.shape)
    target[:, W // 2 :] += 0.3  # an albedo edge
    hit = rng.uniform(size=(H, W)) < 0.01  # hot pixels
    target[hit] += 0.5
    assert abs(_estimate(target) / sigma - 1) < 0.1
    # unused pixels (the background, a hole in the mask) are left out, whatever they hold
    used = USED.copy()
    used[:, :20] = False
    target[:, :20] = rng.uniform(size=(H, 20, 3))
    assert abs(_estimate(target, used) / sigma - 1) < 0.1


def test_robust_variance_edge_cases():
    assert robust_variance(np.zeros(0)) == 0.0
    assert robust_variance(np.zeros(100)) == 0.0  # noise-free: no spread, no floor
    q = 1 / 255  # noise far below a code step: mostly zeros; the floor keeps the few steps
    d = np.where(np.random.default_rng(0).uniform(size=1000) < 0.05, q / 2, 0.0)
    assert 0 < robust_variance(d, 2 * q) < q**2
    assert details(np.zeros((2, 5, 3)), np.ones((2, 5, 3), bool))[0][0].size == 0  # too small for a window


def test_the_verdict_counts_two_sided_entries_inside_the_range():
    # a dark 8-bit target at the truth: entries at code 0 are censored (their one-sided residual
    # is not a draw of the noise) and entries whose model lies within 3σ of 0 read truncated
    # noise; the χ² leaves both out, so a residual of pure noise elsewhere is 1× the noise
    import jax
    from conftest import small_default_scene

    import diffshade as ds
    from fitting import Observations
    from fitting._problem import Problem
    from fitting._report import candidate, noise_ratio_limit

    scene, opts = small_default_scene(48, 48)
    clean = np.asarray(jax.jit(lambda s: ds.render(s, opts))(scene), np.float64) * 0.04
    sigma = 2 / 255
    rng = np.random.default_rng(2)
    target = np.round(np.clip(clean + rng.normal(0, sigma, clean.shape), 0, 1) * 255) / 255
    prob = Problem.build(scene, opts, Observations(target, saturation=1.0, quantum=1 / 255), ["material.diffuse"])
    n = sum(vd.target.shape[0] for vd in prob.data)
    model = np.zeros(3 * n)
    b = prob.views[0]  # one view: the model at its compacted pixels
    model.reshape(-1, 3)[: len(b.rows)] = clean.reshape(-1, 3)[b.rows]
    r = np.where(prob.two_sided(), rng.normal(0, sigma, 3 * n), 0.0)
    r = np.where(np.concatenate([np.asarray(vd.lo).reshape(-1) for vd in prob.data]), 3 * sigma, r)  # one-sided
    keep = prob.inside_range(model, 3 * sigma) & prob.two_sided()
    n2 = int(prob.two_sided().sum())
    cand = candidate(prob, (np.ones(3), r, np.zeros((3 * n, 3)), model, np.zeros(3, bool), 0, True), "", n2, sigma)
    assert cand.n_chi2 == int(keep.sum()) < n2 and cand.rss2 == float(r[keep] @ r[keep])
    assert abs(cand.ratio - 1) < noise_ratio_limit(cand.n_chi2) - 1
    assert np.sqrt(float(r @ r) / (n2 - 3)) / sigma > noise_ratio_limit(n2)  # the censored in: rejected


def test_tied_window_means_leave_no_empty_bin():
    # many windows at one value (a flat, clipped or dark region) tie the quantiles: a bin that
    # gets no window is left out, not a NaN in the fit of the variance
    rng = np.random.default_rng(1)
    d = rng.normal(0, 0.01, 5000)
    m = np.where(rng.uniform(size=5000) < 0.8, 0.0, rng.uniform(0, 1, 5000))
    a, b = variance_model(d, m, 0.0)
    assert np.isfinite(a) and np.isfinite(b) and abs(np.sqrt(a + b * m.mean()) / 0.01 - 1) < 0.1


def test_downsampling_keeps_what_was_clipped():
    # a 2x2 block with one clipped sub-pixel averages below the level: it is marked clipped, and
    # a fit takes it as a lower bound (censored from above) where the global level would not
    import jax
    from conftest import small_default_scene

    import diffshade as ds
    from fitting import Observations, downsample
    from fitting._problem import Problem

    img = np.full((8, 10, 3), 0.5)
    img[0, 0, 1] = 1.0  # one green sub-pixel at the level
    mask = np.ones((8, 10))
    mask[7, 9] = 0
    d = downsample(img, 2, saturation=1.0, mask=mask)
    assert d.image.shape == (4, 5, 3) and abs(d.image[0, 0, 1] - 0.625) < 1e-12 and d.image[0, 0, 1] < 1.0
    assert d.clipped[0, 0].tolist() == [False, True, False] and d.clipped.sum() == 1
    assert d.mask[3, 4] == 0 and d.mask[0, 0] == 1
    with pytest.raises(ValueError, match="factor"):
        downsample(img, 0)
    scene, opts = small_default_scene(24, 24)
    target = np.asarray(jax.jit(lambda s: ds.render(s, opts))(scene), np.float64)
    clipped = np.zeros((24, 24), bool)
    clipped[12, 12] = True
    prob = Problem.build(scene, opts, Observations(target, saturation=1.0, clipped=[clipped]), ["material.diffuse"])
    hi = prob.images_of(np.concatenate([np.asarray(vd.hi).reshape(-1) for vd in prob.data]))[0]
    assert (target < 1).all() and hi[12, 12].all() and int(hi.sum()) == 3
    from fitting import FitError

    with pytest.raises(FitError, match="clipped 0: shape"):
        Problem.build(scene, opts, Observations(target, clipped=[np.zeros((5, 5), bool)]), ["material.diffuse"])


def test_the_reports_image_quality_is_scikit_images_psnr_and_ssim():
    """The report's PSNR (its definition, written out) and SSIM (scikit-image's own module) are
    scikit-image's public metrics over the target's range; an exact match gives PSNR inf."""
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    from fitting._report import image_quality

    rng = np.random.default_rng(7)
    target = rng.uniform(0.1, 0.8, (24, 20, 3))
    fitted = target + rng.normal(0, 0.02, target.shape)
    span = target.max() - target.min()
    psnr, ssim = image_quality(fitted, target)
    assert psnr == pytest.approx(peak_signal_noise_ratio(target, fitted, data_range=span), rel=1e-12)
    assert ssim == pytest.approx(structural_similarity(target, fitted, channel_axis=-1, data_range=span), rel=1e-12)
    assert image_quality(target, target) == (float("inf"), pytest.approx(1.0))


def test_level_dependent_noise_weights_calibrate_the_standard_errors():
    """Renders with known read + photon noise (σ² = a + b I per entry), 40 seeds: fitted with the
    level-dependent noise model (Observations(noise_model="level"): weights σ̄/σ at the model),
    the standard errors are calibrated (each parameter's z-scores spread 0.75–1.25; at most 3 of
    280 beyond 3 s.e., 0.76 expected); fitted with uniform weights the specular's spread is
    understated (its z-scores spread beyond 1.25: the highlights are noisier than it assumes)."""
    import equinox as eqx

    import diffshade as ds
    from fitting import Observations, fit

    s = ds.icosphere(4)
    cam = ds.Camera(
        eye=[0, 0, 3.0], target=[0, 0, 0], up=[0, 1, 0], fov_y=45.0, near=0.5, far=10.0, width=48, height=48
    )
    mat = ds.Material(ambient=0.0, diffuse=[0.6, 0.45, 0.3], specular=0.5, shininess=30.0)
    lights = ds.DirectionalLights(color=[[1, 1, 1.0]], direction=[[-0.3, -0.4, -1.0]], ambient=[[0, 0, 0.0]])
    scene = ds.Scene(mesh=ds.Mesh(s.vertices, s.faces), camera=cam, material=mat, directional=lights, ambient_light=0.0)
    opts = ds.RenderOptions.from_keys(shading="phong", specular="blinn", fog="none")
    img = np.asarray(ds.render(scene, opts), np.float64)
    a, b = 0.002**2, 0.0009
    free = ["material.diffuse", "material.specular", "material.shininess"]
    truth = np.r_[0.6, 0.45, 0.3, 0.5, 0.5, 0.5, 30.0]
    grey = ds.Material(ambient=0.0, diffuse=[0.5, 0.5, 0.5], specular=0.3, shininess=20.0)
    start = eqx.tree_at(lambda s: s.material, scene, grey)
    z = {}
    for model in ("uniform", "level"):
        rows = []
        for seed in range(40):
            rng = np.random.default_rng(seed)
            t = img + rng.normal(size=img.shape) * np.sqrt(a + b * np.clip(img, 0, None))
            r = fit(start, opts, Observations([t], noise_model=model), free, intervals=False)
            assert r.successful, (model, seed, r.result)
            rows.append((r.values - truth) / r.stderr)
        z[model] = np.array(rows)
    spread = z["level"].std(0)
    assert (spread > 0.75).all() and (spread < 1.25).all(), spread
    assert (np.abs(z["level"]) > 3).sum() <= 3
    assert z["uniform"][:, 3:6].std(0).max() > 1.25, z["uniform"].std(0)
    assert any("level-dependent weights" in n for n in r.notes), r.notes


@pytest.mark.parametrize("offset", [0.0, 0.006])
def test_the_read_noise_is_measured_where_the_signal_is_zero(offset):
    """Dark entries clipped at the sensor's zero (an attached shadow, half of it read 0): the
    censored likelihood gives the read noise back (within 10 %; the clipped entries' mean
    square, taken as read, is 0.5σ²), and a constant the model lacks there (a black level) is
    the offset, not noise."""
    from fitting._noise import dark_read_noise

    rng = np.random.default_rng(3)
    sigma, b = 0.004, 6e-5
    mu = np.where(rng.uniform(size=4000) < 0.7, 0.0, rng.uniform(0, 2 * sigma, 4000))  # shadow and its rim
    y_true = mu + offset + rng.normal(size=mu.size) * np.sqrt(sigma**2 + b * mu)
    cens = y_true <= 0
    y = np.where(cens, 0.0, y_true)
    assert 0.2 < cens.mean() < 0.5 or offset > 0
    a, c = dark_read_noise(y, mu, cens, b)
    assert abs(np.sqrt(a) / sigma - 1) < 0.1 and abs(c - offset) < 0.1 * sigma
    naive = float(np.mean((y - mu - offset) ** 2))  # the clipped entries' residuals taken as read
    assert abs(np.sqrt(naive) / sigma - 1) > 0.2 or offset > 0


def test_noise_free_dark_entries_do_not_pin_the_variance_at_zero():
    """Noise-free 16-bit dark entries all read one code: their censored-likelihood variance is
    0, and as a point of the variance line weighed by its precision it would outweigh every bin
    (weights of 1e18: a fit's residual then read 1e-10× the noise and a wrong model passed). The
    variance stays at or above the codes' quantisation q²/12, and the bins still shape the line."""
    from fitting._noise import anchored

    q2 = (1 / 65535) ** 2 / 12
    bins = [[(0.2, 3e-11, 500), (0.5, 5e-11, 500), (0.8, 7e-11, 500)]] * 3
    models = [(1.8e-11, 6.7e-11)] * 3

    def dark(bounds):
        return [(np.full(300, 0.015), np.zeros(300), np.zeros(300, bool))] * 3

    out, used = anchored(models, bins, dark, q2)
    for a, b in out:
        assert a >= q2 * 0.99 and b > 0, (a, b)
    assert all(u is not None and u[0] == 300 and abs(u[1] - 0.015) < 1e-6 for u in used)
