"""The stages of ``fluo demo`` (see demo.py for how they run).

Each stage is ``fn(ctx)``: it reads what earlier stages left in ``ctx.state``,
writes files into ``ctx.out``, records numbers in ``ctx.metrics[stage]`` and
figures with ``ctx.figure``.
"""

from __future__ import annotations

import numpy as np

from . import mrml_io
from .phantoms import add_phantom_to_scene, make_phantom, write_phantom

TUBE_DEPTHS_MM = [2.7, 3.7, 4.7, 5.7, 6.7]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def stage_phantoms(ctx):
    """Digital phantoms: cylinder-tube at the thesis's tube depths, oral cavity, slab."""
    depths = TUBE_DEPTHS_MM[::2] if ctx.quick else TUBE_DEPTHS_MM
    ctx.metrics["tube_depths_mm"] = depths
    out = {}
    tubes = {}
    for d in depths:
        ph = make_phantom("cylinder-tube", depth_mm=d, seed=ctx.seed)
        write_phantom(ph, ctx.out / "phantoms" / f"cylinder-tube-{d:.1f}mm")
        tubes[d] = ph
        out[f"cylinder-tube {d:.1f} mm: tube volume error %"] = ph.truth()["regions"]["2"]["volume_error_pct"]
    others = {}
    for name in ("oral-cavity", "slab"):
        ph = make_phantom(name, seed=ctx.seed)
        write_phantom(ph, ctx.out / "phantoms" / name)
        others[name] = ph
        for label, r in ph.truth()["regions"].items():
            out[f"{name} region {r['name']}: volume error %"] = r["volume_error_pct"]
    ctx.state["tube_phantoms"] = tubes
    ctx.state["phantoms"] = others
    # The demo's own scene starts from the cylinder-tube phantom at the first depth.
    scene = mrml_io.new_scene()
    add_phantom_to_scene(scene, tubes[depths[0]])
    ctx.state["scene"] = scene
    mrml_io.save_scene(scene, ctx.out / "scene.mrml")
    ctx.metrics["phantoms"] = out

    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    ph = tubes[depths[0]]
    i = ph.labels.shape[2] // 2
    ext = [ph.origin_mm[1], ph.origin_mm[1] + ph.spacing_mm[1] * ph.labels.shape[1],
           ph.origin_mm[2], ph.origin_mm[2] + ph.spacing_mm[2] * ph.labels.shape[0]]
    axes[0].imshow(ph.cbct_hu[:, :, i], cmap="gray", vmin=-300, vmax=300, origin="lower", extent=ext)
    axes[0].set_title(f"cylinder-tube CBCT (tube at {depths[0]} mm), y-z slice")
    axes[0].set_xlabel("y [mm]")
    axes[0].set_ylabel("z [mm]")
    oc = others["oral-cavity"]
    j = oc.labels.shape[1] // 2 + 5
    ext = [oc.origin_mm[0], oc.origin_mm[0] + oc.spacing_mm[0] * oc.labels.shape[2],
           oc.origin_mm[2], oc.origin_mm[2] + oc.spacing_mm[2] * oc.labels.shape[0]]
    axes[1].imshow(oc.cbct_hu[:, j, :], cmap="gray", vmin=-300, vmax=300, origin="lower", extent=ext)
    axes[1].set_title("oral-cavity CBCT, x-z slice")
    axes[1].set_xlabel("x [mm]")
    axes[2].imshow(oc.labels[:, j, :], cmap="viridis", origin="lower", extent=ext,
                   interpolation="nearest")
    axes[2].set_title("oral-cavity labels (0 air, 1 agar, 2 tongue)")
    axes[2].set_xlabel("x [mm]")
    fig.tight_layout()
    fig.savefig(ctx.out / "phantoms.png", dpi=90)
    plt.close(fig)
    ctx.figure("phantoms", "phantoms.png", "Digital phantoms: synthetic CBCT (HU) and label maps.")


STAGES = [
    ("phantoms", "digital phantoms", stage_phantoms),
]
