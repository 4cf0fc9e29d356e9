"""Digital phantoms: synthetic intraoperative CBCT, label map and optical truth.

Three phantoms from the thesis's experiments, each an MRML scene with

- ``CBCT``: scalar volume, HU-like int16, 0.8 mm voxels, partial-volume edges,
  a CBCT-like blur and noise;
- ``CBCTLabels``: label map (0 = air, 1.. = materials) whose region volumes
  match the analytic shapes (volume-preserving voxelisation, see voxelize.py);
- ground truth as ``truth.json`` beside the scene and as the JSON attribute
  ``FluoGuide.Truth`` of ``CBCTLabels``: geometry, analytic and label-map
  volumes, and optical properties per region at excitation and emission;
- ``optics.json`` beside the scene: the same optics as the tomography commands
  read them (docs/tomography-own-scene.md), without the ICG each region holds,
  so ``fluo tomo simulate / record-scan / reconstruct`` run on the phantom
  with ``--yield`` taken from ``truth.json``.

Frame: RAS mm, the tissue's top surface at z = 0 (camera side, +S up), the
phantom centred on x = y = 0.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage

from fluoguide import atomic
from fluoguide.errors import FluoInputError, seeded_rng
from fluoguide.optics_table import icg_liquid_optics, non_fluorescent_optics
from fluoguide.voxelize import voxelize

HU = {"air": -1000.0, "water": 0.0, "agar": 20.0, "polyurethane": 110.0,
      "icg_tube": 150.0, "tongue": 70.0}


@dataclass
class Phantom:
    """A digital phantom in memory (arrays indexed [k, j, i] = [z, y, x])."""

    name: str
    cbct_hu: np.ndarray
    labels: np.ndarray
    spacing_mm: np.ndarray
    origin_mm: np.ndarray
    region_names: dict
    optics: dict
    analytic_volumes_mm3: dict
    geometry: dict
    params: dict = field(default_factory=dict)

    def labelmap_volumes_mm3(self):
        vox = float(np.prod(self.spacing_mm))
        counts = np.bincount(self.labels.ravel(), minlength=max(self.region_names) + 1)
        return {int(k): float(counts[k] * vox) for k in self.region_names if k != 0}

    def optics_file(self):
        """The phantom's ``optics.json`` (a new dict): each region's
        coefficients with its ICG's absorption taken out (the commands add
        it back from the yield, by ICG's absorption per unit yield), the
        names, the one refractive index and ``fluorophore`` ICG when a
        region holds it.  Values rounded to 12 significant digits (the
        subtraction's last bits are noise)."""
        from fluoguide.optics_table import without_icg

        def r(v):
            return float(f"{v:.12g}")

        base = without_icg(self.optics)
        n = {float(o["n"]) for o in self.optics.values()}
        if len(n) != 1:   # every phantom is one medium; the file holds one index
            raise ValueError(f"phantom {self.name}: regions differ in refractive index {n}")
        return {"n": n.pop(),
                "excitation": {str(k): {"mua_per_mm": r(v[0]), "musp_per_mm": r(v[1])}
                               for k, v in base.items()},
                "emission": {str(k): {"mua_per_mm": r(v[2]), "musp_per_mm": r(v[3])}
                             for k, v in base.items()},
                "fluorophore": "ICG" if self.yields_per_mm() else None,
                "names": {str(k): v for k, v in self.region_names.items() if k != 0},
                "comment": f"{self.name} phantom: optics without the ICG of each region; "
                           "its yields are truth.json's regions[..].optics.yield_per_mm"}

    def yields_per_mm(self):
        """True fluorescence yield eta * mua_f [1/mm] per fluorescent label."""
        return {int(k): float(o["yield_per_mm"]) for k, o in self.optics.items()
                if float(o["yield_per_mm"]) > 0}

    def truth(self):
        lab_vol = self.labelmap_volumes_mm3()
        regions = {}
        for k, name in self.region_names.items():
            if k == 0:
                continue
            a = self.analytic_volumes_mm3[k]
            regions[str(k)] = {
                "name": name,
                "analytic_volume_mm3": a,
                "labelmap_volume_mm3": lab_vol[k],
                "volume_error_pct": 100.0 * (lab_vol[k] - a) / a,
                "optics": self.optics[k],
            }
        return {
            "phantom": self.name,
            "frame": "RAS mm; tissue top surface at z = 0, +z towards the camera",
            "voxel_mm": self.spacing_mm.tolist(),
            "shape_kji": list(self.labels.shape),
            "origin_mm": self.origin_mm.tolist(),
            "regions": regions,
            "geometry": self.geometry,
            "params": self.params,
        }


def _grid(lo, hi, voxel_mm):
    """Shape (K, J, I) and origin of an axis-aligned grid covering [lo, hi]."""
    lo = np.asarray(lo, float)
    hi = np.asarray(hi, float)
    n = np.ceil((hi - lo) / voxel_mm).astype(int)
    origin = lo + 0.5 * voxel_mm  # voxel centres
    return (int(n[2]), int(n[1]), int(n[0])), origin


def _render_cbct(labels, fractions, hu_by_label, spacing, rng, noise_hu=15.0, blur_mm=0.4):
    """HU image from partial-volume fractions, blurred and with noise (int16)."""
    img = np.zeros(labels.shape, dtype=np.float32)
    for lab, frac in fractions.items():
        img += frac * np.float32(hu_by_label[lab])
    sigma = [blur_mm / s for s in spacing[::-1]]
    img = ndimage.gaussian_filter(img, sigma)
    img += rng.normal(0.0, noise_hu, img.shape).astype(np.float32)
    return np.clip(np.round(img), -1024, 3071).astype(np.int16)


#: the peak memory a phantom adds per voxel of its grid [bytes]: voxel-centre
#: coordinates (float64), the partial-volume fractions and their stack (float32
#: per label), the blurred, noisy CBCT (float32 and float64 noise), the scene's
#: copies. Measured (``fluo phantom``, /usr/bin/time -v, peak less the 0.32 GB
#: of imports; the three phantoms at 0.4 to 0.2 mm, 3 to 29 million voxels):
#: 44-70 B per voxel, the most on the finest grids; 80 B is 1.14-1.24x the
#: measured peak at 0.3 mm and finer, up to 1.8x at 0.4 mm (docs/reliability.md,
#: "Memory estimates")
PHANTOM_BYTES_PER_VOXEL = 80.0


def _check_memory(name, shape, voxel_mm):
    """Refuse a phantom grid whose estimated peak does not fit (before any work)."""
    from fluoguide.memory import GB, available_bytes, check_fits

    voxels = float(np.prod(shape))
    need = PHANTOM_BYTES_PER_VOXEL * voxels
    avail = available_bytes()
    hint = "use a larger --voxel-mm"
    if avail:
        # the voxel count goes as 1/voxel^3: the smallest size that fits, to 0.05 mm
        v_fit = np.ceil(voxel_mm * (need / avail) ** (1 / 3) / 0.05) * 0.05
        hint = (f"use --voxel-mm {v_fit:.2f} or more (about "
                f"{need * (voxel_mm / v_fit) ** 3 / GB:.1f} GB)")
    check_fits(need, f"the {name} phantom at {voxel_mm:g} mm ({voxels / 1e6:.0f} million "
               "voxels)", hint, field="voxel_mm", value=voxel_mm)


def _check_voxel(voxel_mm):
    v = float(voxel_mm)
    if not (0.1 <= v <= 5.0):
        raise FluoInputError("voxel size must be within 0.1..5 mm", field="voxel_mm", value=v)
    return v


def slab(voxel_mm=0.8, seed=0):
    """The 11 x 11 x 6 cm polyurethane calibration slab (mua 0.005, musp 0.89, n 1.52)."""
    v = _check_voxel(voxel_mm)
    a, b, h = 110.0, 110.0, 60.0
    margin = 4 * v
    shape, origin = _grid((-a / 2 - margin, -b / 2 - margin, -h - margin),
                          (a / 2 + margin, b / 2 + margin, margin), v)
    _check_memory("slab", shape, v)

    def inside(x, y, z):
        return (np.abs(x) <= a / 2) & (np.abs(y) <= b / 2) & (z <= 0) & (z >= -h)

    vols = {1: a * b * h}
    labels, fr = voxelize([(1, inside)], shape, (v, v, v), origin, vols)
    rng = seeded_rng(seed)
    cbct = _render_cbct(labels, fr, {0: HU["air"], 1: HU["polyurethane"]}, (v, v, v), rng)
    return Phantom("slab", cbct, labels, np.array([v, v, v]), origin,
                   {0: "air", 1: "polyurethane"},
                   {1: non_fluorescent_optics(0.005, 0.89, 1.52)}, vols,
                   {"size_mm": [a, b, h], "top_z_mm": 0.0}, {"voxel_mm": v, "seed": seed})


def _tube_in_cylinder_volume(R, r):
    """Volume [mm^3] of a radius-r tube along x through a radius-R cylinder's axis,
    clipped by the cylinder wall: integral over the tube disc of the chord 2 sqrt(R^2 - y^2)."""
    # Gauss-Legendre in polar coordinates over the tube's cross-section disc.
    xs, ws = np.polynomial.legendre.leggauss(64)
    rho = 0.5 * r * (xs + 1)
    wr = 0.5 * r * ws
    th = np.pi * (xs + 1)
    wt = np.pi * ws
    RHO, TH = np.meshgrid(rho, th, indexing="ij")
    y = RHO * np.cos(TH)
    integrand = 2 * np.sqrt(R * R - y * y) * RHO
    return float(np.einsum("i,j,ij->", wr, wt, integrand))


def cylinder_tube(voxel_mm=0.8, seed=0, depth_mm=4.7, tube_diameter_mm=2.4,
                  tube_icg_ug_per_ml=2.0, background_icg_ug_per_ml=0.0):
    """9 cm liquid cylinder, 2 cm deep, with an ICG tube at a chosen depth.

    The tube runs along x through the cylinder's axis (y = 0); ``depth_mm`` is
    the distance from the liquid surface (z = 0) to the tube's axis, as the
    thesis's phantom experiment varied it from 2.7 to 6.7 mm.
    """
    v = _check_voxel(voxel_mm)
    R, H = 45.0, 20.0
    r = 0.5 * float(tube_diameter_mm)
    d = float(depth_mm)
    if not (r > 0 and r < 10):
        raise FluoInputError("tube diameter must be within 0..20 mm", field="tube_diameter_mm",
                             value=tube_diameter_mm)
    if d - r < 0.5 or d + r > H - 0.5:
        raise FluoInputError(f"tube must lie inside the {H:g} mm deep liquid "
                             f"(0.5 mm clearance)", field="depth_mm", value=d)
    margin = 4 * v
    shape, origin = _grid((-R - margin, -R - margin, -H - margin), (R + margin, R + margin, margin), v)
    _check_memory("cylinder-tube", shape, v)

    def liquid(x, y, z):
        return (x * x + y * y <= R * R) & (z <= 0) & (z >= -H)

    def tube(x, y, z):
        return liquid(x, y, z) & (y * y + (z + d) ** 2 <= r * r)

    v_tube = _tube_in_cylinder_volume(R, r)
    vols = {1: np.pi * R * R * H - v_tube, 2: v_tube}
    labels, fr = voxelize([(1, liquid), (2, tube)], shape, (v, v, v), origin, vols)
    rng = seeded_rng(seed)
    cbct = _render_cbct(labels, fr, {0: HU["air"], 1: HU["water"], 2: HU["icg_tube"]}, (v, v, v), rng)
    optics = {1: icg_liquid_optics(background_icg_ug_per_ml),
              2: icg_liquid_optics(tube_icg_ug_per_ml)}
    geometry = {"cylinder_radius_mm": R, "liquid_depth_mm": H, "tube_axis": [1.0, 0.0, 0.0],
                "tube_centre_mm": [0.0, 0.0, -d], "tube_radius_mm": r, "tube_depth_mm": d,
                "top_z_mm": 0.0}
    return Phantom("cylinder-tube", cbct, labels, np.array([v, v, v]), origin,
                   {0: "air", 1: "liquid", 2: "icg_tube"}, optics, vols, geometry,
                   {"voxel_mm": v, "seed": seed, "depth_mm": d, "tube_diameter_mm": 2 * r,
                    "tube_icg_ug_per_ml": tube_icg_ug_per_ml,
                    "background_icg_ug_per_ml": background_icg_ug_per_ml})


def _half_ellipsoid_overlap(cav, tng, n=801):
    """Volume [mm^3] of (tongue ellipsoid) intersect (cavity half-ellipsoid, z <= 0),
    by 2D quadrature over x, y of the overlap of their z-intervals (exact in z)."""
    (ca, cb, cc), (tc, (ta, tb, tcz)) = cav, tng
    x = np.linspace(tc[0] - ta, tc[0] + ta, n)
    y = np.linspace(tc[1] - tb, tc[1] + tb, n)
    X, Y = np.meshgrid(x, y, indexing="ij")
    qt = 1 - ((X - tc[0]) / ta) ** 2 - ((Y - tc[1]) / tb) ** 2
    qc = 1 - (X / ca) ** 2 - (Y / cb) ** 2
    ok = (qt > 0) & (qc > 0)
    ht = tcz * np.sqrt(np.where(ok, qt, 0))
    hc = cc * np.sqrt(np.where(ok, qc, 0))
    lo = np.maximum(tc[2] - ht, -hc)
    hi = np.minimum(tc[2] + ht, 0.0)
    length = np.where(ok, np.clip(hi - lo, 0, None), 0.0)
    return float(np.trapezoid(np.trapezoid(length, y, axis=1), x))


def oral_cavity(voxel_mm=0.8, seed=0, tissue_icg_ug_per_ml=0.4, tongue_icg_ug_per_ml=2.0):
    """A mouth-like cavity in an agar block with a tongue-like fluorescent inclusion.

    Agar block 70 x 60 x 50 mm (top at z = 0); the cavity is the lower half of
    an ellipsoid (semi-axes 25, 20, 25 mm) opening at the top face, so its
    walls curve away from a camera looking down into it; the tongue is an
    ellipsoid (12, 15, 8 mm) resting on the cavity floor, half of it
    protruding into the cavity.  The agar holds a low ICG level (homogeneous
    fluorescence for surface-mapping tests); the tongue a higher one.
    """
    v = _check_voxel(voxel_mm)
    bx, by, bz = 70.0, 60.0, 50.0
    cav = (25.0, 20.0, 25.0)
    t_centre = (0.0, 4.0, -24.0)
    t_axes = (12.0, 15.0, 8.0)
    margin = 4 * v
    shape, origin = _grid((-bx / 2 - margin, -by / 2 - margin, -bz - margin),
                          (bx / 2 + margin, by / 2 + margin, margin), v)
    _check_memory("oral-cavity", shape, v)

    def block(x, y, z):
        return (np.abs(x) <= bx / 2) & (np.abs(y) <= by / 2) & (z <= 0) & (z >= -bz)

    def cavity(x, y, z):
        return (z <= 0) & ((x / cav[0]) ** 2 + (y / cav[1]) ** 2 + (z / cav[2]) ** 2 <= 1)

    def tissue(x, y, z):
        return block(x, y, z) & ~cavity(x, y, z)

    def tongue(x, y, z):
        return (((x - t_centre[0]) / t_axes[0]) ** 2 + ((y - t_centre[1]) / t_axes[1]) ** 2
                + ((z - t_centre[2]) / t_axes[2]) ** 2) <= 1

    v_block = bx * by * bz
    v_cav = 2.0 / 3.0 * np.pi * cav[0] * cav[1] * cav[2]
    v_tongue = 4.0 / 3.0 * np.pi * t_axes[0] * t_axes[1] * t_axes[2]
    v_overlap = _half_ellipsoid_overlap(cav, (t_centre, t_axes))
    vols = {1: v_block - v_cav - (v_tongue - v_overlap), 2: v_tongue}
    labels, fr = voxelize([(1, tissue), (2, tongue)], shape, (v, v, v), origin, vols)
    rng = seeded_rng(seed)
    cbct = _render_cbct(labels, fr, {0: HU["air"], 1: HU["agar"], 2: HU["tongue"]}, (v, v, v), rng)
    optics = {1: icg_liquid_optics(tissue_icg_ug_per_ml, base_mua_x=0.003, base_mua_m=0.003),
              2: icg_liquid_optics(tongue_icg_ug_per_ml, base_mua_x=0.003, base_mua_m=0.003)}
    geometry = {"block_mm": [bx, by, bz], "cavity_semi_axes_mm": list(cav),
                "cavity_centre_mm": [0.0, 0.0, 0.0], "tongue_centre_mm": list(t_centre),
                "tongue_semi_axes_mm": list(t_axes), "top_z_mm": 0.0}
    return Phantom("oral-cavity", cbct, labels, np.array([v, v, v]), origin,
                   {0: "air", 1: "agar", 2: "tongue"}, optics, vols, geometry,
                   {"voxel_mm": v, "seed": seed, "tissue_icg_ug_per_ml": tissue_icg_ug_per_ml,
                    "tongue_icg_ug_per_ml": tongue_icg_ug_per_ml})


PHANTOMS = {"slab": slab, "cylinder-tube": cylinder_tube, "oral-cavity": oral_cavity}


def make_phantom(name, **params):
    """Build phantom ``name`` (one of PHANTOMS) with keyword parameters."""
    if name not in PHANTOMS:
        raise FluoInputError(f"unknown phantom; choose one of {', '.join(PHANTOMS)}",
                             field="phantom", value=name)
    for key, value in params.items():
        if key == "seed":
            if not isinstance(value, (int, np.integer)) or not 0 <= value < 2**32:
                raise FluoInputError("seed must be an integer within 0..2**32-1", field="seed",
                                     value=value)
        elif isinstance(value, (int, float, np.number)) and not np.isfinite(value):
            # NaN slips through every range check (all comparisons are False)
            raise FluoInputError("must be a finite number", field=key, value=float(value))
    return PHANTOMS[name](**params)


def add_phantom_to_scene(scene, phantom):
    """Add ``CBCT`` and ``CBCTLabels`` nodes (with the truth attribute) to a scene."""
    from fluoguide import mrml_io

    vol = mrml_io.add_volume(scene, "CBCT", phantom.cbct_hu, phantom.spacing_mm, phantom.origin_mm)
    vol.SetAttribute("FluoGuide.Phantom", phantom.name)
    lab = mrml_io.add_volume(scene, "CBCTLabels", phantom.labels, phantom.spacing_mm,
                             phantom.origin_mm, labelmap=True)
    lab.SetAttribute("FluoGuide.Phantom", phantom.name)
    mrml_io.set_json_attribute(lab, "FluoGuide.Truth", phantom.truth())
    return vol, lab


def write_phantom(phantom, out_dir):
    """Write ``out_dir/scene.mrml`` (+ NRRD files), ``out_dir/truth.json`` and
    ``out_dir/optics.json`` (:meth:`Phantom.optics_file`).

    Everything is written into a staging folder and moved in as one journaled
    transaction (``fluoguide.atomic``): a failure or a kill leaves the old
    phantom or the new one, never a mix.
    Returns the scene path.
    """
    from fluoguide import mrml_io

    out_dir = Path(out_dir).resolve()
    with atomic.staged_folder(out_dir, last=("truth.json", "scene.mrml")) as tmp:
        scene = mrml_io.new_scene()
        add_phantom_to_scene(scene, phantom)
        mrml_io.save_scene(scene, tmp / "scene.mrml")
        (tmp / "truth.json").write_text(json.dumps(phantom.truth(), indent=2, allow_nan=False))
        (tmp / "optics.json").write_text(json.dumps(phantom.optics_file(), indent=2,
                                                    allow_nan=False))
    return out_dir / "scene.mrml"


def ellipsoid_inclusion_optics():
    """optics.json of :func:`ellipsoid_inclusion_labelmap`'s labels (a new dict):
    body 3 and inclusion 7 at n 1.37, with ICG's absorption per unit yield
    (docs/tomography-own-scene.md)."""
    return {"n": 1.37,
            "excitation": {"3": {"mua_per_mm": 0.01, "musp_per_mm": 1.0},
                           "7": {"mua_per_mm": 0.012, "musp_per_mm": 1.1}},
            "emission": {"3": {"mua_per_mm": 0.008, "musp_per_mm": 0.9},
                         "7": {"mua_per_mm": 0.01, "musp_per_mm": 1.0}},
            "fluorophore": "ICG"}


def ellipsoid_inclusion_labelmap(spacing_mm=(0.5, 0.6, 0.7), direction=((-1, 0, 0), (0, -1, 0),
                                                                       (0, 0, 1)),
                                 origin_mm=(120.0, -80.0, 340.0), semi_axes_mm=(28.0, 22.0, 14.0),
                                 inclusion_diameter_mm=6.0, inclusion_gap_mm=4.0,
                                 inclusion_offset_mm=(3.0, -2.0), body_label=3,
                                 inclusion_label=7):
    """A label map unlike the cylinder tube: an ellipsoidal body with a spherical
    inclusion ``inclusion_gap_mm`` below its curved top surface, on an
    anisotropic grid with any IJK-to-RAS direction and origin.

    Geometry in the label map's own frame (x along I, y along J, z along K, the
    body centred in the volume, +z up): the inclusion sits under the surface
    point above (``inclusion_offset_mm`` in x, y from the body's centre), its
    top ``inclusion_gap_mm`` below that point.  Labels: 0 air,
    ``body_label``, ``inclusion_label`` (not 1 and 2: any labels work).
    Voxels are labelled by their centre.

    Returns a dict: ``labels_kji``, ``spacing_mm``, ``origin_mm``,
    ``direction``, ``inclusion_centre_ras_mm``, ``inclusion_radius_mm``,
    ``surface_point_ras_mm`` (the surface above the inclusion), labels.
    """
    sp = np.asarray(spacing_mm, float)
    d = np.asarray(direction, float)
    o = np.asarray(origin_mm, float)
    a = np.asarray(semi_axes_mm, float)
    margin = 2.0
    shape_ijk = np.ceil((2 * a + 2 * margin) / sp).astype(int) + 1
    centre = 0.5 * (shape_ijk - 1) * sp
    k, j, i = np.indices(shape_ijk[::-1])
    p = np.stack([i * sp[0], j * sp[1], k * sp[2]], axis=-1) - centre
    body = np.einsum("...k,...k->...", p / a, p / a) <= 1.0
    ox, oy = inclusion_offset_mm
    top = a[2] * np.sqrt(max(0.0, 1.0 - (ox / a[0]) ** 2 - (oy / a[1]) ** 2))
    r = 0.5 * float(inclusion_diameter_mm)
    c_inc = np.array([ox, oy, top - inclusion_gap_mm - r])
    inc = body & (np.linalg.norm(p - c_inc, axis=-1) <= r)
    labels = np.zeros(shape_ijk[::-1], np.uint8)
    labels[body] = body_label
    labels[inc] = inclusion_label

    def to_ras(q_local):
        return o + d @ (np.asarray(q_local, float) + centre)

    return {"labels_kji": labels, "spacing_mm": sp, "origin_mm": o, "direction": d,
            "inclusion_centre_ras_mm": to_ras(c_inc), "inclusion_radius_mm": r,
            "surface_point_ras_mm": to_ras([ox, oy, top]), "body_label": body_label,
            "inclusion_label": inclusion_label}
