"""Figures of the simulation studies: forward model | NP | SP | HP on one colour scale."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fluoguide import atomic


def plot_case(out_dir, index, title, fields):
    """PNG of every reconstruction of one case next to the truth (same scale)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.tri as mtri

    out = Path(out_dir)
    vmax = max(float(np.max(v)) for _, v in fields.values())
    n = len(fields)
    fig, axes = plt.subplots(1, n, figsize=(3.3 * n, 2.8))
    axes = np.atleast_1d(axes)
    for ax, (name, (mesh, values)) in zip(axes, fields.items()):
        if mesh.dim == 2:
            tri = mtri.Triangulation(mesh.nodes_mm[:, 0], mesh.nodes_mm[:, 1], mesh.elements)
            im = ax.tripcolor(tri, 1e3 * np.asarray(values), shading="gouraud", cmap="inferno",
                              vmin=0, vmax=1e3 * vmax)
        else:  # the y = 0 section through the target
            from FluoTomoLib.fem.locate import locator

            xx, zz = np.meshgrid(np.linspace(-20, 20, 201), np.linspace(0, -20, 101))
            pts = np.stack([xx.ravel(), np.zeros(xx.size), zz.ravel()], axis=1)
            img = (locator(mesh).interpolation_matrix(pts, outside="zero") @ values).reshape(xx.shape)
            im = ax.imshow(1e3 * img, extent=(-20, 20, -20, 0), origin="upper", cmap="inferno",
                           vmin=0, vmax=1e3 * vmax)
        ax.set_aspect("equal")
        ax.set_xlim(-20, 20)
        ax.set_ylim(-20, 0)
        ax.set_title("forward model" if name == "truth" else name, fontsize=9)
        ax.set_xlabel("x [mm]")
    axes[0].set_ylabel("depth axis [mm] (surface at 0)")
    fig.colorbar(im, ax=list(axes), shrink=0.8, label="yield [1e-3 / mm]")
    fig.suptitle(title, fontsize=10)
    path = out / f"case_{index:02d}.png"
    atomic.save_figure(fig, path, dpi=80)
    plt.close(fig)
    return str(path)
