"""Figures of the simulation studies: forward model | NP | SP | HP on one colour scale."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fluoguide import atomic


def plot_case(out_dir, index, title, fields):
    """PNG of every reconstruction of one case next to the truth (same colour scale),
    with the true target outlined on every panel (half-way between the background and
    the target yield of the forward model).  Two panels a row, ~500 px each."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.tri as mtri

    out = Path(out_dir)
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
    atomic.save_figure(fig, path, dpi=100)
    plt.close(fig)
    return str(path)


# parameters that may vary within one study, and how a point's label names them
_LABELS = (("case", ""), ("lambda", "lambda "), ("noise_pct", "noise "), ("seed", "seed "),
           ("forward_mm", "fwd "), ("recon_mm", "rec "), ("data_mm", "data "),
           ("roi_depth_mm", "roi "), ("scheme", ""), ("hp_basis", "basis "))
_COLOURS = {"NP": "tab:red", "SP": "tab:blue", "HP": "tab:green"}


def _point_label(row, varying):
    parts = []
    for key, prefix in _LABELS:
        if key in varying:
            v = row[key]
            v = v.split(": ", 1)[-1] if key == "case" else (f"{v:g}" if isinstance(v, float) else v)
            parts.append(f"{prefix}{v}")
    return ", ".join(parts)


def plot_error_vs_time(rows, out_dir, title="", name="error_vs_time.png"):
    """PNG of the absolute peak and centroid errors [%] against the time one
    reconstruction costs [s] (the solver plus its Jacobian, which a fresh
    model pays once), one colour per method, each point labelled with what
    varies in the study. Returns the path, or None when no task finished."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    ok = [r for r in rows if r.get("status", "ok") == "ok" and r.get("peak_error_pct") is not None
          and r.get("seconds") is not None]
    if not ok:
        return None
    varying = {k for k, _ in _LABELS if len({str(r.get(k)) for r in ok}) > 1}
    annotate = len(ok) <= 60
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.2))
    floor = 1e-2     # |error| below 0.01 % is drawn at 0.01 % (log axis)
    for ax, key, what in ((axes[0], "peak_error_pct", "peak yield"),
                          (axes[1], "centroid_error_pct", "centroid depth")):
        for method in sorted({r["method"] for r in ok}):
            pts = [r for r in ok if r["method"] == method and r.get(key) is not None]
            if not pts:
                continue
            x = [r["seconds"] + (r.get("jacobian_seconds") or 0.0) for r in pts]
            y = [max(abs(r[key]), floor) for r in pts]
            ax.scatter(x, y, s=36, color=_COLOURS.get(method, "k"), label=method, alpha=0.85,
                       edgecolors="k", linewidths=0.4)
            if annotate and varying:
                for xi, yi, r in zip(x, y, pts):
                    ax.annotate(_point_label(r, varying), (xi, yi), textcoords="offset points",
                                xytext=(4, 3), fontsize=7, color=_COLOURS.get(method, "k"))
        ax.set_xscale("log")
        ax.set_yscale("log")
        for axis in (ax.xaxis, ax.yaxis):      # 0.5, 2, 10 rather than 5x10^-1 ...
            axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
            axis.set_minor_formatter(FuncFormatter(lambda v, _: ""))
        ax.set_xlabel("time per reconstruction incl. its Jacobian [s]")
        ax.set_ylabel(f"|{what} error| [%] (0.01: below 0.01)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(title="method", fontsize=8)
    failed = len(rows) - len(ok)
    fig.suptitle(f"{title}: error against time ({len(ok)} reconstructions"
                 + (f", {failed} failed: see table.csv" if failed else "") + ")", fontsize=11)
    fig.tight_layout()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    from fluoguide.atomic import atomic_path

    with atomic_path(out / name) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)
    return str(out / name)
