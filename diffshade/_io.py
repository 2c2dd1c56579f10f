"""Scene files (TOML), validated on the host, and the built-in default scene.

A scene file::

    [mesh]
    path = "bunny.ply"          # relative to the scene file; or: icosphere = 3 (subdivisions)
    vertices = "authored"       # the file's vertices and normals (default); "merged": merged by position
    [camera]
    eye = [0, 0, 3]; target = [0, 0, 0]; up = [0, 1, 0]
    fov_y = 45.0; near = 0.1; far = 100.0; width = 256; height = 256
    [render]                    # static options (RenderOptions.from_keys: flat keys)
    shading = "phong"; specular = "phong"; fog = "exp"; layers = 1
    [material]
    ambient = [0.1, 0.1, 0.1]; diffuse = [0.7, 0.2, 0.2]; specular = 0.5; shininess = 40
    [[light]]
    type = "point"; color = [1, 1, 1]; position = [2, 2, 3]; attenuation = [1, 0.1, 0.01]
    [fog]
    color = [0.6, 0.6, 0.7]; density = 0.15

Several objects, each with its own material (material ids 0, 1, ... in order; a ``[mesh]`` with
``[material]``, if given, is object 0)::

    [[object]]
    quad = [6, 6]; normal = [0, 1, 0]; translate = [0, -1, 0]     # or icosphere/radius, box, path
    material = { diffuse = 0.8 }
    [[object]]
    box = [1, 1, 0.4]; translate = [0, 0, 0.5]; scale = 1.0
    [object.material]
    opacity = 0.3; absorption = [0.5, 1, 2]; transmission = 0.5; ior = 1.5   # kay = true, kay_min, kay_max, kay_power
    [render]
    transparency = true; absorption = true; transmission = true; layers = 4
    shadows = true; shadow_resolution = 1024; shadow_pcf = 3
    [shadow]
    bias = 0.001; slope_bias = 0.5

An area light (a rectangle of ``size = [w, h]`` facing ``normal``, its height along ``up``),
sampled as ``render.area_grid = [n, m]`` directed point emitters (default 4 × 4; attenuation
default ``[0, 0, 1]``, inverse-square; ``color = L w h`` is a Lambertian emitter of radiance L)::

    [[light]]
    type = "area"; color = [4, 4, 4]; position = [0, 2, 0]; normal = [0, -1, 0]; up = [0, 0, 1]; size = [1, 0.5]
    [render]
    area_grid = [8, 8]

A multi-lobe light: several spot lobes sharing one position and attenuation, one light (each
lobe as a spot light's keys, with its own colour and per-light ambient)::

    [[light]]
    type = "multi_lobe"; position = [0, 2, 2]; attenuation = [1, 0, 0.05]
    lobes = [{ axis = [0, -1, -1], cutoff = 30, exponent = 4, color = [1, 0.2, 0.2] },
             { axis = [1, -1, -1], cutoff = 20, edge = 5, color = [0.2, 0.2, 1] }]

A light's ``color`` is its diffuse and specular colour; ``specular = [r, g, b]`` gives it a
separate specular colour (OpenGL's ``GL_DIFFUSE`` / ``GL_SPECULAR``), and ``ambient`` its
per-light ambient colour (used with ``render.per_light_ambient``). ``render.compat = "opengl"``
starts from OpenGL's fixed-function choices (:meth:`RenderOptions.opengl`); other ``[render]``
keys override them.

Every error names the file, the field and the allowed range.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from ._camera import Camera, OpenCVCamera, OrthographicCamera
from ._domains import SceneError
from ._materials import _MATERIAL_FIELDS
from ._mesh import COLOR_MODES, VERTEX_MODES, Mesh, MeshError, box, combine, icosphere, load_mesh, quad
from ._mtl import load_material, map_texture
from ._options import RenderOptions, ShadowMaps, ShadowRays
from ._scene import (
    MAPPED_FIELDS,
    SCALAR_MAPPED,
    AreaLights,
    DirectionalLights,
    Fog,
    Material,
    MultiLobeLights,
    PointLights,
    Scene,
    SpotLights,
    no_area,
    no_directional,
    no_multi_lobe,
    no_point,
    no_spot,
)
from ._texture import FILTERS, WRAPS
from .color import EncodingError, parse_encoding


class _V:
    """Field validation helpers bound to a source name."""

    def __init__(self, source: str):
        self.source = source

    def fail(self, where: str, msg: str):
        raise SceneError(f"{self.source}: {where}: {msg}")

    def num(self, d: dict, key: str, where: str, default=None, lo=None, hi=None, lo_open=False, hi_open=False):
        if key not in d:
            if default is None:
                self.fail(f"{where}.{key}", "missing (required)")
            return float(default)
        x = d[key]
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            self.fail(f"{where}.{key}", f"must be a number, got {x!r}")
        x = float(x)
        if not math.isfinite(x):
            self.fail(f"{where}.{key}", f"must be finite, got {x}")
        rng = f"{'(' if lo_open else '['}{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}{')' if hi_open else ']'}"
        if lo is not None and (x < lo or (lo_open and x == lo)):
            self.fail(f"{where}.{key}", f"must lie in {rng}, got {x}")
        if hi is not None and (x > hi or (hi_open and x == hi)):
            self.fail(f"{where}.{key}", f"must lie in {rng}, got {x}")
        return x

    def vec(self, d: dict, key: str, where: str, n=3, default=None, lo=None, hi=None, scalar_ok=False, nonzero=False):
        if key not in d:
            if default is None:
                self.fail(f"{where}.{key}", "missing (required)")
            return np.asarray(default, dtype=np.float64)
        x = d[key]
        if scalar_ok and isinstance(x, (int, float)) and not isinstance(x, bool):
            x = [x] * n
        if (
            not isinstance(x, list)
            or len(x) != n
            or any(isinstance(e, bool) or not isinstance(e, (int, float)) for e in x)
        ):
            self.fail(
                f"{where}.{key}", f"must be a list of {n} numbers{' (or one number)' if scalar_ok else ''}, got {x!r}"
            )
        a = np.asarray(x, dtype=np.float64)
        if not np.isfinite(a).all():
            self.fail(f"{where}.{key}", f"must be finite, got {x!r}")
        if lo is not None and (a < lo).any():
            self.fail(f"{where}.{key}", f"each entry must be >= {lo}, got {x!r}")
        if hi is not None and (a > hi).any():
            self.fail(f"{where}.{key}", f"each entry must be <= {hi}, got {x!r}")
        if nonzero and not np.any(a):
            self.fail(f"{where}.{key}", "must not be the zero vector")
        return a

    def table(self, d: dict, key: str, required=False) -> dict:
        if key not in d:
            if required:
                self.fail(key, "missing section (required)")
            return {}
        t = d[key]
        if not isinstance(t, dict):
            self.fail(key, f"must be a table, got {type(t).__name__}")
        return t

    def unknown(self, d: dict, allowed, where: str):
        extra = sorted(set(d) - set(allowed))
        if extra:
            self.fail(where, f"unknown field(s) {extra}; allowed: {sorted(allowed)}")


def _key_defaults() -> dict:
    """Every flat ``[render]`` key with a value of its type (each group switched on)."""
    on = RenderOptions.from_keys(shadows=True, transparency=True, clamp=True, fog="exp").keys()
    return {**on, "shadow_ray_crossings": ShadowRays().crossings}


def _options(v: _V, r: dict) -> RenderOptions:
    defaults = _key_defaults()
    # back_material: a [back_material] table decides (the key is accepted, and read as that)
    v.unknown(r, (*defaults, "compat", "back_material"), "render")
    compat = r.get("compat", "diffshade")
    if compat not in ("diffshade", "opengl"):
        v.fail(
            "render.compat",
            f"must be 'diffshade' (the defaults) or 'opengl' (OpenGL's fixed-function choices), got {compat!r}",
        )
    kw = {}
    for k, x in r.items():
        if k == "compat":
            continue
        default = defaults.get(k, False)
        if isinstance(default, bool):
            if not isinstance(x, bool):
                v.fail(f"render.{k}", f"must be true or false, got {x!r}")
        elif isinstance(default, tuple):
            if not isinstance(x, list) or len(x) != len(default):
                v.fail(f"render.{k}", f"must be a list of {len(default)} positive integers, got {x!r}")
            x = tuple(x)
        elif isinstance(default, int):
            lowest = 0 if k in ("ray_depth", "shadow_ray_crossings", "ray_capacity") else 1
            if isinstance(x, bool) or not isinstance(x, int) or x < lowest:
                v.fail(f"render.{k}", f"must be an integer >= {lowest}, got {x!r}")
        if k != "back_material":
            kw[k] = x
    try:
        return RenderOptions.opengl(**kw) if compat == "opengl" else RenderOptions.from_keys(kw)
    except ValueError as exc:
        v.fail("render", str(exc).replace("RenderOptions.", ""))


_MAP_KEYS = tuple(f + "_map" for f in MAPPED_FIELDS)


def _resolve(path: str, base: Path | None) -> Path:
    """A file a scene file names: relative paths are relative to the scene file's folder."""
    p = Path(path)
    return base / p if not p.is_absolute() and base is not None else p


