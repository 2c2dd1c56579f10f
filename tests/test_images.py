"""Image files through libraries (diffshade.images): 8/16-bit PNG, 8/16-bit and float TIFF,
half and float OpenEXR, .npy; values exact through a round trip, the colour encoding read from
the file where it declares one, every PNG row filter read whole, bad files named."""

import os
import struct
import zlib

import numpy as np
import pytest

import diffshade as ds
from diffshade import color as C

RNG = np.random.default_rng(7)
IMG = RNG.uniform(size=(9, 11, 3))
IMG[0, 0], IMG[0, 1] = 0.0, 1.0  # both ends, clipped codes


@pytest.mark.parametrize(
    "name,encoding,bits,declared",
    [
        ("x.png", "srgb", 8, "srgb"),
        ("x.png", "linear", 8, "linear"),
        ("x.png", "gamma:2.2", 8, "gamma:2.2"),
        ("x.png", "srgb", 16, "srgb"),
        ("x.png", "linear", 16, "linear"),
        ("x.png", "gamma:2.2", 16, "gamma:2.2"),
        ("x.tif", "srgb", 16, "srgb"),
        ("x.tiff", "linear", 16, None),  # a TIFF without a profile declares nothing
        ("x.tif", "srgb", 8, "srgb"),
    ],
)
def test_integer_files_round_trip_their_codes_and_declare_their_encoding(tmp_path, name, encoding, bits, declared):
    path = tmp_path / name
    ds.write_image(path, IMG, encoding, bits)
    im = ds.read_image(path)
    assert im.encoding == declared, im.why
    assert im.bits == bits and im.quantum == 1 / (2**bits - 1)
    assert np.array_equal(im.codes, C.quantise(IMG, encoding, bits))
    # decoded, the image is the linear one to within the slope times half a code step
    assert np.abs(im.linear(encoding) - IMG).max() < (3.0 if encoding != "linear" else 0.51) / (2**bits - 1)
    assert not any(p.name.endswith(".part") for p in tmp_path.iterdir())


@pytest.mark.parametrize(
    "name,bits,dtype",
    [("x.exr", 32, np.float32), ("x.exr", 16, np.float16), ("x.tif", 32, np.float32), ("x.npy", 64, np.float64)],
)
@pytest.mark.parametrize("channels", [1, 3, 4])
def test_float_files_round_trip_their_values_exactly(tmp_path, name, bits, dtype, channels):
    img = RNG.uniform(-0.5, 40.0, size=(6, 5, channels))  # floats are not clipped: HDR and negative kept
    img = img[..., 0] if channels == 1 else img
    path = tmp_path / name
    ds.write_image(path, img, bits=bits)
    im = ds.read_image(path)
    assert im.encoding == "linear" and im.bits is None and im.quantum is None
    assert im.codes.shape == img.shape
    assert np.array_equal(im.codes.astype(np.float64), img.astype(dtype).astype(np.float64))


def test_icc_profiles_and_undeclared_files(tmp_path):
    from PIL import Image, ImageCms

    codes = C.quantise(RNG.uniform(size=(6, 7, 3)), "srgb")
    Image.fromarray(codes).save(tmp_path / "icc.png", icc_profile=C.srgb_profile())
    im = ds.read_image(tmp_path / "icc.png")
    assert im.encoding == "srgb" and "ICC profile" in im.why and np.array_equal(im.codes, codes)
    lab = ImageCms.ImageCmsProfile(ImageCms.createProfile("LAB")).tobytes()
    Image.fromarray(codes).save(tmp_path / "lab.png", icc_profile=lab)
    with pytest.raises(ds.ImageError, match=r"lab.png: its ICC profile is .*not sRGB"):
        ds.read_image(tmp_path / "lab.png")
    import tifffile

    tifffile.imwrite(tmp_path / "lab.tif", codes, photometric="rgb", extratags=[(34675, "B", None, lab, True)])
    with pytest.raises(ds.ImageError, match=r"lab.tif: its ICC profile is .*not sRGB"):
        ds.read_image(tmp_path / "lab.tif")
    Image.fromarray(codes).save(tmp_path / "plain.png")
    assert ds.read_image(tmp_path / "plain.png").encoding is None
    Image.fromarray(codes).save(tmp_path / "plain.jpg", quality=95)
    im = ds.read_image(tmp_path / "plain.jpg")
    pil = np.asarray(Image.open(tmp_path / "plain.jpg"), int)  # the same libjpeg, give or take its IDCT
    assert im.encoding is None and im.bits == 8 and np.abs(im.codes.astype(int) - pil).max() <= 2


