import os

# Tests compare against float64 finite differences; the library itself never changes jax.config.
import jax

jax.config.update("jax_enable_x64", True)

import numpy as np
import pytest

MESHES = os.path.join(os.path.dirname(__file__), "data", "meshes")  # real meshes, with their licences


def shared_mesh_dir():
    return os.path.abspath(MESHES)


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