def _map(v: _V, m: dict, key: str, where: str, base: Path | None):
    """A ``<field>_map`` entry: an image path, or a table ``{path, wrap, filter, encoding}``."""
    spec = m[key]
    w = f"{where}.{key}"
    if isinstance(spec, str):
        spec = {"path": spec}
    if not isinstance(spec, dict) or not isinstance(spec.get("path"), str):
        v.fail(w, f"must be an image path or a table {{path, wrap, filter, encoding}}, got {spec!r}")
    v.unknown(spec, ("path", "wrap", "filter", "encoding"), w)
    for k, allowed in (("wrap", WRAPS), ("filter", FILTERS)):
        if k in spec and spec[k] not in allowed:
            v.fail(f"{w}.{k}", f"must be one of {', '.join(repr(a) for a in allowed)}, got {spec[k]!r}")
    field = key[: -len("_map")]
    if "encoding" in spec:
        if field in SCALAR_MAPPED:
            v.fail(f"{w}.encoding", f"a {field} map holds linear values; give no encoding")
        try:
            parse_encoding(spec["encoding"])
        except EncodingError as exc:
            v.fail(f"{w}.encoding", str(exc))
    p = _resolve(spec["path"], base)
    try:
        return map_texture(
            field, p, w, spec.get("encoding"), wrap=spec.get("wrap", "repeat"), filter=spec.get("filter", "trilinear")
        )
    except MeshError as exc:
        v.fail(w, str(exc).removeprefix(f"{w}: "))