def _png16_with_filters(codes, kinds):
    """A 16-bit PNG whose rows use the given filter types (what libpng's adaptive filtering writes)."""
    h, w, c = codes.shape
    bpp = 2 * c
    rows = codes.astype(">u2").view(np.uint8).reshape(h, w * bpp).astype(np.int64)
    out, prev = [], np.zeros(w * bpp, np.int64)
    for y in range(h):
        cur, kind = rows[y], kinds[y % len(kinds)]
        left = np.concatenate([np.zeros(bpp, np.int64), cur[:-bpp]])
        upleft = np.concatenate([np.zeros(bpp, np.int64), prev[:-bpp]])
        if kind == 0:
            f = cur
        elif kind == 1:
            f = cur - left
        elif kind == 2:
            f = cur - prev
        elif kind == 3:
            f = cur - ((left + prev) >> 1)
        else:
            p = left + prev - upleft
            pa, pb, pc = np.abs(p - left), np.abs(p - prev), np.abs(p - upleft)
            f = cur - np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, prev, upleft))
        out.append(bytes([kind]) + (f & 255).astype(np.uint8).tobytes())
        prev = cur

    def chunk(cid, payload):
        return struct.pack(">I", len(payload)) + cid + payload + struct.pack(">I", zlib.crc32(cid + payload))

    ctype = {1: 0, 2: 4, 3: 2, 4: 6}[c]
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 16, ctype, 0, 0, 0))
        + chunk(b"IDAT", zlib.compress(b"".join(out)))
        + chunk(b"IEND", b"")
    )


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_16_bit_pngs_are_read_whole_with_every_row_filter(tmp_path, channels):
    # Pillow reads 16-bit colour PNGs as 8-bit, silently; libpng reads them whole
    codes = RNG.integers(0, 65536, size=(10, 13, channels)).astype(np.uint16)
    codes[3] = codes[2]  # repeated rows and smooth runs, as real images have
    path = tmp_path / "f.png"
    path.write_bytes(_png16_with_filters(codes, [0, 1, 2, 3, 4]))
    im = ds.read_image(path)
    assert im.bits == 16 and np.array_equal(im.codes.reshape(codes.shape), codes)


@pytest.mark.parametrize("suffix", [".png", ".tif", ".exr", ".npy"])
def test_bad_files_are_named(tmp_path, suffix):
    path = tmp_path / f"x{suffix}"
    ds.write_image(path, IMG)
    whole = path.read_bytes()
    path.write_bytes(whole[: len(whole) // 3])
    with pytest.raises(ds.ImageError, match=rf"x\{suffix}: "):
        ds.read_image(path)
    path.write_bytes(whole[:8] + os.urandom(64))  # the right signature, garbage after it
    with pytest.raises(ds.ImageError, match=rf"x\{suffix}: "):
        ds.read_image(path)
    with pytest.raises(ds.ImageError, match="not found"):
        ds.read_image(tmp_path / f"none{suffix}")


def test_what_cannot_be_written_is_refused_before_anything_is_written(tmp_path):
    for name, kw, words in [
        ("x.gif", {}, "cannot write a .gif"),
        ("x.png", {"bits": 32}, "bits in"),
        ("x.exr", {"bits": 8}, "bits in"),
        ("x.tif", {"encoding": "gamma:2.2"}, "declares sRGB .* or nothing"),
    ]:
        with pytest.raises(ds.ImageError, match=words):
            ds.write_image(tmp_path / name, IMG, **kw)
    with pytest.raises(ds.ImageError, match=r"\[H, W\] or \[H, W, C\]"):
        ds.write_image(tmp_path / "y.png", np.zeros(5))
    assert list(tmp_path.iterdir()) == []
