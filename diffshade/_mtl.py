"""Materials as authored: Wavefront MTL files and the maps they name (docs/model.md §15).

``Ka Kd Ks Ke`` are the ambient, diffuse, specular and emitted colours, ``Ns`` the Phong
exponent and ``d`` the opacity; ``map_Ka map_Kd map_Ks map_Ke map_Ns map_d`` name image maps
that multiply them (the MTL convention, and OpenGL's ``GL_MODULATE``). ``Tr`` is not read:
exporters write it with both meanings (MeshLab writes ``Tr 1`` on opaque materials), and ``d``
says the same thing unambiguously. A map's ``-clamp on`` is ``wrap = "clamp"``; options that
would change the coordinates (``-o``, ``-s``, ``-t``) or the values (``-mm``, ``-bm``,
``-imfchan``) are refused by name rather than ignored.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._mesh import MeshError
from ._scene import SCALAR_MAPPED, Material
from ._texture import Texture, texture_from_image

_COLOURS = {"Ka": "ambient", "Kd": "diffuse", "Ks": "specular", "Ke": "emission"}
_MAPS = {
    "map_Ka": "ambient",
    "map_Kd": "diffuse",
    "map_Ks": "specular",
    "map_Ke": "emission",
    "map_Ns": "shininess",
    "map_d": "opacity",
}
_IGNORED = {"illum", "Ni", "Tr", "Tf", "sharpness", "bump", "map_bump", "disp", "decal", "refl", "map_refl", "norm"}
_REFUSED_OPTIONS = {"-o", "-s", "-t", "-mm", "-bm", "-imfchan", "-texres", "-boost", "-cc"}
_FLAG_OPTIONS = {"-blendu", "-blendv", "-clamp"}


def _numbers(words, n, where):
    try:
        vals = [float(w) for w in words]
    except ValueError:
        raise MeshError(f"{where}: expected numbers, got {' '.join(words)!r}") from None
    if len(vals) == 1 and n == 3:
        vals = vals * 3
    if len(vals) != n or not np.isfinite(vals).all():
        raise MeshError(f"{where}: expected {n} finite number(s), got {' '.join(words)!r}")
    return vals


def _map_args(words, where):
    """``(file name, wrap)`` of a ``map_*`` line's arguments (the name may contain spaces)."""
    wrap = "repeat"
    i = 0
    while i < len(words) and words[i].startswith("-") and len(words[i]) > 1:
        opt = words[i]
        if opt in _REFUSED_OPTIONS:
            raise MeshError(f"{where}: the map option {opt} is not supported (it changes the coordinates or values)")
        if opt not in _FLAG_OPTIONS or i + 1 >= len(words):
            raise MeshError(f"{where}: unknown map option {opt!r}")
        if opt == "-clamp":
            wrap = "clamp" if words[i + 1].lower() == "on" else "repeat"
        i += 2
    name = " ".join(words[i:])
    if not name:
        raise MeshError(f"{where}: the map names no image file")
    return name, wrap


def _parse_mtl(path: Path) -> dict:
    """``{material name: {field: value or (image path, wrap, line)}}`` in file order."""
    mats: dict = {}
    cur = None
    with open(path, errors="replace") as fh:
        for lineno, raw in enumerate(fh, 1):
            line = raw.split("#", 1)[0].strip()
            if not line:
                continue
            key, *words = line.split()
            where = f"{path}: line {lineno}"
            if key == "newmtl":
                cur = mats.setdefault(" ".join(words), {})
                continue
            if cur is None:
                raise MeshError(f"{where}: {key!r} before any newmtl")
            if key in _COLOURS:
                cur[_COLOURS[key]] = _numbers(words, 3, where)
            elif key == "Ns":
                cur["shininess"] = _numbers(words, 1, where)[0]
            elif key == "d":
                cur["opacity"] = _numbers(words[-1:], 1, where)[0]
            elif key in _MAPS:
                name, wrap = _map_args(raw.split("#", 1)[0].split()[1:], where)
                cur[_MAPS[key] + "_map"] = (path.parent / name, wrap, where)
            elif key not in _IGNORED:
                raise MeshError(f"{where}: unknown MTL statement {key!r}")
    return mats


def _obj_materials(path: Path) -> tuple[list[Path], list[str]]:
    libs, used = [], []
    with open(path, errors="replace") as fh:
        for line in fh:
            if line.startswith("mtllib"):
                libs.append(path.parent / line.split(None, 1)[1].strip())
            elif line.startswith("usemtl"):
                name = line.split(None, 1)[1].strip() if len(line.split()) > 1 else ""
                if name not in used:
                    used.append(name)
    return libs, used


def map_texture(field: str, image, where: str, encoding=None, wrap: str = "repeat", filter: str = "trilinear"):
    """The :class:`Texture` of ``field``'s map from the image file ``image``: a colour map decoded
    by ``encoding`` (default: its file's declared one), a shininess or opacity map as linear grey.
    Raises :class:`MeshError` starting with ``where`` and naming the file."""
    if not Path(image).is_file():
        raise MeshError(f"{where}: the {field} map's image {image} was not found")
    try:
        enc = None if field in SCALAR_MAPPED else encoding
        tex = texture_from_image(image, encoding=enc, wrap=wrap, filter=filter)
    except Exception as exc:
        raise MeshError(f"{where}: the {field} map's image {image} could not be read ({exc})") from exc
    if field in SCALAR_MAPPED and tex.channels == 3:
        t = np.asarray(tex.texels)
        if not np.allclose(t[..., 0:1], t):
            raise MeshError(f"{where}: the {field} map {image} must be grey (one channel), got colour")
        tex = Texture(t[..., :1], wrap=wrap, filter=filter)
    return tex


def load_material(path: str | Path, name: str | None = None, encoding: str | None = None) -> Material:
    """The :class:`diffshade.Material` ``name`` of an MTL file, or of the MTL an OBJ names
    (``mtllib``); by default the one material the OBJ uses (or the MTL's first). Maps are read
    through :func:`diffshade.texture_from_image`, colour maps decoded by their declared encoding
    (sRGB where a file declares none; ``encoding`` overrides it), shininess and opacity maps as
    linear values. Raises :class:`diffshade.MeshError` naming the file and line: a missing or
    unreadable MTL or image, an unknown statement or option, a grey map in colour."""
    path = Path(path)
    if not path.is_file():
        raise MeshError(f"{path}: material file not found")
    if path.suffix.lower() == ".obj":
        libs, used = _obj_materials(path)
        if not libs:
            raise MeshError(f"{path}: the OBJ names no material library (mtllib)")
        mats: dict = {}
        for lib in libs:
            if not lib.is_file():
                raise MeshError(f"{path}: its material library {lib} was not found")
            mats.update(_parse_mtl(lib))
        if name is None:
            if len(used) > 1:
                raise MeshError(f"{path}: the OBJ uses {len(used)} materials ({used}): name one")
            name = used[0] if used else next(iter(mats), None)
    else:
        mats = _parse_mtl(path)
        name = next(iter(mats), None) if name is None else name
    if name not in mats:
        raise MeshError(f"{path}: no material {name!r} (the file has {list(mats)})")
    fields = {}
    for f, val in mats[name].items():
        if f.endswith("_map"):
            image, wrap, where = val
            val = map_texture(f[: -len("_map")], image, where, encoding, wrap=wrap)
        fields[f] = val
    try:
        return Material(**fields)
    except ValueError as exc:
        raise MeshError(f"{path}: material {name!r}: {exc}") from exc