def _material(v: _V, m: dict, where: str, gl: bool = False, base: Path | None = None) -> Material:
    """A material table; with ``gl`` (``render.compat = "opengl"``) the values left out are
    OpenGL's defaults, and shininess 0 is allowed (as in ``glMaterial``). ``mtl`` (an MTL file,
    or an OBJ that names one; ``mtl_material`` picks one of its materials) gives the values and
    maps as authored, the table's own entries override them; ``<field>_map`` names an image map."""
    keys = (*_MATERIAL_FIELDS, "kay", "casts_shadow", *_MAP_KEYS, "mtl", "mtl_material")
    v.unknown(m, keys, where)
    d = Material.opengl() if gl else Material()
    if "mtl_material" in m and "mtl" not in m:
        v.fail(f"{where}.mtl_material", "names a material of an 'mtl' file; give the file too")
    if "mtl" in m:
        d = _authored(v, m, where, base)
    maps = {k: _map(v, m, k, where, base) if k in m else getattr(d, k) for k in _MAP_KEYS}
    flags = {}
    for k, default in (("kay", False), ("casts_shadow", True)):
        flags[k] = m.get(k, default)
        if not isinstance(flags[k], bool):
            v.fail(f"{where}.{k}", f"must be true or false, got {flags[k]!r}")
    kay = flags["kay"]
    return Material(
        casts_shadow=flags["casts_shadow"],
        opacity=v.num(m, "opacity", where, default=float(d.opacity), lo=0.0, hi=1.0),
        kay=kay,
        kay_min=v.num(m, "kay_min", where, default=float(d.kay_min), lo=0.0, hi=1.0),
        kay_max=v.num(m, "kay_max", where, default=float(d.kay_max), lo=0.0, hi=1.0),
        kay_power=v.num(m, "kay_power", where, default=float(d.kay_power), lo=0.0, lo_open=True),
        transmission=v.vec(
            m, "transmission", where, default=np.asarray(d.transmission), lo=0.0, hi=1.0, scalar_ok=True
        ),
        absorption=v.vec(m, "absorption", where, default=np.asarray(d.absorption), lo=0.0, scalar_ok=True),
        mirror=v.vec(m, "mirror", where, default=np.asarray(d.mirror), lo=0.0, hi=1.0, scalar_ok=True),
        refraction=v.vec(m, "refraction", where, default=np.asarray(d.refraction), lo=0.0, hi=1.0, scalar_ok=True),
        emission=v.vec(m, "emission", where, default=np.asarray(d.emission), lo=0.0, scalar_ok=True),
        ambient=v.vec(m, "ambient", where, default=np.asarray(d.ambient), lo=0.0, hi=1.0, scalar_ok=True),
        diffuse=v.vec(m, "diffuse", where, default=np.asarray(d.diffuse), lo=0.0, hi=1.0, scalar_ok=True),
        specular=v.vec(m, "specular", where, default=np.asarray(d.specular), lo=0.0, hi=1.0, scalar_ok=True),
        shininess=v.num(m, "shininess", where, default=float(d.shininess), lo=0.0, lo_open=not gl),
        ior=v.num(m, "ior", where, default=float(d.ior), lo=0.0, lo_open=True),
        roughness=v.num(m, "roughness", where, default=float(d.roughness), lo=0.0, lo_open=True, hi=1.0),
        roughness_y=v.num(m, "roughness_y", where, default=float(d.roughness_y), lo=0.0, lo_open=True, hi=1.0),
        diffuse_roughness=v.num(m, "diffuse_roughness", where, default=float(d.diffuse_roughness), lo=0.0),
        tangent=v.vec(m, "tangent", where, default=np.asarray(d.tangent), nonzero=True),
        **maps,
    )


def _authored(v: _V, m: dict, where: str, base: Path | None) -> Material:
    """The material an ``mtl`` entry names (:func:`diffshade.load_material`)."""
    for k in ("mtl", "mtl_material"):
        if k in m and not isinstance(m[k], str):
            v.fail(f"{where}.{k}", f"must be a string, got {m[k]!r}")
    try:
        return load_material(_resolve(m["mtl"], base), m.get("mtl_material"))
    except MeshError as exc:
        v.fail(f"{where}.mtl", str(exc))


_LIGHT_KINDS = ("directional", "point", "spot", "area", "multi_lobe")


