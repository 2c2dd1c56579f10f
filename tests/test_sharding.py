"""Views stacked into one program, sharded over devices, and over processes (jax.distributed).

The device count and the distributed runtime are fixed when JAX starts, so the multi-device fits
run in processes of their own (``tests/sharded_fit.py``); pytest's own process checks the
stacking itself."""

import json
import os
import socket
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from conftest import small_default_scene

import diffshade as ds
from fitting import Observations
from fitting._problem import Problem, ViewData, stack_views, view_devices

HERE = os.path.dirname(os.path.abspath(__file__))
WORKER = os.path.join(HERE, "sharded_fit.py")
sys.path.insert(0, HERE)
from sharded_fit import FREE, TRUTH  # noqa: E402


def _truth():
    return np.concatenate([np.atleast_1d(TRUTH[n]) for n in FREE]).astype(np.float64)


def _run(args, devices=None):
    """tests/sharded_fit.py in a process of its own, with the suite's XLA flags (conftest's
    cheapest compile) and, where given, that many host devices."""
    env = dict(os.environ)
    if devices is not None:
        env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={devices}".strip()
    return subprocess.Popen(
        [sys.executable, WORKER, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        cwd=os.path.join(HERE, ".."),
    )


def _result(p, timeout=420):
    out, err = p.communicate(timeout=timeout)
    assert p.returncode == 0, err[-3000:]
    return [json.loads(line) for line in out.splitlines() if line.startswith("{")]


def _views(n=3):
    scene, opts = small_default_scene()
    out = []
    for k in range(n):
        a = 2 * np.pi * k / n
        c = scene.camera
        cam = ds.Camera(
            eye=[3 * np.sin(a), 0.5, 3 * np.cos(a)],
            target=c.target,
            up=c.up,
            fov_y=c.fov_y,
            near=c.near,
            far=c.far,
            width=32,
            height=32,
            exposure=1.0 + 0.2 * k,
        )
        out.append(eqx.tree_at(lambda s: s.camera, scene, cam))
    return scene, opts, out


def test_stacked_views_render_what_the_views_do_one_by_one():
    """Views of one structure are stacked (one program maps over them, with per-view parameters
    selected by a traced view index); the flat image is the one the views give one by one."""
    scene, opts, views = _views()
    targets = [np.asarray(ds.render(v, opts)) for v in views]
    free = ["material.diffuse", "material.shininess", "view[*].camera.exposure"]
    prob = Problem.build(scene, opts, Observations(targets, views=views), free)
    assert prob.stacked
    data = prob.device_data()
    assert isinstance(data, ViewData) and data.target.shape[0] == 3
    assert len({vd.target.shape for vd in prob.data}) == 1  # padded alike
    theta = np.asarray(prob.pset.theta_of(scene, views), np.float64)
    theta = theta * np.linspace(0.9, 1.1, len(theta))  # every view's exposure differs
    images = jax.jit(prob.images)
    one_by_one = np.asarray(images(jnp.asarray(theta), prob.data))
    stacked = np.asarray(images(jnp.asarray(theta), data))
    np.testing.assert_allclose(stacked, one_by_one, rtol=0, atol=1e-12)
    # the exposure of view k scales view k alone
    th2 = theta.copy()
    th2[-1] *= 2.0  # view 2's
    img2 = np.asarray(images(jnp.asarray(th2), data)).reshape(3, -1)
    img1 = stacked.reshape(3, -1)
    np.testing.assert_allclose(img2[:2], img1[:2], atol=1e-12)
    np.testing.assert_allclose(img2[2], 2.0 * img1[2], rtol=1e-12, atol=1e-14)
    # and without a per-view parameter: the same images
    prob = Problem.build(scene, opts, Observations(targets, views=views), free[:2])
    theta = jnp.asarray(theta[: len(prob.pset.labels)])
    images = jax.jit(prob.images)
    np.testing.assert_allclose(
        np.asarray(images(theta, prob.device_data())), np.asarray(images(theta, prob.data)), rtol=0, atol=1e-12
    )


def test_views_of_another_structure_are_not_stacked():
    """A view with another image size (or light count) is its own piece of the program."""
    scene, opts, views = _views(2)
    c = views[1].camera
    big = eqx.tree_at(
        lambda s: s.camera,
        views[1],
        ds.Camera(eye=c.eye, target=c.target, up=c.up, fov_y=c.fov_y, near=c.near, far=c.far, width=40, height=40),
    )
    targets = [np.asarray(ds.render(v, opts)) for v in (views[0], big)]
    prob = Problem.build(scene, opts, Observations(targets, views=[views[0], big]), ["material.diffuse"])
    assert not prob.stacked and isinstance(prob.device_data(), list)
    assert stack_views(prob.data) is None


def test_device_count_divides_the_views():
    devs = [f"d{i}" for i in range(4)]
    assert view_devices(devs, 8) == tuple(devs)
    assert view_devices(devs, 6) == tuple(devs[:3])
    assert view_devices(devs, 5) == tuple(devs[:1])
    assert len(view_devices(None, 4)) == len(jax.devices())


def test_views_sharded_over_four_host_devices():
    """Four views on four host devices: each device holds one view's pixels, the compiled
    programs' only communication is all-reduces of the small normal-equation terms (no operand
    grows with the pixels), and the fit equals the one-device fit to 1e-6 (and the truth)."""
    p = _run(["devices"], devices=4)
    one, four = _result(p)
    assert one["devices"] == 1 and four["devices"] == 4
    assert sorted(four["shards"]) == [[0, 1], [1, 1], [2, 1], [3, 1]]
    assert one["shards"] == [[0, 4]]
    coll = four["collectives"]
    assert coll, "a sharded program with no communication cannot reduce over the views"
    assert {k for k, _ in coll} == {"all-reduce"}
    n_free = len(four["values"])
    assert max(s for _, s in coll) <= (n_free + 1) ** 2 < four["pixels"]
    assert one["successful"] and four["successful"]
    a, b = np.asarray(one["values"]), np.asarray(four["values"])
    np.testing.assert_allclose(b, a, rtol=1e-6)
    np.testing.assert_allclose(a, _truth(), rtol=1e-6)


def test_two_processes_on_localhost():
    """The same fit under jax.distributed: two processes with two host devices each, the views
    sharded over all four; both end at the truth and at the same values."""
    with socket.socket() as s:
        s.bind(("localhost", 0))
        port = str(s.getsockname()[1])
    procs = [_run(["process", str(i), "2", port]) for i in range(2)]
    res = [_result(p)[0] for p in procs]
    assert sorted(r["process"] for r in res) == [0, 1]
    assert all(r["devices"] == 4 and r["local"] == 2 for r in res)
    assert all(r["successful"] for r in res)
    a, b = (np.asarray(r["values"]) for r in res)
    np.testing.assert_allclose(a, b, rtol=1e-12)
    np.testing.assert_allclose(a, _truth(), rtol=1e-6)
