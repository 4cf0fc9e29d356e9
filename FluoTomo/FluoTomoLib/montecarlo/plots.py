"""The validation figure: R(rho) and interior fluence, Monte Carlo against the FEM."""

from __future__ import annotations

import numpy as np

_COLOURS = {"empirical": "tab:red", "fresnel": "tab:blue"}


def validation_figure(result, medium_text, path):
    """2 x 2 PNG: R(rho) (log) with MC error bars and the models; their difference from
    MC [%] with the MC's 2-sigma band; interior fluence against rho at each depth;
    the FEM's fluence difference from MC [%]."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["rows"]
    rho = np.array([r["rho_mm"] for r in rows])
    mc = np.array([r["mc"] for r in rows])
    se = np.array([r["mc_se"] for r in rows])
    fig, ax = plt.subplots(2, 2, figsize=(13, 9.5))
    a = ax[0, 0]
    a.errorbar(rho, mc, yerr=2 * se, fmt="o", ms=4, color="k", label="Monte Carlo (MCX), 2 SE")
    for b, A in result["A"].items():
        a.plot(rho, [r[f"fem_{b}"] for r in rows], "-", color=_COLOURS.get(b),
               label=f"FEM, A = {A:.3f} ({b})")
    a.plot(rho, [r["dipole"] for r in rows], "--", color="tab:gray", label="dipole R(rho)")
    if "reference" in rows[0]:
        a.plot(rho, [r.get("reference", np.nan) for r in rows], "x", color="tab:green",
               label="independent MC run")
    a.set_yscale("log")
    a.set_xlabel("source-detector distance rho [mm]")
    a.set_ylabel("R(rho) [1/mm^2 per entering photon]")
    a.set_title(f"Spatially resolved reflectance ({medium_text})")
    a.legend(fontsize=9)
    a.grid(alpha=0.3)
    a = ax[0, 1]
    band = 200 * se / mc
    a.fill_between(rho, -band, band, color="0.85", label="MC: 2 SE")
    a.axhspan(-3, 3, color="tab:green", alpha=0.08, label="+-3 %")
    for b in result["A"]:
        a.plot(rho, [r[f"fem_{b}_vs_mc_pct"] for r in rows], "o-", ms=3, color=_COLOURS.get(b),
               label=f"FEM ({b}) - MC")
    a.plot(rho, [r["dipole_vs_mc_pct"] for r in rows], "--", color="tab:gray", label="dipole - MC")
    if "reference" in rows[0]:
        a.plot(rho, [r.get("mc_vs_reference_pct", np.nan) for r in rows], "x", color="tab:green",
               label="MC - independent run")
    a.axhline(0, color="k", lw=0.8)
    a.set_ylim(-25, 25)
    a.set_xlabel("rho [mm]")
    a.set_ylabel("difference from Monte Carlo [%]")
    a.set_title("Model - Monte Carlo (near the beam: diffusion's excess)")
    a.legend(fontsize=8, ncol=2)
    a.grid(alpha=0.3)
    fr = result["fluence_rows"]
    depths = sorted({r["depth_mm"] for r in fr})
    cmap = plt.get_cmap("viridis")
    main = result["boundary"]
    for k, z in enumerate(depths):
        sel = [r for r in fr if r["depth_mm"] == z]
        c = cmap(k / max(len(depths) - 1, 1))
        rr = [r["rho_mm"] for r in sel]
        ax[1, 0].errorbar(rr, [r["mc"] for r in sel],
                          yerr=[2 * (r["mc_se"] if np.isfinite(r["mc_se"]) else 0) for r in sel],
                          fmt="o", ms=4, color=c, label=f"MC, depth {z:g} mm")
        ax[1, 0].plot(rr, [r[f"fem_{main}"] for r in sel], "-", color=c)
        for b in result["A"]:
            ax[1, 1].plot(rr, [r[f"fem_{b}_vs_mc_pct"] for r in sel],
                          "o-" if b == "empirical" else "s--", ms=4, color=c,
                          label=f"{b}, depth {z:g} mm")
    ax[1, 0].set_yscale("log")
    ax[1, 0].set_xlabel("rho [mm]")
    ax[1, 0].set_ylabel("fluence [1/mm^2 per entering photon]")
    ax[1, 0].set_title(f"Interior fluence: MC (points) and FEM ({main}, lines)")
    ax[1, 0].legend(fontsize=8)
    ax[1, 0].grid(alpha=0.3)
    ax[1, 1].axhspan(-3, 3, color="tab:green", alpha=0.08)
    ax[1, 1].axhline(0, color="k", lw=0.8)
    ax[1, 1].set_ylim(-25, 25)
    ax[1, 1].set_xlabel("rho [mm]")
    ax[1, 1].set_ylabel("FEM - MC [%]")
    ax[1, 1].set_title("Interior fluence: FEM - MC (circles: empirical A, squares: Fresnel A)")
    ax[1, 1].legend(fontsize=7, ncol=2)
    ax[1, 1].grid(alpha=0.3)
    fig.tight_layout()
    from fluoguide import atomic

    atomic.save_figure(fig, path, field="--out", dpi=110)   # whole, or nothing
    plt.close(fig)
    return path