def _lights(v: _V, lights: list):
    """The ``[[light]]`` tables as structures of arrays, one per kind (in the file's order)."""
    if not isinstance(lights, list):
        v.fail("light", "must be an array of tables ([[light]])")
    groups: dict[str, list] = {k: [] for k in _LIGHT_KINDS}
    # separate specular colours (OpenGL's GL_SPECULAR) by kind and row; ``color`` sets both otherwise
    specular: dict[str, dict[int, np.ndarray]] = {"directional": {}, "point": {}, "spot": {}}
    if not isinstance(lights, list):
        v.fail("light", f"must be an array of tables ([[light]]), got {type(lights).__name__}")
    for i, l in enumerate(lights):
        w = f"light[{i}]"
        if not isinstance(l, dict):
            v.fail(w, "must be a table")
        kind = l.get("type")
        if not isinstance(kind, str) or kind not in groups:
            v.fail(f"{w}.type", f"must be one of {', '.join(repr(k) for k in _LIGHT_KINDS)}, got {kind!r}")
        if "specular" in l and kind in specular:
            specular[kind][len(groups[kind])] = v.vec(l, "specular", w, lo=0.0, scalar_ok=True)
        groups[kind].append(_multi_lobe_row(v, l, w) if kind == "multi_lobe" else _light_row(v, l, w, kind))
    near = {r[3] is not None for r in groups["directional"]}
    if len(near) > 1:
        v.fail("light", "either every directional light has a distance (near lights) or none has")
    return _stack_lights(groups, specular)


def _attenuation(v: _V, l: dict, w: str, default):
    att = v.vec(l, "attenuation", w, default=default, lo=0.0)
    if not np.any(att):
        v.fail(f"{w}.attenuation", "a0, a1, a2 must not all be 0")
    return att


def _multi_lobe_row(v: _V, l: dict, w: str):
    """``(position, attenuation, lobes)`` of a multi-lobe light table."""
    v.unknown(l, ("type", "position", "attenuation", "lobes"), w)
    pos = v.vec(l, "position", w)
    att = _attenuation(v, l, w, [1.0, 0.0, 0.0])
    lobes = l.get("lobes")
    if not isinstance(lobes, list) or not lobes or not all(isinstance(b, dict) for b in lobes):
        v.fail(f"{w}.lobes", "must be a non-empty array of tables (axis, cutoff, exponent, edge, color, ambient)")
    return pos, att, [_spot_lobe(v, b, f"{w}.lobes[{j}]", lobe=True) for j, b in enumerate(lobes)]


def _light_row(v: _V, l: dict, w: str, kind: str):
    """One directional, point, spot or area light table as its kind's row (colour first)."""
    common = ("type", "color", "ambient") + (("specular",) if kind != "area" else ())
    color = v.vec(l, "color", w, default=[1.0, 1.0, 1.0], lo=0.0, scalar_ok=True)
    amb = v.vec(l, "ambient", w, default=[0.0, 0.0, 0.0], lo=0.0, scalar_ok=True)
    if kind == "directional":  # a distance makes it a near light (an LED pointed at its origin)
        v.unknown(l, common + ("direction", "distance", "origin", "falloff"), w)
        direction = v.vec(l, "direction", w, nonzero=True)
        if "distance" not in l:
            for k in ("origin", "falloff"):
                if k in l:
                    v.fail(f"{w}.{k}", "is a near light's: give its distance too")
            return color, direction, amb, None, None, None
        dist = v.num(l, "distance", w, lo=0.0, lo_open=True)
        origin = v.vec(l, "origin", w, default=[0.0, 0.0, 0.0])
        return color, direction, amb, dist, origin, v.num(l, "falloff", w, default=0.0, lo=0.0)
    pos = v.vec(l, "position", w)
    # an area light is physical by default: inverse-square falloff from each emitter
    att = _attenuation(v, l, w, [0.0, 0.0, 1.0] if kind == "area" else [1.0, 0.0, 0.0])
    if kind == "point":
        v.unknown(l, common + ("position", "attenuation"), w)
        return color, pos, att, amb
    if kind == "spot":
        v.unknown(l, common + ("position", "attenuation", "axis", "cutoff", "exponent", "edge"), w)
        return (color, pos, att, amb, *_spot_lobe(v, l, w)[2:])
    v.unknown(l, common + ("position", "attenuation", "normal", "up", "size"), w)
    normal = v.vec(l, "normal", w, nonzero=True)
    up = v.vec(l, "up", w, default=[0.0, 1.0, 0.0], nonzero=True)
    if np.linalg.norm(np.cross(normal / np.linalg.norm(normal), up / np.linalg.norm(up))) < 1e-6:
        v.fail(f"{w}.up", "must not be parallel to the normal (it orients the rectangle's height)")
    size = v.vec(l, "size", w, n=2, lo=0.0)
    if not np.all(size > 0):
        v.fail(f"{w}.size", f"width and height must be > 0, got {size.tolist()}")
    return color, pos, att, amb, normal, up, size


def _directional(g: list, specular) -> DirectionalLights:
    """The directional rows ``(color, direction, ambient, distance, origin, falloff)`` stacked
    (near lights where they have a distance: all or none do, :func:`_lights` checked)."""
    if not g:
        return no_directional()
    near = g[0][3] is not None
    return DirectionalLights(
        color=np.stack([r[0] for r in g]),
        direction=np.stack([r[1] for r in g]),
        ambient=np.stack([r[2] for r in g]),
        specular=specular,
        distance=np.array([r[3] for r in g]) if near else None,
        origin=np.stack([r[4] for r in g]) if near else None,
        falloff=np.array([r[5] for r in g]) if near else None,
    )


