"""Optical properties of the reference ICG phantoms (docs/physics.md section 3.4).

The liquid-phantom table of the thesis (Table 2-5) is linear in ICG
concentration to the printed digits, so properties at any concentration in
0..2 ug/mL are interpolated (and, with a warning-free extrapolation, up to a
few ug/mL where ICG is still in its linear, non-aggregating range).
Wavelengths: excitation 780 nm (x), emission 830 nm (m).
"""

from __future__ import annotations

from fluoguide.errors import FluoInputError

# ICG [ug/mL] -> (mua_x, musp_x, mua_f_x, mua_m, musp_m), 1/mm; n = 1.33, eta = 4 %
ICG_TABLE = {
    0.0: (0.0026, 0.89, 0.0, 0.0029, 0.81),
    0.4: (0.016, 0.89, 0.013, 0.0068, 0.81),
    0.8: (0.029, 0.89, 0.026, 0.011, 0.81),
    1.2: (0.042, 0.89, 0.039, 0.015, 0.81),
    1.6: (0.055, 0.89, 0.052, 0.018, 0.81),
    2.0: (0.068, 0.89, 0.065, 0.022, 0.81),
}
ICG_QUANTUM_YIELD = 0.04
MAX_ICG_UG_PER_ML = 10.0


def icg_liquid_optics(icg_ug_per_ml, n=1.33, base_mua_x=None, base_mua_m=None,
                      musp_x=0.89, musp_m=0.81):
    """Optical properties of Intralipid + ICG at a concentration [ug/mL].

    Linear fit through the end rows of the reference table (exact at every row
    to the printed digits).  ``base_mua_*`` replace the background absorption
    (e.g. agar instead of Intralipid).  Returns a dict with ``mua_x_per_mm``,
    ``musp_x_per_mm``, ``mua_f_x_per_mm``, ``mua_m_per_mm``, ``musp_m_per_mm``,
    ``eta``, ``yield_per_mm`` (= eta * mua_f_x), ``n`` and ``icg_ug_per_ml``.
    """
    c = float(icg_ug_per_ml)
    if not (0.0 <= c <= MAX_ICG_UG_PER_ML):
        raise FluoInputError(f"ICG concentration must be in 0..{MAX_ICG_UG_PER_ML} ug/mL",
                             field="icg_ug_per_ml", value=c)
    lo, hi = ICG_TABLE[0.0], ICG_TABLE[2.0]
    slope = [(h - l) / 2.0 for l, h in zip(lo, hi)]
    mua_x = lo[0] + slope[0] * c
    mua_f = slope[2] * c
    mua_m = lo[3] + slope[3] * c
    if base_mua_x is not None:
        mua_x = base_mua_x + slope[0] * c
    if base_mua_m is not None:
        mua_m = base_mua_m + slope[3] * c
    return {
        "icg_ug_per_ml": c,
        "mua_x_per_mm": mua_x,
        "musp_x_per_mm": float(musp_x),
        "mua_f_x_per_mm": mua_f,
        "mua_m_per_mm": mua_m,
        "musp_m_per_mm": float(musp_m),
        "eta": ICG_QUANTUM_YIELD,
        "yield_per_mm": ICG_QUANTUM_YIELD * mua_f,
        "n": float(n),
    }


def non_fluorescent_optics(mua_per_mm, musp_per_mm, n):
    """A material without fluorophore, same properties at both wavelengths."""
    return {
        "icg_ug_per_ml": 0.0,
        "mua_x_per_mm": float(mua_per_mm),
        "musp_x_per_mm": float(musp_per_mm),
        "mua_f_x_per_mm": 0.0,
        "mua_m_per_mm": float(mua_per_mm),
        "musp_m_per_mm": float(musp_per_mm),
        "eta": 0.0,
        "yield_per_mm": 0.0,
        "n": float(n),
    }


def icg_absorption_per_yield():
    """Absorption ICG adds per unit fluorescence yield, at excitation and at
    emission: (d mua_x / d yield, d mua_m / d yield), dimensionless.

    Yield = eta * mua_f_x, so 1 /mm of yield is 1 / (eta * mua_f_x per ug/mL)
    ug/mL of ICG; the table's slopes give what that concentration absorbs
    (about 25 at 780 nm and 7.3 at 830 nm).  A reconstruction uses these to
    feed a target's own absorption back into its forward model.
    """
    lo, hi = ICG_TABLE[0.0], ICG_TABLE[2.0]
    per_conc = [(hi[i] - lo[i]) / 2.0 for i in range(5)]   # per ug/mL
    conc_per_yield = 1.0 / (ICG_QUANTUM_YIELD * per_conc[2])
    return per_conc[0] * conc_per_yield, per_conc[3] * conc_per_yield


def without_icg(optics_by_label):
    """Each label's optics with its ICG's absorption taken out: ``{label:
    (mua_x_per_mm, musp_x_per_mm, mua_m_per_mm, musp_m_per_mm)}`` from dicts as
    :func:`icg_liquid_optics` makes them (their ``yield_per_mm`` times ICG's
    absorption per unit yield removed), the tissue a reconstruction's optics
    describe; it adds the dye back from the yield."""
    per_x, per_m = icg_absorption_per_yield()
    out = {}
    for k, o in optics_by_label.items():
        y = float(o.get("yield_per_mm", 0.0))
        out[k] = (float(o["mua_x_per_mm"]) - per_x * y, float(o["musp_x_per_mm"]),
                  float(o["mua_m_per_mm"]) - per_m * y, float(o["musp_m_per_mm"]))
    return out
