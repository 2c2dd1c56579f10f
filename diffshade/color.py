r"""Colour encodings of images on disk: linear, sRGB and a pure gamma (docs/model.md §8).

The renderer works in **linear** values, proportional to the light. Image files usually hold
*encoded* code values ``v`` in [0, 1]; the encoding maps them to linear values ``L``:

- ``"linear"``: :math:`L = v`;
- ``"srgb"`` (IEC 61966-2-1): :math:`L = v / 12.92` for :math:`v \le 0.04045`, else
  :math:`L = ((v + 0.055) / 1.055)^{2.4}`; encoding is the inverse, :math:`v = 12.92 L` for
  :math:`L \le 0.0031308`, else :math:`v = 1.055 L^{1/2.4} - 0.055`;
- ``"gamma:G"``: :math:`L = v^G` (``G`` = 2.2 for a classic display gamma).

Both ends are fixed points (0 → 0, 1 → 1) and every map is increasing, so a pixel clipped at the
top or bottom code is clipped in either domain. In a PNG the encoding is declared by its ``sRGB``
chunk, an ``iCCP`` profile, or a ``gAMA`` chunk (the file gamma ``1/G``): :func:`png_encoding`
reads them, :func:`png_info` writes them. Files are read and written by :mod:`diffshade.images`.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

ENCODINGS = ("linear", "srgb", "gamma:G")
_A, _K_DEC, _K_ENC, _S, _P = 0.055, 0.04045, 0.0031308, 12.92, 2.4


class EncodingError(ValueError):
    """An unknown colour encoding, or a file whose declared encoding cannot be decoded."""


def parse_encoding(name: str) -> tuple[str, float]:
    """``("linear", 1)``, ``("srgb", 2.4)`` or ``("gamma", G)`` from ``"linear"``, ``"srgb"`` or
    ``"gamma:G"`` (``G`` > 0)."""
    if not isinstance(name, str):
        raise EncodingError(f"colour encoding must be a string ({', '.join(ENCODINGS)}), got {name!r}")
    n = name.strip().lower()
    if n in ("linear", "srgb"):
        return n, (1.0 if n == "linear" else _P)
    if n.startswith("gamma:"):
        try:
            g = float(n[6:])
        except ValueError:
            g = float("nan")
        if not (np.isfinite(g) and 0.05 <= g <= 20):
            raise EncodingError(f"colour encoding {name!r}: the gamma must be a number in [0.05, 20], e.g. 'gamma:2.2'")
        return ("linear", 1.0) if abs(g - 1.0) < 1e-9 else ("gamma", g)
    raise EncodingError(f"unknown colour encoding {name!r}; one of 'linear', 'srgb', 'gamma:G' (e.g. 'gamma:2.2')")


def _xp(a):
    return np if isinstance(a, (np.ndarray, float, int, np.floating)) else jnp


def _above(x, knee, f, below):
    """``f(x)`` where ``x > knee``, else ``below(x)``; double where: ``f`` (a power) never sees
    the values off its branch, so neither values nor derivatives there are NaN."""
    xp = _xp(x)
    hi = x > knee
    return xp.where(hi, f(xp.where(hi, x, 1.0)), below(x))


def decode(v, encoding: str = "srgb"):
    """Linear values from encoded code values ``v`` (NumPy or JAX; differentiable, finite at 0)."""
    kind, g = parse_encoding(encoding)
    if kind == "linear":
        return v
    if kind == "srgb":
        return _above(v, _K_DEC, lambda x: ((x + _A) / (1 + _A)) ** _P, lambda x: x / _S)
    return _above(v, 0.0, lambda x: x**g, lambda x: 0.0 * x)


def encode(L, encoding: str = "srgb"):
    """Encoded code values from linear values ``L`` (the inverse of :func:`decode`; values
    outside [0, 1] are encoded as they are, clipping is the caller's)."""
    kind, g = parse_encoding(encoding)
    if kind == "linear":
        return L
    if kind == "srgb":
        return _above(L, _K_ENC, lambda x: (1 + _A) * x ** (1 / _P) - _A, lambda x: x * _S)
    return _above(L, 0.0, lambda x: x ** (1 / g), lambda x: 0.0 * x)


def decode_slope(v, encoding: str = "srgb", floor: float = 0.5 / 255):
    """``dL/dv`` at code value ``v`` (at least ``floor`` for a pure gamma, whose slope is 0 at 0):
    a residual in linear units divided by it is, to first order, the residual in code values."""
    kind, g = parse_encoding(encoding)
    xp = _xp(v)
    if kind == "linear":
        return xp.ones_like(v)
    if kind == "srgb":
        return _above(
            v, _K_DEC, lambda x: _P / (1 + _A) * ((x + _A) / (1 + _A)) ** (_P - 1), lambda x: 0.0 * x + 1.0 / _S
        )
    vv = xp.maximum(v, floor)
    return g * vv ** (g - 1)


# -- PNG chunks -------------------------------------------------------------------------------------


def png_encoding(path) -> tuple[str | None, str]:
    """``(encoding, why)`` from a PNG's chunks: ``sRGB`` → ``"srgb"``; an ``iCCP`` profile whose
    description names sRGB → ``"srgb"`` (any other profile is an :class:`EncodingError`: this
    package does not convert between colour spaces); ``gAMA`` → ``"linear"`` or ``"gamma:G"``;
    none of them (or not a PNG) → ``(None, "...")``."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            fmt, info = im.format, dict(im.info)
    except Exception as exc:  # noqa: BLE001 - PIL raises many types; name the file
        raise EncodingError(f"{path}: cannot read the image header: {exc}") from exc
    if fmt != "PNG":
        return None, f"a {fmt} file declares no encoding this package reads"
    if "srgb" in info:
        return "srgb", "its sRGB chunk"
    if info.get("icc_profile"):
        desc = icc_description(info["icc_profile"])
        if "srgb" in desc.lower().replace(" ", ""):
            return "srgb", f"its ICC profile ({desc})"
        raise EncodingError(
            f"{path}: its ICC profile is {desc!r}, not sRGB; convert the image to sRGB or "
            "declare the encoding (--encoding srgb | linear | gamma:G) to read it as that"
        )
    if "gamma" in info:
        fg = float(info["gamma"])
        if not fg > 0:
            raise EncodingError(f"{path}: its gAMA chunk says {fg}, not a positive gamma")
        g = 1.0 / fg
        return (("linear" if abs(g - 1) < 1e-3 else f"gamma:{g:.4g}"), f"its gAMA chunk ({fg:.5g})")
    return None, "no sRGB, iCCP or gAMA chunk"


def icc_description(icc: bytes) -> str:
    """An ICC profile's description (``"sRGB IEC61966-2.1"``, ``"sRGB built-in"``, ...)."""
    try:
        import io

        from PIL import ImageCms

        return ImageCms.getProfileDescription(ImageCms.ImageCmsProfile(io.BytesIO(icc))).strip()
    except Exception:  # noqa: BLE001 - an unreadable profile
        return "an unreadable ICC profile"


def png_info(encoding: str):
    """A ``PIL.PngImagePlugin.PngInfo`` declaring ``encoding``: ``sRGB`` (with the ``gAMA`` of
    0.45455 the PNG specification asks beside it), or ``gAMA`` of ``1/G`` (1.0 for linear)."""
    import struct

    from PIL.PngImagePlugin import PngInfo

    kind, g = parse_encoding(encoding)
    info = PngInfo()
    if kind == "srgb":
        info.add(b"sRGB", b"\x00")  # rendering intent: perceptual
        info.add(b"gAMA", struct.pack(">I", 45455))
    else:
        info.add(b"gAMA", struct.pack(">I", int(round(100000 / g))))
    return info


def quantise(image, encoding: str = "linear", bits: int = 8) -> np.ndarray:
    """Linear ``image`` clipped to [0, 1], encoded, and rounded to ``bits``-bit codes (8 or 16)."""
    if bits not in (8, 16):
        raise EncodingError(f"bits must be 8 or 16, got {bits}")
    top = 255 if bits == 8 else 65535
    v = encode(np.clip(np.asarray(image, np.float64), 0.0, 1.0), encoding)
    return np.round(np.clip(v, 0.0, 1.0) * top).astype(np.uint8 if bits == 8 else np.uint16)


def srgb_profile() -> bytes:
    """An sRGB ICC profile (LittleCMS's, through Pillow), for files that declare sRGB by one."""
    from PIL import ImageCms

    return ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