def _stack_lights(groups: dict, specular: dict):
    """The rows of each kind stacked into its structure of arrays (an empty one where none)."""

    def stack(rows, k):
        return np.stack([r[k] for r in rows]) if rows else np.zeros((0, 3))

    def spec(kind):
        """The kind's specular colours (a light without its own takes its colour), or None."""
        given = specular[kind]
        return np.stack([given.get(i, r[0]) for i, r in enumerate(groups[kind])]) if given else None

    directional = _directional(groups["directional"], spec("directional"))
    g = groups["point"]
    point = (
        PointLights(
            color=stack(g, 0),
            position=stack(g, 1),
            attenuation=stack(g, 2),
            ambient=stack(g, 3),
            specular=spec("point"),
        )
        if g
        else no_point()
    )
    g = groups["spot"]
    spot = (
        SpotLights(
            color=stack(g, 0),
            position=stack(g, 1),
            attenuation=stack(g, 2),
            ambient=stack(g, 3),
            axis=stack(g, 4),
            cutoff=np.array([r[5] for r in g]),
            exponent=np.array([r[6] for r in g]),
            edge=np.array([r[7] for r in g]),
            specular=spec("spot"),
        )
        if g
        else no_spot()
    )
    g = groups["area"]
    area = (
        AreaLights(
            color=stack(g, 0),
            position=stack(g, 1),
            attenuation=stack(g, 2),
            ambient=stack(g, 3),
            normal=stack(g, 4),
            up=stack(g, 5),
            size=np.stack([r[6] for r in g]),
        )
        if g
        else no_area()
    )
    g = groups["multi_lobe"]
    if not g:
        return directional, point, spot, area, no_multi_lobe()
    L = max(len(r[2]) for r in g)
    dark = (np.zeros(3), np.zeros(3), np.array([0.0, 0.0, -1.0]), 90.0, 0.0, 0.0)  # padding: emits nothing
    lob = [r[2] + [dark] * (L - len(r[2])) for r in g]
    field = lambda k: np.array([[b[k] for b in row] for row in lob])  # noqa: E731
    multi = MultiLobeLights(
        position=stack(g, 0),
        attenuation=stack(g, 1),
        color=field(0),
        ambient=field(1),
        axis=field(2),
        cutoff=field(3),
        exponent=field(4),
        edge=field(5),
    )
    return directional, point, spot, area, multi


def _spot_lobe(v: "_V", b: dict, w: str, lobe: bool = False):
    """``(color, ambient, axis, cutoff, exponent, edge)`` of a spot light or (``lobe``) a lobe table."""
    if lobe:
        v.unknown(b, ("color", "ambient", "axis", "cutoff", "exponent", "edge"), w)
    color = v.vec(b, "color", w, default=[1.0, 1.0, 1.0], lo=0.0, scalar_ok=True)
    amb = v.vec(b, "ambient", w, default=[0.0, 0.0, 0.0], lo=0.0, scalar_ok=True)
    axis = v.vec(b, "axis", w, nonzero=True)
    cutoff = v.num(b, "cutoff", w, lo=0.0, hi=90.0)  # 0: a closed cone, dark
    exponent = v.num(b, "exponent", w, default=0.0, lo=0.0)
    edge = v.num(b, "edge", w, default=0.0, lo=0.0, hi=cutoff)
    return color, amb, axis, cutoff, exponent, edge


_MESH_KEYS = ("path", "vertices", "colors", "icosphere", "radius", "box", "quad", "normal", "divisions")


def _mesh(v: _V, m: dict, where: str, base: Path | None) -> Mesh:
    """One mesh: a file (``path``), or a primitive: ``icosphere`` (subdivisions, with ``radius``),
    ``box`` (extents), ``quad`` (size, with ``normal`` and ``divisions``)."""
    v.unknown(m, _MESH_KEYS, where)
    kinds = [k for k in ("path", "icosphere", "box", "quad") if k in m]
    if len(kinds) != 1:
        v.fail(
            where,
            "give exactly one of 'path' (a mesh file), 'icosphere' (subdivisions), 'box' (extents) or 'quad' (size)",
        )
    kind = kinds[0]
    for k, owner in (
        ("radius", "icosphere"),
        ("normal", "quad"),
        ("divisions", "quad"),
        ("vertices", "path"),
        ("colors", "path"),
    ):
        if k in m and kind != owner:
            v.fail(f"{where}.{k}", f"only applies to '{owner}'")
    if kind == "path":
        if not isinstance(m["path"], str):
            v.fail(f"{where}.path", f"must be a string, got {m['path']!r}")
        p = _resolve(m["path"], base)
        mode = m.get("vertices", "authored")
        if mode not in VERTEX_MODES:
            v.fail(
                f"{where}.vertices",
                f"must be 'authored' (the file's vertices and normals, the default) or 'merged' "
                f"(vertices merged by position, smooth normals computed), got {mode!r}",
            )
        cmode = m.get("colors", "srgb")
        if cmode not in COLOR_MODES:
            v.fail(f"{where}.colors", f"how the file's vertex colours are encoded: one of {COLOR_MODES}, got {cmode!r}")
        try:
            return load_mesh(p, mode, cmode)
        except MeshError as exc:
            v.fail(f"{where}.path", str(exc))
    if kind == "icosphere":
        sub = m["icosphere"]
        if isinstance(sub, bool) or not isinstance(sub, int) or not 0 <= sub <= 7:
            v.fail(f"{where}.icosphere", f"must be an integer in [0, 7], got {sub!r}")
        return icosphere(sub, v.num(m, "radius", where, default=1.0, lo=0.0, lo_open=True))
    if kind == "box":
        ext = v.vec(m, "box", where, scalar_ok=True)
        if (ext <= 0).any():
            v.fail(f"{where}.box", f"extents must be > 0, got {ext.tolist()}")
        return box(ext)
    size = v.vec(m, "quad", where, n=2, scalar_ok=True)
    if (size <= 0).any():
        v.fail(f"{where}.quad", f"sides must be > 0, got {size.tolist()}")
    div = m.get("divisions", 1)
    if isinstance(div, bool) or not isinstance(div, int) or not 1 <= div <= 256:
        v.fail(f"{where}.divisions", f"must be an integer in [1, 256], got {div!r}")
    return quad(size, normal=v.vec(m, "normal", where, default=[0.0, 0.0, 1.0], nonzero=True), divisions=div)


