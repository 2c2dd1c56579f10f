"""Free parameters by name, with their domains handled by reparametrisation.

optimistix's least-squares solvers are unconstrained, so each free parameter ``θ`` is solved for
through an unconstrained ``u``:

- ``unit`` ([0, 1], reflectances k_a, k_d, k_s, k_t, opacity t and Kay's t_min, t_max, fog
  colour): ``θ = sigmoid(u)``;
- ``positive`` (exponent m, Kay's p, absorption μ, attenuation a_i, fog density, light colours,
  emission):
  ``θ = exp(u)``, so the solver works on a log scale (m from 1 to 10⁴ is one scale);
- ``interval(lo, hi)`` (spot cutoff, index of refraction): ``θ = lo + (hi - lo) sigmoid(u)``;
- ``real`` (a light's position, x y z in scene units): ``θ = u``.

Names: ``material.<field>``, ``material[i].<field>`` (material id ``i`` of a multi-material
scene; ``material[0]`` is ``material``) and ``back_material.<field>`` (emission, ambient, diffuse,
specular, shininess, roughness, roughness_y, diffuse_roughness, ior, opacity, kay_min, kay_max, kay_power,
transmission, absorption, mirror, refraction; the roughnesses α of Cook–Torrance and Ward in (0, 1), Oren–Nayar's σ positive);
``ambient_light``; ``<kind>[i].<field>`` with kind ``directional``, ``point``,
``spot`` or ``area`` and field ``color``, ``specular`` (a separate specular colour, where the scene gives
one), ``ambient``, ``a0``/``a1``/``a2`` (attenuation), ``position``
(not directional), ``cutoff``,
``exponent``, ``edge`` (spot), ``width``, ``height`` (area: with the colour, a gauge for a distant
receiver, which sees only the power); ``multi_lobe[i].<position|a0|a1|a2>`` (shared by the lobes) and
``multi_lobe[i].lobe[j].<color|ambient|cutoff|exponent|edge>``; ``fog.<field>`` (color, start, end, density);
``directional[i].direction``, ``spot[i].axis`` and ``material.tangent`` (Ward's): two angles in degrees, the tilt from the
start direction about two axes normal to it (a chart of the sphere centred on the start: no pole
where a light points straight down; the fitted direction is ``direction_of(tilt, frame)``);
``mesh.colors`` (per-vertex albedo, ``[0, 1]``, 3 per vertex; fitted by :mod:`fitting._albedo`);
``material.<emission|ambient|diffuse|specular|shininess|opacity>_map`` (a texture map's texels, at
the start map's resolution: the first four are a linear block, fitted by :mod:`fitting._maps`);
``camera.exposure`` (one gain), ``camera.white_balance`` (RGB gains) and, for an OpenCV camera,
``camera.rvec``/``camera.tvec`` (its pose). RGB fields are per channel unless listed as shared
(one value for the three channels).

**Per view.** A name is shared by every view unless it starts with ``view[i].``: then it is view
``i``'s alone (``view[2].camera.exposure``, ``view[1].point[0].position``), and its start value is
read from that view's scene. ``view[*].<name>`` stands for every view but view 0, the reference
whose gains stay 1: the gauge of exposure and white balance (docs/model.md §9), since
``exposure · white_balance · k`` is all an image shows; ``view[:].<name>`` for every view, view 0
too (a term without a gauge: ``camera.black_level``, a near light's ``directional[0].distance``).
"""

from __future__ import annotations

import dataclasses
import functools
import re
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import diffshade as ds


class ParamError(ValueError):
    """An unknown parameter name, or a start value outside the parameter's domain."""


