"""Images on disk, read and written through libraries: PNG (8 and 16 bits) by libpng
(``imagecodecs``), TIFF (8 and 16 bits, float; any compression) by ``tifffile``, OpenEXR (half
and float) by the OpenEXR project's own bindings, NumPy ``.npy`` arrays, and JPEG, WebP and BMP
by ``imagecodecs``.

:func:`read_image` returns the stored values unchanged (:class:`Image`: the codes, their bit
depth, the colour encoding the file declares and why); :meth:`Image.linear` decodes them
(:mod:`diffshade.color`). The encoding comes from the file where it says: a PNG's ``sRGB``,
``iCCP`` or ``gAMA`` chunk, a TIFF's ICC profile; OpenEXR and float arrays hold linear values by
definition. :func:`write_image` writes linear values encoded as asked, the file declaring it.
Why these libraries (measured): docs/design.md, "Images through libraries".
"""

from __future__ import annotations

import io
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import color

WRITABLE = (".png", ".tif", ".tiff", ".exr", ".npy")


class ImageError(ValueError):
    """An image file that cannot be read or written; the message names the file and the problem."""


@dataclass(frozen=True)
class Image:
    """An image as stored: ``codes`` ``[H, W]`` or ``[H, W, C]`` (``uint8``, ``uint16``, or
    floats), the colour ``encoding`` the file declares (``"srgb"``, ``"linear"``, ``"gamma:G"``;
    None where it declares none) and ``why`` (where that came from)."""

    codes: np.ndarray
    encoding: str | None
    why: str
    path: Path

    @property
    def bits(self) -> int | None:
        """8 or 16 for integer codes; None for floats."""
        return {np.dtype(np.uint8): 8, np.dtype(np.uint16): 16}.get(self.codes.dtype)

    @property
    def quantum(self) -> float | None:
        """The step between neighbouring codes on the [0, 1] scale (1/255, 1/65535); None for floats."""
        return None if self.bits is None else 1.0 / (2**self.bits - 1)

    def values(self) -> np.ndarray:
        """The codes on the [0, 1] scale as float64 (integers over their top code; floats as stored)."""
        if self.bits is None:
            return np.asarray(self.codes, np.float64)
        return self.codes / float(2**self.bits - 1)

    def linear(self, encoding: str | None = None) -> np.ndarray:
        """The values decoded to linear by ``encoding`` (default: the declared one; a file that
        declares none is read as linear)."""
        return color.decode(self.values(), encoding or self.encoding or "linear")


def read_image(path) -> Image:
    """The image at ``path`` as stored (:class:`Image`), its format from its first bytes.

    Raises :class:`ImageError` naming the file: missing, truncated, corrupt, not an image, an
    ICC profile other than sRGB, or a pixel type other than 8/16-bit integers and floats."""
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: image file not found")
    try:
        with open(path, "rb") as f:
            head = f.read(8)
        codes, encoding, why = _reader(head)(path)
    except ImageError:
        raise
    except color.EncodingError as exc:
        raise ImageError(str(exc)) from exc
    except Exception as exc:  # noqa: BLE001 - each library raises its own types; name the file
        raise ImageError(f"{path}: cannot read as an image: {exc}") from exc
    codes = np.asarray(codes)
    if codes.dtype == np.float16:
        codes = codes.astype(np.float32)
    if not (codes.dtype in (np.uint8, np.uint16) or np.issubdtype(codes.dtype, np.floating)):
        raise ImageError(f"{path}: unsupported pixel type {codes.dtype} (8- or 16-bit integers or floats)")
    if codes.ndim not in (2, 3) or min(codes.shape[:2]) == 0:
        raise ImageError(f"{path}: not a 2-D image (an array of shape {codes.shape})")
    return Image(codes, encoding, why, path)


def _reader(head: bytes):
    """The reader of a file that starts with ``head``."""
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        return _read_png
    if head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return _read_tiff
    if head.startswith(b"\x76\x2f\x31\x01"):
        return _read_exr
    if head.startswith(b"\x93NUMPY"):
        return _read_npy
    return _read_other


def _read_png(path: Path):
    import imagecodecs

    encoding, why = color.png_encoding(path)
    return imagecodecs.png_decode(path.read_bytes()), encoding, why


def _read_tiff(path: Path):
    import tifffile

    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        icc = page.tags.get(34675)  # InterColorProfile
        icc = None if icc is None else bytes(icc.value)
        codes = page.asarray()
    if np.issubdtype(codes.dtype, np.floating):
        return codes, "linear", "float samples (linear)"
    if icc is None:
        return codes, None, "no ICC profile"
    desc = color.icc_description(icc)
    if "srgb" in desc.lower().replace(" ", ""):
        return codes, "srgb", f"its ICC profile ({desc})"
    raise ImageError(
        f"{path}: its ICC profile is {desc!r}, not sRGB; convert the image to sRGB or declare the "
        "encoding (--encoding srgb | linear | gamma:G) to read it as that"
    )


def _read_exr(path: Path):
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        chans = f.channels()
        for key in ("RGBA", "RGB", "Y"):
            if key in chans:
                codes = np.asarray(chans[key].pixels)
                break
        else:
            if not all(c in chans for c in "RGB"):
                raise ImageError(f"{path}: an OpenEXR file without R, G, B or Y channels (it has {sorted(chans)})")
            codes = np.stack([np.asarray(chans[c].pixels) for c in "RGB"], axis=-1)
    return codes, "linear", "OpenEXR (linear)"


