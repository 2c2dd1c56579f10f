"""The domain of every number in a scene: one table, one check, one kind of message.

A :class:`Domain` says what a value may be (a finite real or a whole number, its bounds, whether
None stands for "not given"); :func:`check` raises the boundary's error with a message that names
the value as the user wrote it (``material.shininess``, ``point[1].attenuation``, ``--noise``,
``VarPro.max_steps``) and the allowed range. :data:`SCENE` is the table of a :class:`Scene`'s
fields; :func:`check_scene` holds a scene to it and to the relations between fields (a linear
fog's start before its end, the near plane before the far one, a spot's edge inside its cutoff).
The scene-file loader, ``Scene(...)``, :func:`diffshade.render` (outside a trace) and
:func:`fitting.fit` (the start and every view) call it; :mod:`fitting._domains` is the table of
the fit's and the command line's options.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np


class SceneError(ValueError):
    """A scene file, dictionary or object that is malformed; the message names the field."""


@dataclass(frozen=True)
class Domain:
    """Where a value may lie: ``kind`` ``"real"`` (finite) or ``"int"`` (a whole number), between
    ``lo`` and ``hi`` (``None``: unbounded; ``*_open``: the bound itself excluded); ``optional``:
    None is allowed (not given)."""

    kind: str = "real"
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    optional: bool = False

    def describe(self) -> str:
        """The domain in words: "a finite number > 0", "a whole number >= 1", "a finite number in [0, 1]"."""
        what = "a whole number" if self.kind == "int" else "a finite number"
        lo, hi = self.lo, self.hi
        if lo is not None and hi is not None:
            what += f" in {'(' if self.lo_open else '['}{lo:g}, {hi:g}{')' if self.hi_open else ']'}"
        elif lo is not None:
            what += f" {'>' if self.lo_open else '>='} {lo:g}"
        elif hi is not None:
            what += f" {'<' if self.hi_open else '<='} {hi:g}"
        return what + (" (or None: not given)" if self.optional else "")

    def admits(self, value) -> bool:
        """Whether a scalar ``value`` lies in the domain (a bool is no number)."""
        if value is None:
            return self.optional
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
            return False
        x = float(value)
        if not math.isfinite(x) or (self.kind == "int" and not x.is_integer()):
            return False
        if self.lo is not None and (x < self.lo or (self.lo_open and x == self.lo)):
            return False
        return not (self.hi is not None and (x > self.hi or (self.hi_open and x == self.hi)))

    def admits_all(self, values: np.ndarray) -> np.ndarray:
        """Per entry of a float array: finite and within the bounds."""
        ok = np.isfinite(values)
        if self.lo is not None:
            ok &= (values > self.lo) if self.lo_open else (values >= self.lo)
        if self.hi is not None:
            ok &= (values < self.hi) if self.hi_open else (values <= self.hi)
        return ok


def check(name: str, value, domain: Domain, error: type[Exception] = ValueError):
    """``value`` if ``domain`` admits it, else ``error`` naming ``name``, the domain and the value."""
    if not domain.admits(value):
        raise error(f"{name} must be {domain.describe()}, got {value!r}")
    return value


REAL = Domain()
NONNEG = Domain(lo=0.0)
POSITIVE = Domain(lo=0.0, lo_open=True)
UNIT = Domain(lo=0.0, hi=1.0)
ANGLE = Domain(lo=0.0, hi=90.0)  # degrees: a spot's cutoff and edge

_MATERIAL = {
    "emission": NONNEG,
    "ambient": UNIT,
    "diffuse": UNIT,
    "specular": UNIT,
    "shininess": NONNEG,  # 0: OpenGL's default (the highlight is the whole lit side)
    "roughness": Domain(lo=0.0, lo_open=True, hi=1.0),
    "roughness_y": Domain(lo=0.0, lo_open=True, hi=1.0),
    "diffuse_roughness": NONNEG,
    "tangent": REAL,
    "ior": POSITIVE,
    "opacity": UNIT,
    "kay_min": UNIT,
    "kay_max": UNIT,
    "kay_power": POSITIVE,
    "transmission": UNIT,
    "absorption": NONNEG,
    "mirror": UNIT,
    "refraction": UNIT,
}
_LIGHT = {"color": NONNEG, "ambient": NONNEG, "specular": NONNEG, "attenuation": NONNEG, "position": REAL}
_SPOT = {"axis": REAL, "cutoff": ANGLE, "exponent": NONNEG, "edge": ANGLE}  # cutoff 0: a closed cone, dark

#: Every number of a :class:`Scene`, by group and field (``light`` groups by kind).
SCENE: dict[str, dict[str, Domain]] = {
    "material": _MATERIAL,
    "directional": {**_LIGHT, "direction": REAL, "distance": POSITIVE, "origin": REAL, "falloff": NONNEG},
    "point": _LIGHT,
    "spot": {**_LIGHT, **_SPOT},
    "area": {**_LIGHT, "normal": REAL, "up": REAL, "size": NONNEG},
    "multi_lobe": {**_LIGHT, **_SPOT},
    "fog": {"color": NONNEG, "start": NONNEG, "end": NONNEG, "density": NONNEG},
    "camera": {
        "eye": REAL,
        "target": REAL,
        "up": REAL,
        "fov_y": Domain(lo=0.0, hi=180.0, lo_open=True, hi_open=True),
        "pixel_size": POSITIVE,
        "near": POSITIVE,
        "far": POSITIVE,
        "exposure": POSITIVE,
        "white_balance": POSITIVE,
        "black_level": REAL,
        "fx": POSITIVE,
        "fy": POSITIVE,
        "cx": REAL,
        "cy": REAL,
        "rvec": REAL,
        "tvec": REAL,
        "distortion": REAL,
    },
    "scene": {"ambient_light": NONNEG, "background": NONNEG, "shadow_bias": NONNEG, "shadow_slope_bias": NONNEG},
}
_NONZERO = {"direction", "axis", "normal", "up"}  # directions: not the zero vector


def check_scene(scene) -> None:
    """Hold every number of ``scene`` (a :class:`diffshade.Scene` with concrete values) to
    :data:`SCENE` and to the relations between fields; a :class:`SceneError` names the first field
    outside its domain (``material[1].diffuse``, ``spot[0].edge``, ``fog.end``, ...)."""
    _group(scene, "scene", "", None)
    _group(scene.camera, "camera", "camera.", None)
    c = scene.camera
    if float(c.far) <= float(c.near):
        raise SceneError(f"camera.far must be > camera.near ({float(c.near):g}), got {float(c.far):g}")
    if not np.isfinite(np.asarray(scene.mesh.vertices)).all():
        raise SceneError("mesh.vertices must be finite (a NaN or inf vertex)")
    for i, m in enumerate(scene.all_materials()):
        _group(m, "material", "material." if i == 0 else f"material[{i}].", None)
    if scene.back_material is not None:
        _group(scene.back_material, "material", "back_material.", None)
    for kind in ("directional", "point", "spot", "area", "multi_lobe"):
        lights = getattr(scene, kind)
        _group(lights, kind, kind, lights.count)
        if kind in ("spot", "multi_lobe"):
            edge, cutoff = np.asarray(lights.edge, np.float64), np.asarray(lights.cutoff, np.float64)
            if (edge > cutoff).any():
                i = int(np.argwhere(edge > cutoff)[0][0])
                raise SceneError(f"{kind}[{i}].edge must be <= its cutoff ({cutoff.flat[i]:g}), got {edge.flat[i]:g}")
    f = scene.fog
    _group(f, "fog", "fog.", None)
    if float(f.end) < float(f.start):
        raise SceneError(f"fog.end must be >= fog.start ({float(f.start):g}), got {float(f.end):g}")


def _group(obj, group: str, prefix: str, rows: int | None) -> None:
    """Every field of ``obj`` in ``SCENE[group]``; ``rows``: a light kind's row count (named per row)."""
    for name, dom in SCENE[group].items():
        x = getattr(obj, name, None)
        if x is None:
            continue
        a = np.asarray(x, np.float64)
        bad = ~dom.admits_all(a)
        if name in _NONZERO and a.size:
            bad |= np.all(a == 0, axis=-1, keepdims=True)
        if bad.any():
            where = np.argwhere(bad)[0]
            label = f"{prefix}[{int(where[0])}].{name}" if rows is not None else f"{prefix}{name}"
            what = "not the zero vector" if name in _NONZERO and np.isfinite(a).all() else dom.describe()
            shown = a[int(where[0])] if rows is not None else a
            raise SceneError(f"{label} must be {what}, got {np.round(shown, 6).tolist()}")
