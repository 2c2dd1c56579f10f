import contextlib
import os
import re
from importlib.metadata import version

# The suite compiles far more than it runs (each test its own programs, 2 cores), so it asks XLA
# for the cheapest compile: its CPU code emitters of older design, and LLVM without optimisation
# (--xla_backend_optimization_level=0). Measured on jaxlib 0.10.2, 2 cores: `make test`'s pytest
# 10:05 with the default, 6:33 with both (tests/test_trace.py and test_numerics.py: 199 s of CPU
# with the older emitters alone, 109 s with both); what they emit runs slower (a fit's solve 1.2-2x),
# which is why the library leaves XLA's defaults alone. XLA reads XLA_FLAGS at JAX's first
# computation, and aborts on an option it does not know: only for jaxlib 0.10 (0.10.0 and 0.10.2
# checked), and never over an XLA_FLAGS that already chooses the emitters (to run the suite on the
# defaults: XLA_FLAGS=--xla_cpu_use_fusion_emitters=true). Subprocesses (the notebooks' kernels,
# the CLI, the sharding tests) inherit it. LLVM's expensive passes off too
# (--xla_llvm_disable_expensive_passes): tests/test_shading.py 52.8 -> 38.5 s, test_fit.py (more
# running than compiling) 37.8 -> 35.8 s, on top of the two above.
FAST_COMPILE = (
    "--xla_cpu_use_fusion_emitters=false --xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
)
if re.match(r"0\.10\.", version("jaxlib")) and "xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {FAST_COMPILE}".strip()

# Tests compare against float64 finite differences; the library itself never changes jax.config.
import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
import pytest  # noqa: E402

MESHES = os.path.join(os.path.dirname(__file__), "data", "meshes")  # real meshes, with their licences


def shared_mesh_dir():
    return os.path.abspath(MESHES)


def _cast(tree, dtype):
    import jax.numpy as jnp

    return jax.tree.map(lambda a: a.astype(dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, tree)


def float32(tree):
    """``tree`` (a scene, or any pytree) with its floating-point leaves in float32: what the native
    kernels render."""
    return _cast(tree, np.float32)


def float64(tree):
    """``tree`` with its floating-point leaves in float64: what only the JAX stages render."""
    return _cast(tree, np.float64)


@contextlib.contextmanager
def compiles():
    """The names of the programs XLA compiles inside the ``with`` block (a list, filled as it runs)."""
    names = []

    def count(event, duration, **kw):
        if event.endswith("backend_compile_duration"):
            names.append(kw.get("fun_name"))

    jax.monitoring.register_event_duration_secs_listener(count)
    try:
        yield names
    finally:
        jax.monitoring.unregister_event_duration_listener(count)


def small_default_scene(width=32, height=32, **render):
    """The default scene on a 320-face icosphere at a small image size, render options overridden."""
    import diffshade as ds

    d = dict(ds.DEFAULT_SCENE)
    d["camera"] = dict(d["camera"], width=width, height=height)
    d["mesh"] = {"icosphere": 2}
    d["render"] = dict(d["render"], **render)
    return ds.scene_from_dict(d)


def opencv_look_at(eye, target=(0.0, 0.0, 0.0)):
    """OpenCV pose ``(R, t)`` of a camera at ``eye`` looking at ``target``, image y down."""
    eye, target = np.asarray(eye, np.float64), np.asarray(target, np.float64)
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    R = np.stack([right, np.cross(fwd, right), fwd])
    return R, -R @ eye


def pose_problem(size=64, antialias=False):
    """The pose-refinement set-up: the default scene (no fog) on a per-vertex-coloured icosphere,
    an OpenCV camera at its truth ``(R, t)`` and a start 1.97° and 3.7 cm off. Returns
    ``(start, opts, target, R, t, off_deg)``, ``off_deg(rvec)`` the angle from the truth."""
    import equinox as eqx
    import jax.numpy as jnp
    import trimesh

    import diffshade as ds
    from diffshade._camera import rotation_to_rvec

    d = {k: v for k, v in ds.DEFAULT_SCENE.items() if k != "fog"}
    d["render"] = dict(d["render"], fog="none")
    scene, opts = ds.scene_from_dict(d)
    opts = opts.with_keys(vertex_color="diffuse", antialias=antialias)
    tm = trimesh.creation.icosphere(3)
    v = np.asarray(tm.vertices)
    cols = np.clip(0.5 + 0.35 * np.sin(5 * v[:, 0]) * np.cos(4 * v[:, 1] + 2 * v[:, 2]), 0.05, 0.95)[:, None]
    scene = eqx.tree_at(lambda s: s.mesh, scene, ds.Mesh(vertices=v, faces=tm.faces, colors=cols * [1.0, 0.8, 0.6]))
    f = size / 2 / np.tan(np.deg2rad(22.5))
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1]])
    R, t = opencv_look_at([0.5, 0.4, 3.0])

    def cam(R_, t_):
        return ds.OpenCVCamera.from_opencv(K, R=R_, t=t_, width=size, height=size, near=0.5, far=10.0)

    target = np.asarray(ds.render(eqx.tree_at(lambda s: s.camera, scene, cam(R, t)), opts))
    dR = np.asarray(ds.rodrigues(jnp.asarray(np.deg2rad([1.5, -1.0, 0.8]))))
    start = eqx.tree_at(lambda s: s.camera, scene, cam(dR @ R, t + [0.02, -0.01, 0.03]))

    def off_deg(rvec):
        Rf = np.asarray(ds.rodrigues(jnp.asarray(rvec)))
        return np.rad2deg(np.linalg.norm(rotation_to_rvec(Rf @ R.T)))

    return start, opts, target, R, t, off_deg


