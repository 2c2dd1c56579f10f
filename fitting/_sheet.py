"""The CLI's ``fit.png``: a contact sheet of the views a user looks at first.

Each row is one view, ``target | fit | 10× residual + 0.5``. With more than :data:`SHEET_VIEWS`
views, the rows are the worst view (largest RMS residual over its mask) and a spread of the
others by their RMS, worst first; with fewer, every view in order. Every panel is shown at one
exposure that shows the object: a linear capture's targets are nearly black at their own values,
so the sheet scales target, fit and residual alike by ``0.8 / p99`` of the shown targets' masked
values when that is below 0.4 (else 1). Pixels outside the mask are grey.
"""

from __future__ import annotations

import numpy as np

SHEET_VIEWS = 8  # rows of the contact sheet at most
MASKED_GREY = 0.2


def contact_sheet(targets, images, masks=None, max_views: int = SHEET_VIEWS):
    """``(sheet, views, exposure)``: the contact sheet (linear ``[rows·H, 3W, 3]``), the views it
    shows (in row order) and the exposure it shows them at. ``targets``, ``images``: per view
    ``[H, W, 3]`` linear; ``masks``: per view ``[H, W]`` weights or None."""
    n = len(targets)
    masks = [None] * n if masks is None else list(masks)
    used = [np.ones(t.shape[:2], bool) if m is None else np.asarray(m) > 0 for t, m in zip(targets, masks)]
    rms = np.array(
        [
            float(np.sqrt(np.mean((np.asarray(i, np.float64) - t)[u] ** 2))) if u.any() else 0.0
            for t, i, u in zip(targets, images, used)
        ]
    )
    if n <= max_views:
        views = list(range(n))
    else:
        order = np.argsort(-rms, kind="stable")  # worst first
        views = [int(order[i]) for i in np.unique(np.linspace(0, n - 1, max_views).round().astype(int))]
    shown = np.concatenate([np.asarray(targets[k], np.float64)[used[k]].reshape(-1) for k in views] or [np.zeros(1)])
    p99 = float(np.percentile(shown, 99)) if shown.size else 0.0
    exposure = 0.8 / p99 if 0.0 < p99 < 0.4 else 1.0
    rows = []
    for k in views:
        t, img = exposure * np.asarray(targets[k], np.float64), exposure * np.asarray(images[k], np.float64)
        row = np.concatenate([t, img, np.clip(0.5 + 10.0 * (img - t), 0, 1)], axis=1)
        if masks[k] is not None:
            row = np.where(np.tile(used[k], (1, 3))[..., None], row, MASKED_GREY)
        rows.append(row)
    return np.concatenate(rows, axis=0), views, exposure


def holdout_plot(held, width: int = 720, height: int = 300) -> np.ndarray:
    """``[height, width, 3]`` (sRGB-encoded values in [0, 1], for an 8-bit PNG): the held-out
    views' RMS over the noise (:class:`fitting.Holdout`), one bar per view in view order (red
    where it is above the verdict's limit for that view's entries), a line at 1 (the noise), the
    views' indices below (every k-th where they crowd) and the ratio over them all in the title;
    Pillow's own font."""
    from PIL import Image, ImageDraw

    from ._report import noise_ratio_limit

    ratios = np.asarray(held.ratio, np.float64)
    top = max(2.0, float(np.nanmax(np.where(np.isfinite(ratios), ratios, 0))) * 1.1)
    im = Image.new("RGB", (width, height), (255, 255, 255))
    d = ImageDraw.Draw(im)
    x0, x1, y0, y1 = 48, width - 12, 28, height - 30  # the plot's box
    y_of = lambda v: y1 - (y1 - y0) * min(v, top) / top  # noqa: E731
    d.text(
        (x0, 6), f"held-out RMS / noise per view (all: {held.ratio_all:.3g}x, sigma {held.noise:.3g})", fill=(0, 0, 0)
    )
    for v in np.arange(0, top + 1e-9, 1.0 if top <= 10 else np.ceil(top / 8)):
        d.line([(x0 - 4, y_of(v)), (x0, y_of(v))], fill=(0, 0, 0))
        d.text((4, y_of(v) - 6), f"{v:g}", fill=(0, 0, 0))
    n = max(len(ratios), 1)
    step = (x1 - x0) / n
    every = int(np.ceil(n / max((x1 - x0) // 28, 1)))
    for k, (view, r, e) in enumerate(zip(held.views, ratios, held.entries)):
        a, b = x0 + k * step + step * 0.15, x0 + (k + 1) * step - step * 0.15
        bad = r > noise_ratio_limit(max(int(e), 1))
        d.rectangle([a, y_of(r if np.isfinite(r) else top), b, y1], fill=(200, 70, 60) if bad else (70, 110, 190))
        if k % every == 0:
            d.text((a, y1 + 6), str(view), fill=(0, 0, 0))
    d.line([(x0, y1), (x1, y1)], fill=(0, 0, 0))
    d.line([(x0, y0), (x0, y1)], fill=(0, 0, 0))
    d.line([(x0, y_of(1.0)), (x1, y_of(1.0))], fill=(0, 140, 0), width=1)
    d.text((x1 - 60, y_of(1.0) - 14), "the noise", fill=(0, 120, 0))
    return np.asarray(im, np.float64) / 255.0
