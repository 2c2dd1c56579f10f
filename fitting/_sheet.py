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
