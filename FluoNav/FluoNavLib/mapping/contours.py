"""Contour-based tissue classification and its miss rate (docs/physics.md section 6.3).

Fluorescence pixels are those above ``fluo_fraction`` (5 %) of the image's
peak; the classification contour is drawn at ``contour_fraction`` (40 %) of
the peak; the miss rate is 100 % minus the percentage of fluorescence pixels
inside the contour.  A robust peak (99.9th percentile) keeps one hot pixel
from setting the scale.
"""

from __future__ import annotations

import numpy as np

from fluoguide import atomic
from fluoguide.errors import FluoInputError

__all__ = ["miss_rate", "overlay_png"]


def miss_rate(image, mask=None, contour_fraction=0.4, fluo_fraction=0.05, peak_percentile=99.9):
    """(miss rate [%], contour mask, fluorescence-pixel mask) of one image."""
    img = np.asarray(image, float)
    m = np.isfinite(img) if mask is None else (np.asarray(mask, bool) & np.isfinite(img))
    if not m.any():
        raise FluoInputError("no valid pixel to classify", field="image")
    peak = float(np.percentile(img[m], peak_percentile))
    if peak <= 0:
        raise FluoInputError("image has no positive signal", field="image", value=peak)
    fluo = m & (img > fluo_fraction * peak)
    inside = m & (img >= contour_fraction * peak)
    n = int(fluo.sum())
    rate = 100.0 - 100.0 * float((fluo & inside).sum()) / n if n else float("nan")
    return rate, inside, fluo


def overlay_png(path, image, contour_mask, title, mask=None,
                colorbar_label="counts above offset [ADU]"):
    """The image with its classification contour outlined, as a PNG; the colour bar
    says what the image holds and its unit (``colorbar_label``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    img = np.asarray(image, float)
    if mask is not None:
        img = np.where(mask, img, np.nan)
    fig, ax = plt.subplots(figsize=(5, 4))
    im = ax.imshow(img, cmap="magma")
    ax.contour(contour_mask.astype(float), levels=[0.5], colors="cyan", linewidths=1.0)
    ax.set_title(title, fontsize=9)
    ax.axis("off")
    fig.colorbar(im, ax=ax, shrink=0.8, label=colorbar_label)
    atomic.save_figure(fig, path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return str(path)