def scene_from_dict(d: dict[str, Any], source: str = "scene", base: Path | None = None) -> tuple[Scene, RenderOptions]:
    """Build and validate a scene from a dictionary (the parsed TOML)."""
    v = _V(source)
    v.unknown(
        d,
        (
            "mesh",
            "camera",
            "render",
            "material",
            "back_material",
            "light",
            "fog",
            "ambient_light",
            "background",
            "object",
            "shadow",
        ),
        "scene",
    )
    opts = _options(v, v.table(d, "render"))
    gl = v.table(d, "render").get("compat") == "opengl"
    mesh, materials = _objects(v, d, base, gl)
    if opts.raster.vertex_color != "none" and mesh.colors is None:
        v.fail(
            "render.vertex_color",
            f"is {opts.raster.vertex_color!r} but the mesh has no vertex colours (a PLY "
            "with red green blue, an OBJ with v x y z r g b)",
        )
    camera = _camera(v, v.table(d, "camera", required=True), "camera")
    back = _material(v, d["back_material"], "back_material", gl, base) if "back_material" in d else None
    if back is not None and len(materials) > 1:
        v.fail("back_material", "applies to a one-material scene; give each object its own material instead")
    sh = v.table(d, "shadow")
    v.unknown(sh, ("bias", "slope_bias"), "shadow")
    if sh and not isinstance(opts.shadows, ShadowMaps):
        v.fail("render.shadows", "a [shadow] section is given but render.shadows is false")
    directional, point, spot, area, multi = _lights(v, d.get("light", []))
    fog = _fog(v, v.table(d, "fog"), gl, opts)
    ambient = v.vec(d, "ambient_light", "scene", default=[0.2, 0.2, 0.2], lo=0.0, scalar_ok=True)
    # A fogged scene shows the fog colour where nothing is drawn, unless told otherwise (docs/model.md §3).
    bg_default = np.asarray(fog.color) if opts.fog is not None else [0.0, 0.0, 0.0]
    background = v.vec(d, "background", "scene", default=bg_default, lo=0.0, scalar_ok=True)
    if opts.output.antialias:
        mesh = mesh.with_adjacency()  # the silhouette edges' topology, while the faces are concrete
    scene = Scene(
        mesh=mesh,
        camera=camera,
        material=materials[0],
        back_material=back,
        directional=directional,
        point=point,
        spot=spot,
        area=area,
        multi_lobe=multi,
        ambient_light=ambient,
        background=background,
        fog=fog,
        materials=materials[1:],
        **{f"shadow_{k}": v.num(sh, k, "shadow", lo=0.0) for k in sh},  # absent: defaults
    )
    return scene, opts


def _objects(v: _V, d: dict, base: Path | None, gl: bool) -> tuple[Mesh, tuple[Material, ...]]:
    """The scene's mesh (its objects combined) and their materials by id: a ``[mesh]`` with
    ``[material]``, if given, is object 0, then each ``[[object]]`` in order."""
    objects = d.get("object", [])
    if not isinstance(objects, list) or not all(isinstance(o, dict) for o in objects):
        v.fail("object", "must be an array of tables ([[object]])")
    parts = []
    if "mesh" in d or not objects:
        parts.append(
            (
                _mesh(v, v.table(d, "mesh", required=True), "mesh", base),
                _material(v, v.table(d, "material"), "material", gl, base),
            )
        )
    elif "material" in d:
        v.fail("material", "with [[object]] and no [mesh], give each object its own [object.material]")
    for i, o in enumerate(objects):
        w = f"object[{i}]"
        v.unknown(o, _MESH_KEYS + ("translate", "scale", "material"), w)
        m = _mesh(v, {k: x for k, x in o.items() if k in _MESH_KEYS}, w, base)
        shift = v.vec(o, "translate", w, default=[0.0, 0.0, 0.0])
        scale = v.vec(o, "scale", w, default=[1.0, 1.0, 1.0], lo=0.0, scalar_ok=True)
        if np.any(scale == 0):
            v.fail(f"{w}.scale", "must not be 0")
        mo = o.get("material", {})
        if not isinstance(mo, dict):
            v.fail(f"{w}.material", "must be a table")
        nrm = None if m.normals is None else np.asarray(m.normals) / scale  # normals transform by the inverse
        parts.append(
            (
                Mesh(
                    vertices=np.asarray(m.vertices) * scale + shift,
                    faces=m.faces,
                    normals=nrm,
                    colors=m.colors,
                    uv=m.uv,
                ),
                _material(v, mo, f"{w}.material", gl, base),
            )
        )
    for i, (m, mat) in enumerate(parts):
        if mat.maps() and m.uv is None:
            w = "material" if i == 0 and "mesh" in d else f"object[{i - int('mesh' in d)}].material"
            names = ", ".join(k for k in _MAP_KEYS if getattr(mat, k) is not None)
            v.fail(w, f"has texture maps ({names}) but its mesh has no texture coordinates (an OBJ with vt, or a quad)")
    try:
        mesh = parts[0][0] if len(parts) == 1 else combine(*(p[0] for p in parts))
    except ValueError as exc:
        v.fail("object", str(exc))
    return mesh, tuple(p[1] for p in parts)


