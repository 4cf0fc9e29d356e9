"""Figures of the simulation studies: forward model | NP | SP | HP on one colour scale."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def plot_case(out_dir, index, title, fields):
    """PNG of every reconstruction of one case next to the truth (same colour scale),
    with the true target outlined on every panel (half-way between the background and
    the target yield of the forward model).  Two panels a row, ~500 px each."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.tri as mtri

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    vmax = max(float(np.max(v)) for _, v in fields.values())
    n = len(fields)
    cols = 2 if n <= 4 else 4
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 3.0 * rows + 0.6), squeeze=False,
                             constrained_layout=True)
    truth_mesh, truth = fields["truth"]
    level = 0.5 * (float(np.min(truth)) + float(np.max(truth)))
    for ax, (name, (mesh, values)) in zip(axes.flat, fields.items()):
        if mesh.dim == 2:
            tri = mtri.Triangulation(mesh.nodes_mm[:, 0], mesh.nodes_mm[:, 1], mesh.elements)
            im = ax.tripcolor(tri, 1e3 * np.asarray(values), shading="gouraud", cmap="inferno",
                              vmin=0, vmax=1e3 * vmax)
            t_tri = mtri.Triangulation(truth_mesh.nodes_mm[:, 0], truth_mesh.nodes_mm[:, 1],
                                       truth_mesh.elements)
            ax.tricontour(t_tri, np.asarray(truth), levels=[level], colors="cyan",
                          linewidths=1.0)
        else:  # the y = 0 section through the target
            from FluoTomoLib.fem.locate import locator

            xx, zz = np.meshgrid(np.linspace(-20, 20, 201), np.linspace(0, -20, 101))
            pts = np.stack([xx.ravel(), np.zeros(xx.size), zz.ravel()], axis=1)

            def section(m, v):
                return (locator(m).interpolation_matrix(pts, outside="zero") @ v).reshape(xx.shape)

            im = ax.imshow(1e3 * section(mesh, values), extent=(-20, 20, -20, 0), origin="upper",
                           cmap="inferno", vmin=0, vmax=1e3 * vmax)
            ax.contour(xx, zz, section(truth_mesh, truth), levels=[level], colors="cyan",
                       linewidths=1.0)
        ax.set_aspect("equal")
        ax.set_xlim(-20, 20)
        ax.set_ylim(-20, 0)
        ax.set_title("forward model (truth)" if name == "truth" else name, fontsize=11)
        ax.set_xlabel("x [mm]")
        ax.set_ylabel("depth axis [mm] (surface at 0)")
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    fig.colorbar(im, ax=axes, shrink=0.8, label="fluorescence yield [1e-3 / mm]")
    fig.suptitle(f"{title}  (cyan: the true target)", fontsize=12)
    path = out / f"case_{index:02d}.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return str(path)
