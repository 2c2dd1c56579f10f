"""A multi-view fit, run in its own process by ``test_sharding.py`` (the device count and the
distributed runtime are fixed when JAX starts, so they cannot be changed inside pytest's).

    python tests/sharded_fit.py devices N            # N host devices; fits on 1 and on all N
    python tests/sharded_fit.py process PID NPROC PORT  # one of NPROC processes on localhost

Prints one JSON line per fit: the values, whether successful, and (devices mode) how the
stacked views are placed and which collectives the compiled programs contain.
"""

import json
import os
import re
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))

import jax  # noqa: E402

if __name__ == "__main__" and sys.argv[1] == "process":
    # before anything else touches JAX's backends
    jax.config.update("jax_num_cpu_devices", 2)
    jax.distributed.initialize(
        coordinator_address=f"localhost:{sys.argv[4]}",
        num_processes=int(sys.argv[3]),
        process_id=int(sys.argv[2]),
        initialization_timeout=120,
    )
jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402

import diffshade as ds  # noqa: E402
from fitting import Observations, fit  # noqa: E402
from fitting._problem import Problem  # noqa: E402

TRUTH = {
    "material.diffuse": [0.75, 0.35, 0.25],
    "material.specular": [0.5, 0.5, 0.5],
    "material.shininess": 30.0,
    "point[0].a1": 0.05,
    "view[*].camera.exposure": [1.1, 1.2, 1.3],
}

FREE = ["material.diffuse", "material.specular", "material.shininess", "point[0].a1", "view[*].camera.exposure"]
SIZE, N_VIEWS = 32, 4


def views():
    d = dict(ds.DEFAULT_SCENE)
    d["camera"] = dict(d["camera"], width=SIZE, height=SIZE)
    d["mesh"] = {"icosphere": 2}
    scene, opts = ds.scene_from_dict(d)
    out = []
    for k in range(N_VIEWS):
        a = 2 * np.pi * k / N_VIEWS
        c = scene.camera
        cam = ds.Camera(
            eye=[3 * np.sin(a), 0.5, 3 * np.cos(a)],
            target=c.target,
            up=c.up,
            fov_y=c.fov_y,
            near=c.near,
            far=c.far,
            width=SIZE,
            height=SIZE,
            exposure=1.0 + 0.1 * k,
        )
        out.append(eqx.tree_at(lambda s: s.camera, scene, cam))
    targets = [np.asarray(ds.render(v, opts)) for v in out]
    # the start: every view at exposure 1, the material off
    start = eqx.tree_at(
        lambda s: (s.material.diffuse, s.material.shininess),
        scene,
        (scene.material.diffuse * 0.7, scene.material.shininess * 1.5),
    )
    starts = [eqx.tree_at(lambda s: s.camera, start, eqx.tree_at(lambda c: c.exposure, v.camera, 1.0)) for v in out]
    return start, opts, targets, starts


def collectives():
    """Every collective in the compiled programs: (kind, elements of its largest operand)."""
    from fitting._cache import _CACHE

    out = []
    for c in _CACHE.values():
        for m in re.finditer(
            r"= (.+?) (all-gather|all-reduce|all-to-all|collective-permute|reduce-scatter)"
            r"(?:-start)?\(",
            c.as_text(),
        ):
            sizes = [
                int(np.prod([int(d) for d in dims.split(",") if d] or [1]))
                for dims in re.findall(r"\w+\[([\d,]*)\]", m.group(1))
            ]
            out.append((m.group(2), max(sizes)))
    return out


def main(mode):
    scene, opts, targets, starts = views()
    if mode == "devices":
        for n in (1, len(jax.devices())):
            devs = jax.devices()[:n]
            prob = Problem.build(scene, opts, Observations(targets, views=starts), FREE, devices=devs)
            placed = prob.device_data()
            shards = [(s.device.id, s.data.shape[0]) for s in placed.target.addressable_shards]
            r = fit(scene, opts, Observations(targets, views=starts), FREE, devices=devs)
            print(
                json.dumps(
                    dict(
                        devices=n,
                        values=r.values.tolist(),
                        successful=bool(r.successful),
                        names=r.names,
                        shards=shards,
                        pixels=int(placed.target.shape[1]),
                        collectives=collectives() if n > 1 else [],
                    )
                ),
                flush=True,
            )
    else:
        r = fit(scene, opts, Observations(targets, views=starts), FREE)
        print(
            json.dumps(
                dict(
                    process=jax.process_index(),
                    devices=len(jax.devices()),
                    local=len(jax.local_devices()),
                    values=r.values.tolist(),
                    successful=bool(r.successful),
                )
            ),
            flush=True,
        )


if __name__ == "__main__":
    main(sys.argv[1])