def _fog(v: _V, f: dict, gl: bool, opts: RenderOptions) -> Fog:
    """The ``[fog]`` table (OpenGL's defaults with ``gl``); a table without a fog mode is an error."""
    v.unknown(f, ("color", "start", "end", "density"), "fog")
    fog_default = Fog.opengl() if gl else Fog()
    start = v.num(f, "start", "fog", default=float(fog_default.start), lo=0.0)
    end = v.num(f, "end", "fog", default=max(float(fog_default.end), start), lo=start)
    fog = Fog(
        color=v.vec(f, "color", "fog", default=np.asarray(fog_default.color), lo=0.0, scalar_ok=True),
        start=start,
        end=end,
        density=v.num(f, "density", "fog", default=float(fog_default.density), lo=0.0),
    )
    if f and opts.fog is None:
        v.fail("render.fog", "a [fog] section is given but render.fog is 'none'; set it to 'linear', 'exp' or 'exp2'")
    return fog


_GL_CAMERA = ("eye", "target", "up", "fov_y")
_CV_CAMERA = ("K", "fx", "fy", "cx", "cy", "R", "rvec", "t", "tvec", "distortion")
_ORTHO_CAMERA = ("eye", "target", "up", "pixel_size")
_ANY_CAMERA = ("model", "near", "far", "width", "height", "exposure", "white_balance", "black_level")


def _matrix(v: _V, d: dict, key: str, where: str, shape):
    x = d[key]
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        a = None
    if a is None or a.shape != shape or isinstance(x, (str, bool)):
        v.fail(f"{where}.{key}", f"must be a {shape[0]}x{shape[1]} matrix (a list of {shape[0]} rows), got {x!r}")
    if not np.isfinite(a).all():
        v.fail(f"{where}.{key}", "must be finite")
    return a


def _camera(v: _V, c: dict, w: str):
    """A camera table: OpenGL's (eye, target, up, fov_y; ``model = "opengl"``, the default),
    OpenCV's (``model = "opencv"``: K or fx, fy, cx, cy; R or rvec; t or tvec; optional
    distortion) or an orthographic one (``model = "orthographic"``: eye, target, up,
    pixel_size), with near, far, width, height and the gain (exposure, white_balance, black_level)."""
    model = c.get("model", "opencv" if any(k in c for k in _CV_CAMERA) else "opengl")
    keys = {"opengl": _GL_CAMERA, "opencv": _CV_CAMERA, "orthographic": _ORTHO_CAMERA}
    if model not in keys:
        v.fail(f"{w}.model", f"must be 'opengl', 'opencv' or 'orthographic', got {model!r}")
    v.unknown(c, _ANY_CAMERA + keys[model], w)
    size = {}
    for k in ("width", "height"):
        x = c.get(k, 256)
        if isinstance(x, bool) or not isinstance(x, int) or not 1 <= x <= 8192:
            v.fail(f"{w}.{k}", f"must be an integer in [1, 8192], got {x!r}")
        size[k] = x
    gain = dict(
        exposure=v.num(c, "exposure", w, default=1.0, lo=0.0, lo_open=True),
        white_balance=v.vec(c, "white_balance", w, default=[1.0, 1.0, 1.0], scalar_ok=True),
        black_level=v.vec(c, "black_level", w, default=[0.0, 0.0, 0.0], scalar_ok=True),
    )
    if (gain["white_balance"] <= 0).any():
        v.fail(f"{w}.white_balance", f"gains must be > 0, got {gain['white_balance'].tolist()}")
    if model == "opencv":
        near = v.num(c, "near", w, default=0.1, lo=0.0, lo_open=True)
        far = v.num(c, "far", w, default=100.0, lo=near, lo_open=True)
        if "K" in c:
            if any(k in c for k in ("fx", "fy", "cx", "cy")):
                v.fail(w, "give the intrinsics as K or as fx, fy, cx, cy, not both")
            K = _matrix(v, c, "K", w, (3, 3))
        else:
            fx, fy = (v.num(c, k, w, lo=0.0, lo_open=True) for k in ("fx", "fy"))
            K = np.array([[fx, 0.0, v.num(c, "cx", w)], [0.0, fy, v.num(c, "cy", w)], [0.0, 0.0, 1.0]])
        if ("R" in c) == ("rvec" in c):
            v.fail(w, "give the rotation as R (3x3) or as rvec (axis-angle), one of them")
        if ("t" in c) == ("tvec" in c):
            v.fail(w, "give the translation as t or as tvec, one of them")
        rot = dict(R=_matrix(v, c, "R", w, (3, 3))) if "R" in c else dict(rvec=v.vec(c, "rvec", w))
        t = v.vec(c, "t" if "t" in c else "tvec", w)
        dist = np.zeros(5)
        if "distortion" in c:
            x = c["distortion"]
            if not isinstance(x, list) or len(x) not in (4, 5, 8):
                v.fail(
                    f"{w}.distortion",
                    f"must be OpenCV's 4, 5 or 8 coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6]]), got {x!r}",
                )
            dist = v.vec(c, "distortion", w, n=len(x))
        try:
            return OpenCVCamera.from_opencv(K, t=t, near=near, far=far, distortion=dist, **rot, **size, **gain)
        except ValueError as exc:
            v.fail(w, str(exc))
    eye = v.vec(c, "eye", w)
    target = v.vec(c, "target", w, default=[0.0, 0.0, 0.0])
    up = v.vec(c, "up", w, default=[0.0, 1.0, 0.0], nonzero=True)
    if np.allclose(eye, target):
        v.fail(f"{w}.target", f"must differ from {w}.eye")
    if np.linalg.norm(np.cross(target - eye, up)) < 1e-9 * np.linalg.norm(target - eye) * np.linalg.norm(up):
        v.fail(f"{w}.up", "must not be parallel to the viewing direction")
    near = v.num(c, "near", w, default=0.1, lo=0.0, lo_open=True)
    far = v.num(c, "far", w, default=100.0, lo=near, lo_open=True)
    if model == "orthographic":
        px = v.num(c, "pixel_size", w, lo=0.0, lo_open=True)
        return OrthographicCamera(eye=eye, target=target, up=up, pixel_size=px, near=near, far=far, **size, **gain)
    fov = v.num(c, "fov_y", w, default=45.0, lo=0.0, hi=180.0, lo_open=True, hi_open=True)
    return Camera(eye=eye, target=target, up=up, fov_y=fov, near=near, far=far, **size, **gain)