def _read_npy(path: Path):
    codes = np.load(path, allow_pickle=False)
    if not np.issubdtype(codes.dtype, np.floating):
        raise ImageError(f"{path}: a .npy image must hold floats (linear values), got {codes.dtype}")
    return codes, "linear", "a .npy array (floats are linear)"


def _read_other(path: Path):
    import imagecodecs

    return (
        imagecodecs.imread(path),
        None,
        f"a {path.suffix or 'headerless'} file declares no encoding this package reads",
    )


def write_image(path, image, encoding: str = "linear", bits: int | None = None) -> None:
    """``image`` (linear, ``[H, W]`` or ``[H, W, C]``) to ``path``, its format from the suffix:

    - ``.png``: encoded as ``encoding`` into ``bits`` = 8 (the default) or 16-bit codes, the
      ``sRGB`` or ``gAMA`` chunk declaring it;
    - ``.tif``/``.tiff``: the same codes (``bits`` 16, the default, or 8), deflate-compressed, an
      sRGB file tagged with its ICC profile (a TIFF declares no gamma); or ``bits=32``: float32
      linear values;
    - ``.exr``: linear float (``bits`` 32, the default) or half (16) values, ZIP-compressed;
    - ``.npy``: float64 linear values.

    Integer files are clipped to [0, 1]; float files keep the values as they are. The file is
    written whole or not at all (a temporary beside it, then renamed)."""
    path = Path(path)
    suffix = path.suffix.lower().lstrip(".")
    img = np.asarray(image, np.float64)
    if img.ndim not in (2, 3):
        raise ImageError(f"{path}: an image must be [H, W] or [H, W, C], got shape {img.shape}")
    color.parse_encoding(encoding)
    allowed = {"png": (8, 16), "tif": (16, 8, 32), "tiff": (16, 8, 32), "exr": (32, 16), "npy": (64,)}.get(suffix)
    if allowed is None:
        raise ImageError(f"{path}: cannot write a {path.suffix or 'suffix-less'} file; one of .png .tif .exr .npy")
    bits = allowed[0] if bits is None else bits
    if bits not in allowed:
        raise ImageError(f"{path}: a .{suffix} file is written with bits in {allowed}, got {bits}")
    if suffix == "png":
        data = _png_bytes(color.quantise(img, encoding, bits), encoding)
    elif suffix in ("tif", "tiff"):
        data = _tiff_bytes(path, img, encoding, bits)
    elif suffix == "exr":
        data = _exr_bytes(path, img, bits)
    else:
        buf = io.BytesIO()
        np.save(buf, img)
        data = buf.getvalue()
    tmp = path.with_name(path.name + ".part")
    try:
        tmp.write_bytes(data)
        tmp.replace(path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise ImageError(f"{path}: cannot write: {exc}") from exc


def _png_bytes(codes: np.ndarray, encoding: str) -> bytes:
    """libpng's PNG of ``codes`` with the chunks declaring ``encoding`` inserted after its header
    (the PNG specification's place for them: before the image data)."""
    import imagecodecs

    png = imagecodecs.png_encode(codes, level=6)
    end_ihdr = 8 + 4 + 4 + 13 + 4  # signature, IHDR's length, type, data, CRC
    chunks = b"".join(_chunk(cid, payload) for cid, payload, *_ in color.png_info(encoding).chunks)
    return png[:end_ihdr] + chunks + png[end_ihdr:]


def _chunk(cid: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + cid + payload + struct.pack(">I", zlib.crc32(cid + payload))


def _tiff_bytes(path: Path, img: np.ndarray, encoding: str, bits: int) -> bytes:
    import tifffile

    kind, _ = color.parse_encoding(encoding)
    extra = []
    if bits == 32:
        data = img.astype(np.float32)
    else:
        data = color.quantise(img, encoding, bits)
        if kind == "srgb":
            extra = [(34675, "B", None, color.srgb_profile(), True)]
        elif kind != "linear":
            raise ImageError(
                f"{path}: a TIFF declares sRGB (an ICC profile) or nothing (linear); write {encoding} as PNG"
            )
    photometric = "rgb" if data.ndim == 3 and data.shape[2] in (3, 4) else "minisblack"
    buf = io.BytesIO()
    tifffile.imwrite(buf, data, photometric=photometric, compression="zlib", extratags=extra)
    return buf.getvalue()


def _exr_bytes(path: Path, img: np.ndarray, bits: int) -> bytes:
    import tempfile

    import OpenEXR

    data = np.ascontiguousarray(img.astype(np.float16 if bits == 16 else np.float32))
    key = {1: "Y", 3: "RGB", 4: "RGBA"}.get(1 if data.ndim == 2 else data.shape[2])
    if key is None:
        raise ImageError(f"{path}: an OpenEXR file of 1, 3 or 4 channels, got {data.shape[2]}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with tempfile.TemporaryDirectory() as tmp:  # the bindings write only to a named file
        out = Path(tmp) / "image.exr"
        with OpenEXR.File(header, {key: data}) as f:
            f.write(str(out))
        return out.read_bytes()