_RGB = {"emission", "ambient", "diffuse", "specular", "color", "transmission", "absorption", "mirror", "refraction"}
_MATERIAL = {
    "emission": "positive",
    "ambient": "unit",
    "diffuse": "unit",
    "specular": "unit",
    "shininess": "positive",
    "roughness": (0.0, 1.0),
    "roughness_y": (0.0, 1.0),
    "diffuse_roughness": "positive",
    "ior": (1.0, 4.0),
    "opacity": "unit",
    "kay_min": "unit",
    "kay_max": "unit",
    "kay_power": "positive",
    "transmission": "unit",
    "absorption": "positive",
    "mirror": "unit",
    "refraction": "unit",
}
_LIGHT = {
    "color": "positive",
    "ambient": "positive",
    "a0": "positive",
    "a1": "positive",
    "a2": "positive",
    "cutoff": (0.0, 90.0),
    "exponent": "positive",
    "edge": (0.0, 90.0),
    "width": "positive",
    "height": "positive",
    "position": "real",
    "specular": "positive",
    "distance": "positive",
    "origin": "real",
    "falloff": "positive",
}
_NEAR = ("distance", "origin", "falloff")  # a near directional light's (docs/model.md §1)
_SIZE = {"width": 0, "height": 1}  # an area light's size[i, k]
_KINDS = ("directional", "point", "spot", "area", "multi_lobe")
_LOBE = {"color", "ambient", "cutoff", "exponent", "edge"}
_FOG = {"color": "unit", "start": "positive", "end": "positive", "density": "positive"}
_CAMERA = {"exposure": "positive", "white_balance": "positive", "black_level": "real", "rvec": "real", "tvec": "real"}
_VIEW_RE = re.compile(r"^view\[(\d+|\*|:)\]\.(.+)$")
_LIGHT_RE = re.compile(r"^(directional|point|spot|area)\[(\d+)\]\.(\w+)$")
_LOBE_RE = re.compile(r"^multi_lobe\[(\d+)\]\.lobe\[(\d+)\]\.(\w+)$")
_MULTI_RE = re.compile(r"^multi_lobe\[(\d+)\]\.(\w+)$")
_MATERIAL_RE = re.compile(r"^material\[(\d+)\]\.(\w+)$")


def _domain_str(domain) -> str:
    if domain == "unit":
        return "[0, 1]"
    if domain == "positive":
        return "(0, inf)"
    if domain == "real":
        return "(-inf, inf)"
    return f"[{domain[0]}, {domain[1]}]"


def _follow(node, path):
    for k in path:
        node = node[k] if isinstance(k, int) else getattr(node, k)
    return node