def check_grads(f, args, order=1, modes=("fwd", "rev"), atol=None, rtol=None, eps=None):
    """``jax.test_util.check_grads`` (its checks, tolerances and random directions, through its own
    ``check_jvp`` and ``check_vjp``) for ``order=1`` with two compiled programs instead of four:
    the JVP, whose primal output also gives the finite differences, and the whole VJP (forward
    pass and transpose) as one program. ``check_grads`` itself compiles the primal, the JVP, the
    linearised forward pass and the transpose, and the compiles are most of a gradient test's
    time on 2 cores."""
    import jax.numpy as jnp
    from jax import test_util

    if order != 1:
        return test_util.check_grads(f, args, order, modes, atol=atol, rtol=rtol, eps=eps)
    args = tuple(args)
    kw = dict(atol=atol, rtol=rtol, **({} if eps is None else {"eps": eps}))
    zeros = lambda t: jax.tree.map(jnp.zeros_like, t)  # noqa: E731
    if "fwd" in modes:
        push = jax.jit(lambda a, t: jax.jvp(f, a, t))

        def primal(*a):
            return push(a, zeros(a))[0]

        test_util.check_jvp(primal, lambda a, t: push(tuple(a), tuple(t)), args, **kw)
    if "rev" in modes:

        def both(a, u):
            out, back = jax.vjp(f, *a)
            return out, back(u)

        pull = jax.jit(both)
        u0 = zeros(jax.eval_shape(f, *args))
        if "fwd" not in modes:  # (a custom_vjp function has no JVP)

            def primal(*a):
                return pull(a, u0)[0]

        test_util.check_vjp(primal, lambda *a: (primal(*a), lambda u: pull(a, u)[1]), args, **kw)


@pytest.fixture(scope="session")
def meshes_dir():
    return shared_mesh_dir()


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture(scope="session", autouse=True)
def isolated_compilation_cache(tmp_path_factory):
    """The CLI turns on JAX's persistent compilation cache (``$DIFFSHADE_CACHE``, by default the
    user's ``~/.cache/diffshade/xla``). Tests that run it, in this process or in a subprocess,
    use a cache of this session's own: they never read entries another run left (a worker once crashed
    with a segfault reading an entry of the shared cache) and never write into the user's."""
    old = os.environ.get("DIFFSHADE_CACHE")
    os.environ["DIFFSHADE_CACHE"] = str(tmp_path_factory.mktemp("xla-cache"))
    yield
    if old is None:
        os.environ.pop("DIFFSHADE_CACHE", None)
    else:
        os.environ["DIFFSHADE_CACHE"] = old
