"""Materials as authored: Wavefront MTL files and the maps they name (docs/model.md §15).

``Ka Kd Ks Ke`` are the ambient, diffuse, specular and emitted colours, ``Ns`` the Phong
exponent and ``d`` the opacity; ``map_Ka map_Kd map_Ks map_Ke map_Ns map_d`` name image maps
that multiply them (the MTL convention, and OpenGL's ``GL_MODULATE``). ``Tr`` is not read:
exporters write it with both meanings (MeshLab writes ``Tr 1`` on opaque materials), and ``d``
says the same thing unambiguously. A map's ``-clamp on`` is ``wrap = "clamp"``; options that
would change the coordinates (``-o``, ``-s``, ``-t``) or the values (``-mm``, ``-bm``,
``-imfchan``) are refused by name rather than ignored.

:func:`save_material` writes a scene's materials (or one material) back in the same keys, its
maps as 16-bit PNGs beside the file; :func:`load_material` reads them again.
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
    "map_Pr": "roughness",
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
            elif key == "Pr":  # the PBR extension's roughness: Cook-Torrance's alpha (docs/model.md §2)
                cur["roughness"] = _numbers(words, 1, where)[0]
                if not 0.0 < cur["roughness"] <= 1.0:
                    raise MeshError(f"{where}: Pr (the roughness) must be in (0, 1], got {cur['roughness']:g}")
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
    linear values; ``Pr`` (the PBR extension's roughness) as ``roughness``. Raises
    :class:`diffshade.MeshError` naming the file and line: a missing or
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


def save_material(path, material, opts=None, header: str = "") -> Path:
    r"""Write ``material`` (a :class:`Material`, or a :class:`Scene`: its material, its other
    materials as ``material_1``, ... and its back material) as a Wavefront MTL file at ``path``,
    in the keys :func:`load_material` reads: ``Ka Kd Ks Ke`` (linear colours), ``Ns`` (the
    exponent of ``opts``' specular model, said in the file's comment: Phong's by default; for the
    microfacet and Ward models the Phong exponent nearest the lobe), ``Pr`` (those models'
    roughness :math:`\alpha`, the PBR extension's key; Oren–Nayar's :math:`\sigma` and Ward's
    :math:`\alpha_y` and tangent have no key: a comment line says them), ``Ni``,
    ``d`` (the opacity, where ``opts`` has transparency), ``Tf`` (the transmission, where ``opts``
    has it), ``illum``; what MTL has no key for (absorption, Kay's opacity) as a comment line above
    its material. Maps go beside the file as 16-bit PNGs (``<stem>_<material>_<field>.png``:
    colour maps sRGB-encoded, the shininess and opacity maps linear grey, each declaring its
    encoding) named by ``map_*`` lines: a shininess map beyond 1 is scaled into the file and its
    scale moved into ``Ns`` (MTL multiplies the two); a map with ``wrap = "clamp"`` gets
    ``-clamp on``. ``header``: comment lines at the top. Written to a temporary file and moved
    into place (no half-written file). Returns the path."""
    from ._options import RenderOptions
    from ._scene import Scene

    path = Path(path)
    opts = RenderOptions() if opts is None else opts
    if isinstance(material, Scene):
        mats = [("material", material.material)] + [(f"material_{i + 1}", x) for i, x in enumerate(material.materials)]
        if material.back_material is not None:
            mats.append(("back_material", material.back_material))
    elif isinstance(material, Material):
        mats = [("material", material)]
    else:
        raise TypeError(f"save_material: a Material or a Scene, not {type(material).__name__}")
    spec = opts.lighting.specular
    transparency, absorption = opts.layered, opts.layered and opts.transparency.absorption
    lines = [f"# {ln}" for ln in header.splitlines()]
    rough = spec in ("beckmann", "ggx", "ward")
    if rough:
        what = {"beckmann": "Cook-Torrance Beckmann", "ggx": "Cook-Torrance GGX", "ward": "Ward (alpha_x)"}[spec]
        lines.append(
            f"# Pr is the {what} roughness alpha; Ns the Phong exponent nearest its lobe, (2/alpha^2 - 2)/4 "
            "(Walter et al. 2007's Beckmann-Blinn-Phong correspondence m' = 2/alpha^2 - 2, and m = m'/4)"
        )
    lines.append(
        f"# {'' if rough else 'Ns is the ' + ('Blinn-Phong' if spec == 'blinn' else 'Phong') + ' exponent; '}"
        "colours are linear; Ke = emission"
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    for name, m in mats:
        extra = []
        if absorption:
            extra.append(f"# absorption mu {_rgb(m.absorption)} (per unit length)")
        if transparency and m.kay:
            extra.append(
                f"# Kay opacity t_min {float(m.kay_min):.6g} t_max {float(m.kay_max):.6g} p {float(m.kay_power):.6g}"
            )
        if opts.lighting.diffuse_model == "oren_nayar":
            extra.append(f"# Oren-Nayar sigma {float(m.diffuse_roughness):.6g} (radians; MTL has no key for it)")
        if spec == "ward":
            extra.append(
                f"# Ward alpha_y {float(m.roughness_y):.6g}, tangent {_rgb(m.tangent)} (MTL has no key for them)"
            )
        opacity = float(m.opacity) if transparency and not m.kay else 1.0
        a = float(m.roughness)
        ns = (2.0 / (a * a) - 2.0) / 4.0 if rough else float(m.shininess)
        lines += [
            "",
            *extra,
            f"newmtl {name}",
            f"Ka {_rgb(m.ambient)}",
            f"Kd {_rgb(m.diffuse)}",
            f"Ks {_rgb(m.specular)}",
            f"Ns {ns:.6g}",
            *([f"Pr {a:.6g}"] if rough else []),
            f"Ke {_rgb(m.emission)}",
            f"Ni {float(m.ior):.6g}",
            f"d {opacity:.6g}",
        ]
        if opts.lighting.transmission:
            lines.append(f"Tf {_rgb(m.transmission)}")
        lines.append(f"illum {1 if spec == 'none' else (4 if transparency else 2)}")
        lines += _save_maps(m, path.parent, f"{path.stem}_{name}", lines)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text("\n".join(lines) + "\n")
    tmp.replace(path)
    return path


def _rgb(x) -> str:
    return " ".join(f"{float(c):.6g}" for c in np.broadcast_to(np.asarray(x), (3,)))


def _save_maps(m, folder: Path, stem: str, lines: list) -> list[str]:
    """A material's maps as 16-bit PNGs and the ``map_*`` lines that name them (``lines``, the
    material's lines so far, gets a shininess map's scale in ``Ns``)."""
    from .images import write_image

    out = []
    for key, field in _MAPS.items():
        field = field.removesuffix("_map")
        tex = getattr(m, field + "_map")
        if tex is None:
            continue
        texels = np.asarray(tex.texels, np.float64)
        if field == "shininess" and texels.max() > 1:
            scale = float(texels.max())
            texels = texels / scale
            k = next(i for i in range(len(lines) - 1, -1, -1) if lines[i].startswith("Ns "))
            lines[k] = f"Ns {float(m.shininess) * scale:.6g}"
        file = folder / f"{stem}_{field}.png"
        grey = field in SCALAR_MAPPED
        write_image(file, texels[..., 0] if texels.shape[-1] == 1 else texels, "linear" if grey else "srgb", bits=16)
        out.append(f"{key} {'-clamp on ' if tex.wrap == 'clamp' else ''}{file.name}")
    return out
