"""PNG plots of the radiometric calibrations (photon transfer, linearity, dark
signal, ratio images) that a person can read."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fluoguide import atomic

__all__ = ["plot_radiometry", "plot_ratio_images"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_radiometry(res, out_dir):
    """photon_transfer.png, linearity.png, dark.png; returns their paths."""
    plt = _plt()
    out = Path(out_dir)
    paths = []
    mu = np.array(res["ptc"]["mean_adu"])
    var = np.array(res["ptc"]["var_adu2"])
    fit = np.array(res["ptc"]["fit"], bool)
    fig, ax = plt.subplots(figsize=(5, 3.6))
    ax.plot(mu[fit], var[fit], "o", label="fitted (< 70 % of saturation)")
    ax.plot(mu[~fit], var[~fit], "x", label="not fitted")
    x = np.linspace(0, mu.max(), 50)
    ax.plot(x, res["gain_adu_per_e"] * x, "-", label=f"K = {res['gain_adu_per_e']:.3f} ADU/e-")
    ax.set_xlabel("mean signal above dark [ADU]")
    ax.set_ylabel("temporal variance [ADU²]")
    ax.set_title("Photon transfer")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    paths.append(out / "photon_transfer.png")
    atomic.save_figure(fig, paths[-1], dpi=120, bbox_inches="tight")
    plt.close(fig)
    t = np.array(res["linearity"]["exposure_s"])
    fig, ax = plt.subplots(figsize=(5, 3.6))
    ax.plot(t, mu, "o", label="light frames")
    ax.plot(t, res["linearity"]["slope_adu_per_s"] * t + res["linearity"]["intercept_adu"], "-",
            label="linear fit (5-95 % of saturation)")
    ax.legend(fontsize=8)
    ax.set_xlabel("exposure [s]")
    ax.set_ylabel("mean signal above dark [ADU]")
    ax.set_title(f"Linearity: R² {res['linearity_r2']:.5f}, NL {res['nonlinearity_pct']:.2f} %")
    ax.grid(alpha=0.3)
    paths.append(out / "linearity.png")
    atomic.save_figure(fig, paths[-1], dpi=120, bbox_inches="tight")
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(5, 3.6))
    t_dark = np.array(res["dark"]["exposure_s"], float)
    ax.plot(t_dark, res["dark"]["mean_adu"], "o", label="dark frames")
    # the fit the title quotes: slope = dark current x gain, intercept = bias x gain [ADU]
    x = np.linspace(0.0, t_dark.max(), 50)
    gain = res["gain_adu_per_e"]
    ax.plot(x, gain * (res["dark_current_e_per_s"] * x + res["bias_e"]), "-",
            label="fit: (bias + dark current x exposure) x gain")
    ax.legend(fontsize=8)
    ax.set_xlabel("exposure [s]")
    ax.set_ylabel("mean dark signal [ADU]")
    ax.set_title(f"Dark: {res['dark_current_e_per_s']:.2f} e-/s, bias {res['bias_e']:.1f} e-")
    ax.grid(alpha=0.3)
    paths.append(out / "dark.png")
    atomic.save_figure(fig, paths[-1], dpi=120, bbox_inches="tight")
    plt.close(fig)
    return [str(p) for p in paths]


def plot_ratio_images(ratios, out_dir, phantom_to_camera=None):
    """ratio_images.png: measured / model per image, 0.8..1.2 colour range.

    ``phantom_to_camera`` (one 4x4 per image, mm) puts each view's pose in its
    title: the phantom plane's distance from the camera centre and its tilt
    against the optical axis."""
    plt = _plt()
    out = Path(out_dir)
    n = len(ratios)
    fig, axes = plt.subplots(1, n, figsize=(3.4 * n, 3.2), squeeze=False)
    for k, (ax, r) in enumerate(zip(axes[0], ratios)):
        im = ax.imshow(r, vmin=0.8, vmax=1.2, cmap="coolwarm")
        ok = np.isfinite(r)
        title = f"mean {np.mean(r[ok]):.3f}, SD {np.std(r[ok]):.3f}"
        if phantom_to_camera is not None:
            T = np.asarray(phantom_to_camera[k], float)
            normal = T[:3, 2] / np.linalg.norm(T[:3, 2])
            distance = abs(float(normal @ T[:3, 3]))
            tilt = float(np.degrees(np.arccos(min(abs(normal[2]), 1.0))))
            title = f"view {k + 1}: phantom at {distance:.0f} mm,\ntilted {tilt:.0f} deg\n{title}"
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.colorbar(im, ax=axes[0].tolist(), shrink=0.8, label="measured / model (dimensionless)")
    path = out / "ratio_images.png"
    atomic.save_figure(fig, path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return [str(path)]
