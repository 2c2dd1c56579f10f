"""Area-averaged downsampling of a target that keeps what was clipped.

A pixel averaged from ``factor × factor`` sub-pixels of which one was clipped is itself only a
lower bound: the clipped sub-pixel's true value was higher. :func:`downsample` marks it clipped
(per channel), for :class:`fitting.Observations` ``clipped``; a mask is averaged, and a pixel
with any sub-pixel outside the mask is left out (weight 0) rather than half-weighted, since its
value mixes the object with what the mask excludes."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Downsampled(NamedTuple):
    image: np.ndarray  # [H/f, W/f, C] the area average
    clipped: np.ndarray  # [H/f, W/f, C] bool: a sub-pixel was clipped (or already marked)
    mask: np.ndarray | None  # [H/f, W/f] the mask where every sub-pixel is inside it, else 0


def _blocks(a: np.ndarray, f: int) -> np.ndarray:
    h, w = (a.shape[0] // f) * f, (a.shape[1] // f) * f
    return a[:h, :w].reshape(h // f, f, w // f, f, *a.shape[2:])


def downsample(image, factor: int, *, saturation: float | None = None, clipped=None, mask=None) -> Downsampled:
    """``image`` (linear values, ``[H, W, C]``) averaged over ``factor × factor`` blocks (the last
    rows and columns that do not fill a block dropped). ``saturation``: the level at or above
    which a sub-pixel was clipped; ``clipped``: ``[H, W]`` or ``[H, W, C]`` booleans already
    known clipped; ``mask``: ``[H, W]`` weights. Average linear values, not encoded codes
    (decode an sRGB target first: :meth:`diffshade.Image.linear`)."""
    f = int(factor)
    if f < 1:
        raise ValueError(f"factor must be an integer >= 1, got {factor}")
    img = np.asarray(image, np.float64)
    if img.ndim != 3:
        raise ValueError(f"image must be [H, W, C], got shape {img.shape}")
    if f > min(img.shape[:2]):
        raise ValueError(f"factor {f} is larger than the image ({img.shape[1]}x{img.shape[0]})")
    cl = np.zeros(img.shape, bool)
    if saturation is not None:
        cl |= img >= saturation
    if clipped is not None:
        c = np.asarray(clipped, bool)
        cl |= c[..., None] if c.ndim == 2 else c
    small = _blocks(img, f).mean(axis=(1, 3))
    small_cl = _blocks(cl, f).any(axis=(1, 3))
    small_m = None
    if mask is not None:
        m = np.asarray(mask, np.float64)
        mb = _blocks(m, f)
        small_m = np.where((mb > 0).all(axis=(1, 3)), mb.mean(axis=(1, 3)), 0.0)
    return Downsampled(small, small_cl, small_m)