@dataclass(frozen=True)
class Param:
    """One free parameter: where it lives in a Scene, its size and its domain."""

    name: str
    path: tuple  # ("material", "diffuse") / ("point", 0, "a1") / ("multi_lobe", 0, 1, "color") / ("fog", "density")
    size: int  # 3 for a per-channel RGB field, else 1
    domain: object  # "unit" | "positive" | "real" | (lo, hi)
    view: int | None = None  # a per-view parameter: the view it belongs to
    frame: tuple | None = None  # a direction's chart: the start direction d0 and two axes e1, e2 normal to it
    shape: tuple | None = None  # a texture map's texels (H, W, C)

    def get(self, scene: ds.Scene):
        if self.frame is not None:
            return tilt_of(self._node(scene), self.frame)
        if self.path == ("mesh", "colors"):
            return jnp.asarray(scene.mesh.colors).reshape(-1)
        if is_map(self):
            return jnp.asarray(_follow(scene, self.path).texels).reshape(-1)
        return self._leaf(scene)

    def _node(self, scene):
        p = self.path
        if p[0] in _KINDS:
            lights = getattr(scene, p[0])
            field = p[-1]
            if len(p) == 4:  # a lobe of a multi-lobe light
                return getattr(lights, field)[p[1], p[2]]
            if field in ("a0", "a1", "a2"):
                return lights.attenuation[p[1], int(field[1])]
            if field in _SIZE:
                return lights.size[p[1], _SIZE[field]]
            return getattr(lights, field)[p[1]]
        return _follow(scene, p)

    def _leaf(self, scene):
        x = jnp.asarray(self._node(scene))
        return x if self.size == 3 or x.ndim == 0 else jnp.mean(x)

    def set(self, scene: ds.Scene, value, view=None) -> ds.Scene:
        """``scene`` with this parameter at ``value`` (unchanged if it is another view's).

        ``view``: which view ``scene`` is: a Python int (another view's parameter is left out of
        the program), or a traced integer (views stacked and mapped over: a per-view parameter is
        selected where the index is its view)."""
        sel = None
        if self.view is not None:
            if view is None or isinstance(view, (int, np.integer)):
                if view != self.view:
                    return scene
            else:
                sel = jnp.asarray(view) == self.view
        where, new = self._update(scene, value)
        if sel is not None:
            new = jnp.where(sel, new, where(scene))
        return eqx.tree_at(where, scene, new)

    def _update(self, scene, value):
        """``(where, new)``: the scene leaf this parameter lives in, and that leaf at ``value``."""
        if self.frame is not None:
            value = direction_of(value, self.frame)
        if self.path == ("mesh", "colors"):
            return (lambda s: s.mesh.colors), jnp.asarray(value).reshape(-1, 3).astype(scene.mesh.colors.dtype)
        if is_map(self):
            p = self.path
            old = _follow(scene, p).texels
            return (lambda s: _follow(s, p).texels), jnp.asarray(value, old.dtype).reshape(old.shape)
        _, where, index = self.target()
        old = where(scene)
        if index == ():
            return where, jnp.broadcast_to(jnp.asarray(value, old.dtype), old.shape)
        return where, old.at[index].set(jnp.broadcast_to(value, old[index].shape).astype(old.dtype))

    def target(self):
        """``(key, where, index)``: the scene leaf a scalar or RGB parameter lives in (``key``
        names it, ``where`` gets it from a scene) and its place in that leaf (``()``: the whole
        leaf, its value broadcast)."""
        p = self.path
        if p[0] in _KINDS and len(p) == 4:  # a lobe of a multi-lobe light
            _, i, j, field = p
            return ("multi_lobe", field), (lambda s: getattr(s.multi_lobe, field)), (i, j)
        if p[0] in _KINDS:
            kind, i, field = p
            if field in ("a0", "a1", "a2"):
                return (kind, "attenuation"), (lambda s: getattr(s, kind).attenuation), (i, int(field[1]))
            if field in _SIZE:
                return (kind, "size"), (lambda s: getattr(s, kind).size), (i, _SIZE[field])
            return (kind, field), (lambda s: getattr(getattr(s, kind), field)), (i,)
        return p, (lambda s: _follow(s, p)), ()

    @property
    def placed(self) -> bool:
        """Whether the parameter's scalars go into their scene leaf as they are (no chart of a
        direction, no texels or vertex colours): :meth:`ParamSet.apply` writes all such
        parameters of one leaf at once."""
        return self.frame is None and not is_map(self) and self.path != ("mesh", "colors")

    # -- reparametrisation -----------------------------------------------------------------
    @property
    def bounds(self) -> tuple[float, float] | None:
        """``(lo, hi)`` of a bounded domain ([0, 1] or an interval); None for a positive or real one."""
        if self.domain in ("positive", "real"):
            return None
        return (0.0, 1.0) if self.domain == "unit" else self.domain

    @property
    def box(self) -> tuple[float, float]:
        """The domain as ``(lo, hi)``, infinite ends included (a positive one is ``(0, inf)``)."""
        if self.domain == "real":
            return (-np.inf, np.inf)
        return self.bounds or (0.0, np.inf)

    def to_u(self, theta):
        theta = jnp.asarray(theta)
        if self.domain == "real":
            return theta
        if self.bounds is None:
            return jnp.log(jnp.maximum(theta, 1e-30))
        lo, hi = self.bounds
        t = jnp.clip((theta - lo) / (hi - lo), 1e-6, 1 - 1e-6)
        return jnp.log(t) - jnp.log1p(-t)

    def from_u(self, u):
        if self.domain == "real":
            return u
        if self.bounds is None:
            # capped where θ² still fits the float type: measured, the float32 LM walked a
            # shininess whose specular term had left the image to u > 89 and handed θ = inf on
            # (beyond the cap θ is constant, a flat direction the solver leaves alone)
            u = jnp.asarray(u)
            return jnp.exp(jnp.minimum(u, 0.5 * np.log(np.finfo(u.dtype).max)))
        lo, hi = self.bounds
        return lo + (hi - lo) * jax.nn.sigmoid(u)

    def check(self, value, what="value"):
        v = np.asarray(value, np.float64)
        ok = np.isfinite(v).all()
        if self.domain == "unit":
            ok = ok and (v >= 0).all() and (v <= 1).all()
        elif self.domain == "positive":
            ok = ok and (v > 0).all()
        elif self.domain != "real":
            ok = (
                ok and (v >= self.domain[0]).all() and (v <= self.domain[1]).all()
            )  # a start on a bound is moved inside
        if not ok:
            raise ParamError(
                f"{self.name}: {what} {np.round(v, 6).tolist()} is outside its domain {_domain_str(self.domain)}"
            )

    def labels(self) -> list[str]:
        if self.path == ("mesh", "colors"):
            return [f"mesh.colors[{v}][{c}]" for v in range(self.size // 3) for c in "rgb"]
        if is_map(self):
            h, w, ch = self.shape
            rgb = "rgb" if ch == 3 else "v"
            # (joined from pieces: a 256² map's 196,608 labels in a third of the formatting's time)
            rows, cols = [f"{self.name}[{i}," for i in range(h)], [f"{j}][" for j in range(w)]
            chans = [f"{c}]" for c in rgb[:ch]]
            return [r + k + c for r in rows for k in cols for c in chans]
        if self.frame is not None:
            return [f"{self.name}[tilt_u]", f"{self.name}[tilt_v]"]
        axes = "xyz" if self.domain == "real" and self.path[-1] != "black_level" else "rgb"
        return [f"{self.name}[{axes[c]}]" for c in range(3)] if self.size == 3 else [self.name]


MAP_FIELDS = ("emission", "ambient", "diffuse", "specular", "shininess", "roughness", "opacity")
LINEAR_MAPS = ("emission", "ambient", "diffuse", "specular")  # the image is linear in their texels


def is_map(p: Param) -> bool:
    """Whether ``p`` is a texture map's texels (``material.<field>_map``)."""
    return p.shape is not None


def _parse_map(name, scene, shared):
    field = name.split(".")[1][: -len("_map")]
    if field not in MAP_FIELDS:
        raise ParamError(f"unknown parameter {name!r}: the maps are material.<{'|'.join(MAP_FIELDS)}>_map")
    tex = getattr(scene.material, field + "_map")
    if tex is None:
        raise ParamError(
            f"{name}: the material has no {field} map to fit (give Material({field}_map=Texture(...)) a start, "
            "e.g. a constant map of the resolution to fit)"
        )
    if shared:
        raise ParamError(f"{name} has no shared form")
    first = dict(scene.material.map_sharing).get(field)
    if first is not None:
        raise ParamError(
            f"{name}: the {field} map is the same Texture as material.{first}_map (one map for both, "
            f"docs/model.md §15): free material.{first}_map, which maps both"
        )
    shape = tuple(int(n) for n in tex.texels.shape)
    domain = "positive" if field == "shininess" else "unit"
    return Param(name, ("material", field + "_map"), int(np.prod(shape)), domain, shape=shape)


def _parse_mesh_colors(name, scene, shared):
    if scene.mesh.colors is None:
        raise ParamError(
            "mesh.colors: the mesh has no vertex colours to fit (load a mesh with colours, or give "
            "Mesh(colors=...) a start)"
        )
    if shared:
        raise ParamError("mesh.colors has no shared form")
    return Param(name, ("mesh", "colors"), 3 * int(scene.mesh.colors.shape[0]), "unit")


def _parse_camera(name, scene, shared):
    parts = name.split(".")
    if len(parts) != 2 or parts[1] not in _CAMERA:
        raise ParamError(f"unknown parameter {name!r}: a camera has {', '.join(_CAMERA)}")
    if parts[1] in ("rvec", "tvec") and not isinstance(scene.camera, ds.OpenCVCamera):
        raise ParamError(f'{name}: only an OpenCV camera (model = "opencv") has a pose vector')
    rgb = parts[1] in ("white_balance", "black_level") and not shared
    if parts[1] in ("rvec", "tvec") and shared:
        raise ParamError(f"{name}: a pose vector has no shared form")
    return Param(name, tuple(parts), 3 if rgb or parts[1] in ("rvec", "tvec") else 1, _CAMERA[parts[1]])


def _parse_lobe(name, scene, shared, m):
    i, j, field = int(m.group(1)), int(m.group(2)), m.group(3)
    lights = scene.multi_lobe
    if field not in _LOBE:
        raise ParamError(f"unknown parameter {name!r}: a lobe has the fields {sorted(_LOBE)}")
    if i >= lights.count:
        raise ParamError(f"unknown parameter {name!r}: the scene has {lights.count} multi-lobe light(s)")
    if j >= lights.lobes:
        raise ParamError(f"unknown parameter {name!r}: multi-lobe light {i} has {lights.lobes} lobe slot(s)")
    size = 3 if field in _RGB and not shared else 1
    return Param(name, ("multi_lobe", i, j, field), size, _LIGHT[field])


def _parse_multi(name, scene, shared, m):
    i, field = int(m.group(1)), m.group(2)
    if field not in ("a0", "a1", "a2", "position"):
        raise ParamError(
            f"unknown parameter {name!r}: a multi-lobe light has position, a0, a1, a2; its lobes have "
            f"multi_lobe[{i}].lobe[j].<{'|'.join(sorted(_LOBE))}>"
        )
    if i >= scene.multi_lobe.count:
        raise ParamError(f"unknown parameter {name!r}: the scene has {scene.multi_lobe.count} multi-lobe light(s)")
    return Param(name, ("multi_lobe", i, field), 3 if field == "position" else 1, _LIGHT[field])


def _parse_light(name, scene, shared, m):
    kind, i, field = m.group(1), int(m.group(2)), m.group(3)
    count = getattr(scene, kind).count
    direction = (kind, field) in (("directional", "direction"), ("spot", "axis"))
    if not direction and (
        field not in _LIGHT
        or (kind != "spot" and field in ("cutoff", "exponent", "edge"))
        or (kind == "directional" and (field[0] == "a" and field != "ambient" or field == "position"))
        or (kind != "area" and field in _SIZE)
        or (kind != "directional" and field in _NEAR)
    ):
        raise ParamError(f"unknown parameter {name!r}: a {kind} light has no field {field!r}")
    if i >= count:
        raise ParamError(f"unknown parameter {name!r}: the scene has {count} {kind} light(s)")
    if field == "specular" and getattr(getattr(scene, kind), "specular", None) is None:
        raise ParamError(
            f"{name}: the scene's {kind} lights have no separate specular colour (their colour sets "
            "both); give one with `specular = [r, g, b]` in the scene file"
        )
    if field in _NEAR and not scene.directional.near:
        raise ParamError(
            f"{name}: the scene's directional lights are at infinity; give them a distance to make them "
            "near lights (a scene file's `distance =`, a capture's light_distance / --light-distance)"
        )
    size = 3 if (field in _RGB and not shared) or field in ("position", "origin") else 1
    if field in ("position", "origin", "direction", "axis") and shared:
        raise ParamError(f"{name}: a {field} has no shared form")
    if direction:
        d0 = np.asarray(getattr(getattr(scene, kind), field)[i], np.float64)
        return Param(name, (kind, i, field), 2, "real", frame=direction_frame(d0))
    return Param(name, (kind, i, field), size, _LIGHT[field])


def _parse_material_i(name, scene, shared, m):
    i, field = int(m.group(1)), m.group(2)
    count = len(scene.all_materials())
    if field not in _MATERIAL:
        raise ParamError(f"unknown parameter {name!r}: a material has no field {field!r}")
    if i >= count:
        raise ParamError(f"unknown parameter {name!r}: the scene has {count} material(s)")
    path = ("material", field) if i == 0 else ("materials", i - 1, field)
    return Param(name, path, 3 if field in _RGB and not shared else 1, _MATERIAL[field])


def _parse_other(name, scene, shared):
    """Materials by name, fog, the ambient light; else the list of every known name."""
    parts = name.split(".")
    if parts[0] in ("material", "back_material") and parts[1:] == ["tangent"]:  # Ward's: a direction
        if parts[0] == "back_material" and scene.back_material is None:
            raise ParamError(f"unknown parameter {name!r}: the scene has no back material")
        if shared:
            raise ParamError(f"{name}: a direction has no shared form")
        d0 = np.asarray(getattr(scene, parts[0]).tangent, np.float64)
        return Param(name, tuple(parts), 2, "real", frame=direction_frame(d0))
    if parts[0] in ("material", "back_material") and len(parts) == 2 and parts[1] in _MATERIAL:
        if parts[0] == "back_material" and scene.back_material is None:
            raise ParamError(f"unknown parameter {name!r}: the scene has no back material")
        size = 3 if parts[1] in _RGB and not shared else 1
        return Param(name, tuple(parts), size, _MATERIAL[parts[1]])
    if parts[0] == "fog" and len(parts) == 2 and parts[1] in _FOG:
        size = 3 if parts[1] == "color" and not shared else 1
        return Param(name, tuple(parts), size, _FOG[parts[1]])
    if name == "ambient_light":
        return Param(name, ("ambient_light",), 1 if shared else 3, "positive")
    raise ParamError(
        f"unknown parameter {name!r}; known: material.<{'|'.join(_MATERIAL)}|tangent>, material[i].<...> (material id i), "
        "back_material.<...>, ambient_light, <directional|point|spot|area>[i].<color|specular|ambient|position|a0|a1|a2|cutoff|"
        "exponent|edge|width|height>, directional[i].direction, spot[i].axis, multi_lobe[i].<position|a0|a1|a2>, multi_lobe[i].lobe[j].<color|ambient|cutoff|exponent|edge>, "
        "fog.<color|start|end|density>, camera.<exposure|white_balance|black_level|rvec|tvec>, mesh.colors, material.<field>_map, view[i].<any of these>"
    )


_PATTERNS = (
    (_LOBE_RE, _parse_lobe),
    (_MULTI_RE, _parse_multi),
    (_LIGHT_RE, _parse_light),
    (_MATERIAL_RE, _parse_material_i),
)


def parse(name: str, scene: ds.Scene, shared: bool = False, n_views: int | None = None) -> Param:
    """The :class:`Param` called ``name`` in ``scene`` (raises :class:`ParamError`); ``n_views``
    (when known) bounds a ``view[i].`` prefix."""
    m = _VIEW_RE.match(name)
    if m:
        if m.group(1) in "*:":
            raise ParamError(
                f"{name}: view[{m.group(1)}] is expanded by the parameter set (it needs the number of views)"
            )
        i = int(m.group(1))
        if n_views is not None and i >= n_views:
            raise ParamError(f"unknown parameter {name!r}: the fit has {n_views} view(s)")
        return dataclasses.replace(parse(m.group(2), scene, shared), name=name, view=i)
    if name == "mesh.colors":
        return _parse_mesh_colors(name, scene, shared)
    if name.startswith("material.") and name.endswith("_map"):
        return _parse_map(name, scene, shared)
    if name.split(".")[0] == "camera":
        return _parse_camera(name, scene, shared)
    for pattern, fn in _PATTERNS:
        m = pattern.match(name)
        if m:
            return fn(name, scene, shared, m)
    return _parse_other(name, scene, shared)


def direction_frame(d0) -> tuple:
    """``(d0, e1, e2)``: the unit start direction and two unit axes normal to it (host tuples)."""
    d0 = np.asarray(d0, np.float64)
    n = np.linalg.norm(d0)
    if not np.isfinite(n) or n == 0:
        raise ParamError(f"a direction to fit must be a non-zero vector, got {d0.tolist()}")
    d0 = d0 / n
    helper = np.eye(3)[np.argmin(np.abs(d0))]  # the world axis least aligned with d0
    e1 = np.cross(d0, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d0, e1)
    return tuple(tuple(float(c) for c in v) for v in (d0, e1, e2))


def direction_of(tilt, frame):
    r"""The unit direction tilted from the start ``d0`` by ``tilt = (a, b)`` degrees about the chart's
    axes (the exponential map of the sphere at ``d0``): with :math:`w = a e_1 + b e_2` in radians
    and :math:`\varphi = |w|`, :math:`d = \cos\varphi\, d_0 + \frac{\sin\varphi}{\varphi} w`
    (double ``where``: smooth through 0). Singular only 180° from ``d0``."""
    d0, e1, e2 = (jnp.asarray(v) for v in frame)
    t = jnp.deg2rad(jnp.asarray(tilt))
    w = t[0] * e1.astype(t.dtype) + t[1] * e2.astype(t.dtype)
    p2 = t[0] * t[0] + t[1] * t[1]
    small = p2 < 1e-8
    phi = jnp.sqrt(jnp.where(small, 1.0, p2))
    sinc = jnp.where(small, 1.0 - p2 / 6.0, jnp.sin(phi) / phi)
    cos = jnp.where(small, 1.0 - p2 / 2.0 + p2 * p2 / 24.0, jnp.cos(phi))
    return cos * d0.astype(t.dtype) + sinc * w


def tilt_of(direction, frame):
    """The inverse of :func:`direction_of`: the tilt (degrees) of ``direction`` in the chart."""
    d0, e1, e2 = (jnp.asarray(v) for v in frame)
    d = jnp.asarray(direction)
    d = d / jnp.linalg.norm(d)
    s = jnp.stack([d @ e1.astype(d.dtype), d @ e2.astype(d.dtype)])
    sn2 = s @ s
    ok = sn2 > 0
    sn = jnp.sqrt(jnp.where(ok, sn2, 1.0))
    phi = jnp.arctan2(sn, d @ d0.astype(d.dtype))
    return jnp.rad2deg(jnp.where(ok, phi / sn, 1.0) * s)


def expand_views(names, n_views: int | None) -> list[str]:
    """``view[*].<name>`` → ``view[1].<name>``, …, ``view[n-1].<name>`` (view 0 is the reference);
    ``view[:].<name>`` → every view's, ``view[0].<name>`` too (a term with no gauge: an offset, a
    light's distance)."""
    out = []
    for n in names:
        m = _VIEW_RE.match(n)
        if m and m.group(1) == ":":
            if n_views is None:
                raise ParamError(f"{n}: view[:] needs the number of views")
            out += [f"view[{i}].{m.group(2)}" for i in range(n_views)]
        elif m and m.group(1) == "*":
            if n_views is None:
                raise ParamError(f"{n}: view[*] needs the number of views")
            if n_views < 2:
                raise ParamError(f"{n}: view[*] means every view but the reference view 0, and the fit has one view")
            out += [f"view[{i}].{m.group(2)}" for i in range(1, n_views)]
        else:
            out.append(n)
    return out


class ParamSet:
    """An ordered set of free parameters and the flat vectors ``θ`` (natural) and ``u`` (solver)."""

    def __init__(self, names, scene: ds.Scene, shared=(), n_views: int | None = None):
        names, shared = expand_views(names, n_views), set(expand_views(shared, n_views))
        unknown_shared = shared - set(names)
        if unknown_shared:
            raise ParamError(f"shared parameters {sorted(unknown_shared)} are not among the free parameters")
        if len(set(names)) != len(names):
            raise ParamError("a parameter is listed twice")
        self.params = [parse(n, scene, n in shared, n_views) for n in names]
        for p in self.params:
            if p.view is not None and p.name.split(".", 1)[1] in names:
                raise ParamError(f"{p.name}: {p.name.split('.', 1)[1]} is free for every view already")
        self.sizes = [p.size for p in self.params]
        self.offsets = np.cumsum([0] + self.sizes)

    @functools.cached_property
    def labels(self) -> list[str]:
        """One label per scalar (``name[i]``, a map's ``name[row,col][channel]``), built once: a
        256² colour map has 196,608, and a fit asks for them several times."""
        return [lab for p in self.params for lab in p.labels()]

    @property
    def moves_camera(self) -> bool:
        """Whether a camera pose is free (what each pixel sees then moves with it)."""
        return any(p.path[0] == "camera" and p.path[-1] in ("rvec", "tvec") for p in self.params)

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.params]

    def theta_of(self, scene, views=None):
        """The parameters' values in ``scene`` (a per-view one's in ``views[i]`` when given)."""
        get = lambda p: p.get(scene if p.view is None or views is None else views[p.view])  # noqa: E731
        return jnp.concatenate([jnp.atleast_1d(get(p)) for p in self.params])

    def split(self, vec):
        return [vec[a:b] if p.size > 1 else vec[a] for p, a, b in zip(self.params, self.offsets[:-1], self.offsets[1:])]

    def apply(self, scene, theta, view=None):
        """``scene`` with the parameters at ``theta``; ``view``: which view ``scene`` is (its
        own per-view parameters are set, other views' left alone; an int, or a traced index
        when the views are stacked).

        The parameters that go into a scene leaf as they are (:attr:`Param.placed`) are written
        leaf by leaf, each leaf one gather from ``theta`` (a fit's program then holds one small
        kernel per leaf, not a scatter per parameter under each of its tangents); the others
        (directions, maps, vertex colours, per-view ones of a traced view) one by one."""
        static_view = view is None or isinstance(view, (int, np.integer))
        leaves = {}
        rest = []
        for p, a in zip(self.params, self.offsets[:-1]):
            if not p.placed or (p.view is not None and not static_view):
                rest.append((p, a))
                continue
            if p.view is not None and p.view != view:
                continue
            key, where, index = p.target()
            if key not in leaves:
                leaves[key] = (where, np.full(np.shape(where(scene)), -1))
            leaves[key][1][index] = np.arange(a, a + p.size) if p.size > 1 else a
        for where, idx in leaves.values():
            old = where(scene)
            new = jnp.where(idx >= 0, jnp.asarray(theta)[np.maximum(idx, 0)].astype(old.dtype), old)
            scene = eqx.tree_at(where, scene, new)
        for p, a in rest:
            scene = p.set(scene, theta[a] if p.size == 1 else theta[a : a + p.size], view)
        return scene

    def _domains(self):
        """Per scalar: its kind (0 real, 1 positive, 2 an interval) and the interval's ends."""
        if getattr(self, "_domain_arrays", None) is None:
            per = [
                (0, 0.0, 1.0) if p.domain == "real" else (1, 0.0, 1.0) if p.bounds is None else (2, *p.bounds)
                for p in self.params
            ]
            # (repeated per parameter: a 256² map's lists per scalar took 0.04 s)
            kind, lo, hi = (np.repeat(np.asarray([d[i] for d in per]), self.sizes) for i in range(3))
            self._domain_arrays = (kind, lo.astype(np.float64), hi.astype(np.float64))
        return self._domain_arrays

    def theta_from_u(self, u):
        """θ from ``u``, every scalar by its domain (:meth:`Param.from_u`), as one elementwise
        expression over the vector."""
        kind, lo, hi = self._domains()
        u = jnp.asarray(u)
        # capped where θ² still fits the float type (Param.from_u)
        pos = jnp.exp(jnp.minimum(u, 0.5 * np.log(np.finfo(u.dtype).max)))
        box = lo.astype(u.dtype) + (hi - lo).astype(u.dtype) * jax.nn.sigmoid(u)
        return jnp.where(kind == 1, pos, jnp.where(kind == 2, box, u))

    def u_from_theta(self, theta):
        return jnp.concatenate([jnp.atleast_1d(p.to_u(v)) for p, v in zip(self.params, self.split(theta))])

    def u_from_theta_np(self, theta) -> np.ndarray:
        """:meth:`u_from_theta` in NumPy float64 on ``[..., n]`` arrays (host work, no dispatch)."""
        th = np.asarray(theta, np.float64)
        u = np.empty_like(th)
        for p, a, b in zip(self.params, self.offsets[:-1], self.offsets[1:]):
            v = th[..., a:b]
            if p.domain == "real":
                u[..., a:b] = v
            elif p.bounds is None:
                u[..., a:b] = np.log(np.maximum(v, 1e-30))
            else:
                lo, hi = p.bounds
                t = np.clip((v - lo) / (hi - lo), 1e-6, 1 - 1e-6)
                u[..., a:b] = np.log(t) - np.log1p(-t)
        return u

    def theta_from_u_np(self, u) -> np.ndarray:
        """:meth:`theta_from_u` in NumPy float64 (host work, no dispatch)."""
        kind, lo, hi = self._domains()
        u = np.asarray(u, np.float64)
        with np.errstate(over="ignore"):
            pos = np.exp(np.minimum(u, 0.5 * np.log(np.finfo(np.float64).max)))
            box = lo + (hi - lo) / (1.0 + np.exp(-u))
        return np.where(kind == 1, pos, np.where(kind == 2, box, u))

    def check(self, theta, what="start value"):
        for p, v in zip(self.params, self.split(np.asarray(theta))):
            p.check(v, what)