def load_camera(path: str | Path) -> Camera | OpenCVCamera | OrthographicCamera:
    """A camera from a JSON or TOML file with the keys of a scene file's ``[camera]`` table (an
    OpenCV calibration: ``K``, ``R``/``rvec``, ``t``/``tvec``, ``distortion``, ``width``,
    ``height``; OpenGL's ``eye``, ``target``, ``up``, ``fov_y``; or an orthographic camera's
    ``model = "orthographic"``, ``eye``, ``target``, ``up``, ``pixel_size``)."""
    import json

    path = Path(path)
    if not path.exists():
        raise SceneError(f"{path}: camera file not found")
    try:
        if path.suffix.lower() == ".json":
            d = json.loads(path.read_text())
        else:
            with open(path, "rb") as fh:
                d = tomllib.load(fh)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SceneError(f"{path}: not valid {'JSON' if path.suffix.lower() == '.json' else 'TOML'}: {exc}") from exc
    except OSError as exc:
        raise SceneError(f"{path}: cannot read: {exc}") from exc
    if not isinstance(d, dict):
        raise SceneError(f"{path}: must hold a table of camera fields, got {type(d).__name__}")
    v = _V(str(path))
    return _camera(v, d.get("camera", d) if isinstance(d.get("camera"), dict) else d, "camera")


def load_scene(path: str | Path) -> tuple[Scene, RenderOptions]:
    """Load and validate a TOML scene file; returns ``(scene, options)``."""
    path = Path(path)
    if not path.exists():
        raise SceneError(f"{path}: scene file not found")
    try:
        with open(path, "rb") as fh:
            d = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"{path}: not valid TOML: {exc}") from exc
    except OSError as exc:
        raise SceneError(f"{path}: cannot read: {exc}") from exc
    return scene_from_dict(d, str(path), path.parent)


DEFAULT_SCENE: dict[str, Any] = {
    "mesh": {"icosphere": 4},
    "camera": {
        "eye": [0.0, 0.0, 3.0],
        "target": [0.0, 0.0, 0.0],
        "up": [0.0, 1.0, 0.0],
        "fov_y": 45.0,
        "near": 0.5,
        "far": 10.0,
        "width": 256,
        "height": 256,
    },
    "render": {"shading": "phong", "specular": "phong", "fog": "exp"},
    "material": {
        "ambient": [0.15, 0.12, 0.1],
        "diffuse": [0.75, 0.35, 0.25],
        "specular": [0.5, 0.5, 0.5],
        "shininess": 30.0,
    },
    "light": [
        {"type": "point", "color": [1.0, 1.0, 1.0], "position": [2.0, 2.0, 3.0], "attenuation": [1.0, 0.05, 0.02]},
        {"type": "directional", "color": [0.3, 0.3, 0.35], "direction": [1.0, -0.5, -1.0]},
    ],
    "fog": {"color": [0.55, 0.6, 0.7], "density": 0.12},
    "ambient_light": [0.3, 0.3, 0.3],
}


def default_scene() -> tuple[Scene, RenderOptions]:
    """The built-in default scene: a 5,120-face icosphere, a point and a directional light, exp fog."""
    return scene_from_dict(DEFAULT_SCENE, "default scene")
