"""A seeded family of label-map scenes with their truth (issue #31): the proving
ground of the label-map tomography, scenes nobody tuned for.

Each scene is drawn from ``numpy.random.default_rng(seed)``: a body (an
ellipsoid from nearly spherical to a flat-topped dome, or a slab-like block
with a domed top), one to three inclusions (spheres and ellipsoids of 2.5-8 mm
at 1-7 mm under the skin, off the body's axis), anisotropic voxels of
0.5-1.0 mm, an RAS, LPS or oblique IJK-to-RAS direction and an origin far
from zero, optical properties across the near-infrared tissue range, the
inclusions' yield with dye in the background in some scenes (contrast 20:1 to
1000:1), and relative noise of 0.5-5 %. Its segmentation variant
(``segmentation_error_mm``) keeps the truth and hands the reconstruction a label
map whose inclusions are dilated, eroded or shifted by about a millimetre, as a
CBCT segmentation would be.

The data are never made by the reconstruction's model: :func:`simulate` runs
the FEM on the whole label map at the ``fine`` level (its own, finer mesh);
``fluoguide``'s Monte Carlo engine can stand in for it (``engine="mc"``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: labels of the family's maps: the body, the inclusions (1..3 of them)
BODY_LABEL = 3
INCLUSION_LABELS = (7, 8, 9)
#: the relative noise of the data [%] is drawn in [NOISE_PCT[0], NOISE_PCT[1]]
NOISE_PCT = (0.5, 5.0)


@dataclass
class Scene:
    """One scene of the family and its truth.

    Attributes
    ----------
    seed : the scene's seed (the whole scene follows from it)
    labels_kji : (K, J, I) uint8, the true label map
    spacing_mm, origin_mm, direction : its geometry (IJK to RAS)
    optics : the optics document (optics.json's dict)
    yield_by_label : {label: true yield [1/mm]} (the body's is its background dye)
    noise_pct : the data's relative noise [%]
    inclusions : one dict per inclusion: ``label``, ``shape``, ``centre_ras_mm``,
        ``radii_mm``, ``depth_mm`` (skin to its top)
    description : one line a person can read
    segmentation : "true", or what was done to the label map handed over
        (``recon_labels_kji``)
    recon_labels_kji : the label map the reconstruction is given
    """

    seed: int
    labels_kji: np.ndarray
    spacing_mm: np.ndarray
    origin_mm: np.ndarray
    direction: np.ndarray
    optics: dict
    yield_by_label: dict
    noise_pct: float
    inclusions: list
    description: str
    segmentation: str = "true"
    recon_labels_kji: np.ndarray = field(default=None, repr=False)

    def labelmap(self, recon=True):
        """The scene's LabelMap: the one handed to the reconstruction (``recon``)
        or the truth."""
        from FluoTomoLib.tomography import LabelMap

        lab = self.recon_labels_kji if recon and self.recon_labels_kji is not None \
            else self.labels_kji
        return LabelMap(lab, self.spacing_mm, self.origin_mm, self.direction)

    def target(self):
        """The first (shallowest drawn) inclusion's label: the reconstruction's
        target (meshed finely; the default scan covers every inclusion)."""
        return int(self.inclusions[0]["label"])


def _rotation(rng, kind):
    if kind == "RAS":
        return np.eye(3)
    if kind == "LPS":
        return np.diag([-1.0, -1.0, 1.0])
    # oblique: a rotation about a random axis by 15-40 degrees (the body stays
    # "up" along its own K axis; the RAS frame is what is oblique)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    ang = np.deg2rad(rng.uniform(15.0, 40.0))
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K


def _optics(rng):
    """Body and inclusion optics in the near-infrared tissue range [1/mm]."""
    mua = rng.uniform(0.004, 0.03)
    musp = rng.uniform(0.6, 1.6)

    def entry(f_mua, f_musp):
        return {"mua_per_mm": round(float(mua * f_mua), 5),
                "musp_per_mm": round(float(musp * f_musp), 4)}

    ex = {str(BODY_LABEL): entry(1.0, 1.0)}
    em = {str(BODY_LABEL): entry(0.8, 0.9)}
    for lab in INCLUSION_LABELS:
        f1, f2 = rng.uniform(0.8, 1.3), rng.uniform(0.85, 1.2)
        ex[str(lab)] = entry(f1, f2)
        em[str(lab)] = entry(0.8 * f1, 0.9 * f2)
    return {"n": round(float(rng.uniform(1.33, 1.45)), 3), "excitation": ex, "emission": em,
            "fluorophore": "ICG"}


def make_scene(seed, inclusions=None, segmentation_error_mm=0.0, body=None):
    """Scene number ``seed`` of the family.

    Parameters
    ----------
    seed : int, the scene (everything is drawn from it)
    inclusions : 1..3, or None to draw it (one in 60 %, two in 30 %, three in 10 %)
    segmentation_error_mm : 0, or the size [mm] of the segmentation error handed
        to the reconstruction: the inclusions dilated, eroded or shifted by it
        (drawn per scene)
    body : "ellipsoid", "dome" or None to draw it
    """

    rng = np.random.default_rng([31, int(seed)])
    body = body or str(rng.choice(["ellipsoid", "dome"], p=[0.6, 0.4]))
    n_inc = inclusions or int(rng.choice([1, 2, 3], p=[0.6, 0.3, 0.1]))
    spacing = np.round(rng.uniform(0.5, 1.0, 3), 2)
    if body == "ellipsoid":
        semi = np.array([rng.uniform(12, 18), rng.uniform(10, 14), rng.uniform(7, 10)])
    else:                       # wide and flat: a slab-like block with a domed top
        semi = np.array([rng.uniform(15, 20), rng.uniform(12, 16), rng.uniform(5, 8)])
    margin = 2.0
    shape_ijk = np.ceil((2 * semi + 2 * margin) / spacing).astype(int) + 1
    centre = 0.5 * (shape_ijk - 1) * spacing
    k, j, i = np.indices(shape_ijk[::-1])
    p = np.stack([i * spacing[0], j * spacing[1], k * spacing[2]], axis=-1) - centre
    if body == "ellipsoid":
        inside = np.einsum("...k,...k->...", p / semi, p / semi) <= 1.0
    else:
        # a block of depth semi_z below z = 0 with an elliptic dome of height
        # semi_z / 2 on top, its corners rounded
        r2 = (p[..., 0] / semi[0]) ** 2 + (p[..., 1] / semi[1]) ** 2
        top = 0.5 * semi[2] * np.sqrt(np.clip(1 - r2, 0, None))
        inside = (r2 <= 1.0) & (p[..., 2] >= -semi[2]) & (p[..., 2] <= top)

    def skin_z(x, y):
        """Height of the skin above (x, y) in the local frame."""
        r2 = (x / semi[0]) ** 2 + (y / semi[1]) ** 2
        if body == "ellipsoid":
            return semi[2] * np.sqrt(max(0.0, 1 - r2))
        return 0.5 * semi[2] * np.sqrt(max(0.0, 1 - r2))

    labels = np.zeros(shape_ijk[::-1], np.uint8)
    labels[inside] = BODY_LABEL
    incs = []
    masks = []
    placed = []
    for n in range(n_inc):
        lab = INCLUSION_LABELS[n]
        for _ in range(200):
            shape = str(rng.choice(["sphere", "ellipsoid"]))
            d = rng.uniform(2.5, 8.0)
            radii = np.full(3, d / 2) if shape == "sphere" else \
                np.array([d / 2, d / 2 * rng.uniform(0.6, 1.0), d / 2 * rng.uniform(0.5, 0.9)])
            # off the body's axis: up to 45 % of the semi-axes in x and y
            ox, oy = rng.uniform(-0.45, 0.45) * semi[0], rng.uniform(-0.45, 0.45) * semi[1]
            depth = rng.uniform(1.0, 7.0 if n_inc == 1 else 5.0)
            cz = skin_z(ox, oy) - depth - radii[2]
            c = np.array([ox, oy, cz])
            floor = -semi[2] + 1.5 + radii[2] if body == "dome" else -semi[2] * 0.7
            if cz < floor:
                continue
            # apart from the others by at least 3 mm between their edges
            if any(np.linalg.norm(c - q) < r + radii.max() + 3.0 for q, r in placed):
                continue
            m = inside & (np.einsum("...k,...k->...", (p - c) / radii, (p - c) / radii) <= 1.0)
            if m.sum() < 8:
                continue
            break
        else:
            continue
        placed.append((c, radii.max()))
        labels[m] = lab
        masks.append((lab, m))
        incs.append({"label": lab, "shape": shape, "radii_mm": radii.round(3).tolist(),
                     "depth_mm": round(float(depth), 3), "centre_local_mm": c})
    kind = str(rng.choice(["RAS", "LPS", "oblique"], p=[0.3, 0.3, 0.4]))
    direction = _rotation(rng, kind)
    origin = rng.uniform(-300, 300, 3).round(1)
    for inc in incs:
        c = inc.pop("centre_local_mm")
        inc["centre_ras_mm"] = (origin + direction @ (c + centre)).tolist()
    optics = _optics(rng)
    y_inc = rng.uniform(1e-3, 5e-3)
    yields = {}
    for inc in incs:
        yields[inc["label"]] = float(y_inc * (1.0 if inc is incs[0] else rng.uniform(0.3, 1.5)))
    contrast = None
    if rng.random() < 0.3:
        contrast = float(rng.choice([20.0, 100.0, 1000.0]))
        yields[BODY_LABEL] = float(y_inc / contrast)
    noise = float(np.round(np.exp(rng.uniform(np.log(NOISE_PCT[0]), np.log(NOISE_PCT[1]))), 2))
    used = {str(BODY_LABEL)} | {str(inc["label"]) for inc in incs}
    for table in ("excitation", "emission"):
        optics[table] = {k: v for k, v in optics[table].items() if k in used}
    desc = (f"{body} {2 * semi[0]:.0f}x{2 * semi[1]:.0f}x{2 * semi[2]:.0f} mm, "
            f"{len(incs)} inclusion(s) " + ", ".join(
                f"{i['shape']} {2 * max(i['radii_mm']):.1f} mm at {i['depth_mm']:.1f} mm"
                for i in incs)
            + f"; voxels {spacing.tolist()} mm, {kind}; noise {noise:g} %"
            + (f"; background dye 1:{contrast:g}" if contrast else ""))
    sc = Scene(int(seed), labels, spacing, origin, direction, optics, yields, noise, incs, desc)
    if segmentation_error_mm:
        sc.recon_labels_kji, sc.segmentation = _segmentation_error(
            labels, masks, spacing, float(segmentation_error_mm), rng)
    return sc


def _segmentation_error(labels, masks, spacing, mm, rng):
    """The label map a segmentation ``mm`` off would hand over: each inclusion
    dilated or eroded by ``mm`` (a distance transform in mm, anisotropic voxels
    included) or shifted by ``mm`` along a random direction (inside the body)."""
    from scipy import ndimage

    out = labels.copy()
    what = str(rng.choice(["dilated", "eroded", "shifted"]))
    body = labels > 0
    for lab, m in masks:
        out[m] = BODY_LABEL
        if what == "dilated":
            d = ndimage.distance_transform_edt(~m, sampling=spacing[::-1])
            new = (d <= mm) & body
        elif what == "eroded":
            d = ndimage.distance_transform_edt(m, sampling=spacing[::-1])
            new = d > mm
            if new.sum() < 4:               # a segmentation keeps something
                new = d >= d.max()
        else:
            v = rng.normal(size=3)
            v *= mm / np.linalg.norm(v)
            shift = np.round(v[::-1] / spacing[::-1]).astype(int)
            new = np.roll(m, tuple(shift), axis=(0, 1, 2)) & body
        out[new] = lab
    return out, f"{what} {mm:g} mm"


def simulate(scene, engine="fem", accuracy="fine", photons=None, sources_ras=None,
             detectors_ras=None, seed=None):
    """The scene's acquisition (the default scan: a patch over each inclusion, or the
    ``sources_ras`` and ``detectors_ras`` given, RAS mm, e.g. a planned scan),
    simulated on the TRUE label map with the engine's own mesh and the scene's noise
    (its seed, or ``seed``). Returns (Acquisition, info)."""
    from FluoTomoLib.tomography import optics_from_dict, simulate_acquisition

    lm = scene.labelmap(recon=False)
    optics = optics_from_dict(scene.optics)
    kw = {} if photons is None else {"photons": photons}
    return simulate_acquisition(lm, optics, scene.yield_by_label, sources_ras, detectors_ras,
                                noise_pct=scene.noise_pct,
                                seed=scene.seed if seed is None else int(seed),
                                engine=engine, accuracy=accuracy,
                                target=scene.target(), **kw)
