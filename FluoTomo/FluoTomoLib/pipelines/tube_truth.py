"""The cylinder-tube cases' ground truth: what the true phantom sends to the camera.

The tube study (:mod:`FluoTomoLib.pipelines.tube`) grades its reconstructions on
data simulated by an independent, finer model: the whole phantom on its own
graded mesh (0.8 mm at the laser raster and the tube, 1.5 mm elsewhere; about
300k nodes), with the analytic tube's optics, never the reconstruction's mesh
or label map.  All the camera needs from it is the emission field on the
surface it films (the top of the liquid), one column per laser position:
:class:`SurfaceTruth`.

That simulation is most of a laptop's budget for a case (a few GB for its
factorisations), and it never changes for a depth.  So the demo's depths are
stored here, in ``data/tube_truth/depth_<d>mm.npz``, made by the command of
:func:`regenerate_command`; a case reads its depth's set when the case's
simulation options are the stored ones (:data:`STORED_OPTIONS`) and simulates
otherwise, and says which it did.  The noise (tracking, shot and read noise)
is drawn per case from its seed either way.  ``test_tube_truth.py`` reruns one
depth and compares it with the stored set.
"""

from __future__ import annotations

import json
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fluoguide.errors import FluoInputError
from fluoguide.progress import check_cancel, report, scaled

STORE = Path(__file__).resolve().parent / "data" / "tube_truth"
#: the simulation options of the stored sets (``simulate_and_reconstruct``'s defaults)
STORED_OPTIONS = {"fine_mm": 0.8, "simulate_coarse_mm": 1.5, "n_sources": 16,
                  "source_spacing_mm": 2.5}
#: layout version of a stored set (2: the tube's optics by the nodes' shares of it;
#: sets of 1 sampled them at the nodes, +13 % dye at 4.7 mm, and are refused)
FORMAT = 2
#: the phantom's parameters a set is made for (``fluoguide.phantoms.cylinder_tube``'s
#: but the seed, which only draws the CBCT's noise): another phantom simulates
PHANTOM_KEYS = ("voxel_mm", "tube_diameter_mm", "tube_icg_ug_per_ml",
                "background_icg_ug_per_ml")
#: the stored fields are float32 (a quarter of the disk); their rounding,
#: 6e-8 relative, is far below the frames' shot noise
FIELD_DTYPE = np.float32


@dataclass
class SurfaceTruth:
    """The emission fields of the true phantom on the surface the camera films.

    Attributes
    ----------
    vertices_mm : (V, 3) float
        The surface's vertices (RAS, mm): the top facets of the simulation mesh.
    facets : (F, 3) int
        Its triangles, indices into ``vertices_mm``.
    fields_per_w : (V, S) float
        Emission fluence per watt of laser power [1/mm^2] at each vertex, one
        column per laser position of the raster (:func:`raster_targets`).
    sources_mm : (S, 3) float
        Where the true beams entered the surface (the sources simulated).
    info : dict
        ``depth_mm``, the simulation options, the simulation mesh's
        ``mesh_nodes`` / ``mesh_elements`` and ``seconds``, and ``source``
        (``"simulated"`` or the stored file).
    """

    vertices_mm: np.ndarray
    facets: np.ndarray
    fields_per_w: np.ndarray
    sources_mm: np.ndarray
    info: dict = field(default_factory=dict)


def raster_targets(n_sources, source_spacing_mm):
    """The laser raster across the tube: (S, 3) points on the liquid surface
    along y at x = 0, ``source_spacing_mm`` apart, centred on the tube."""
    ys = (np.arange(int(n_sources)) - 0.5 * (int(n_sources) - 1)) * float(source_spacing_mm)
    return np.stack([np.zeros_like(ys), ys, np.zeros_like(ys)], axis=1)


def tube_indicator(points_mm, geometry):
    """True where points (N, 3) lie in the phantom's analytic tube (along x)."""
    c = np.asarray(geometry["tube_centre_mm"], float)
    r = float(geometry["tube_radius_mm"])
    d = np.asarray(points_mm, float) - c
    return (d[:, 1] ** 2 + d[:, 2] ** 2) <= r * r


def true_yield_at(points_mm, phantom):
    """The true fluorescence yield [1/mm] at points (N, 3): the analytic tube's
    inside it, the liquid's elsewhere in the liquid, NaN outside the liquid."""
    truth = phantom.truth()
    geo = truth["geometry"]
    p = np.asarray(points_mm, float)
    R, H = float(geo["cylinder_radius_mm"]), float(geo["liquid_depth_mm"])
    top = float(geo.get("top_z_mm", 0.0))
    inside = (p[:, 0] ** 2 + p[:, 1] ** 2 <= R * R) & (p[:, 2] <= top) & (p[:, 2] >= top - H)
    y_tube = float(truth["regions"]["2"]["optics"]["yield_per_mm"])
    y_liquid = float(truth["regions"]["1"]["optics"]["yield_per_mm"])
    return np.where(inside, np.where(tube_indicator(p, geo), y_tube, y_liquid), np.nan)


def simulate_truth(phantom, fine_mm=0.8, simulate_coarse_mm=1.5, n_sources=16,
                   source_spacing_mm=2.5, progress=None, cancel=None):
    """Simulate the true phantom's emission fields on the filmed surface.

    The whole phantom is meshed on its own (``fine_mm`` [mm] at the raster and
    the tube, capped at the burial depth; ``simulate_coarse_mm`` elsewhere);
    the nodes take the analytic tube's optics (not its voxels) by their share of
    the tube (``meshing.shares.analytic_fractions``: the true dye, not the 13 % more
    that sampling the tube at the nodes gave at 4.7 mm); the FEM
    emission fields from each laser position (:func:`raster_targets`, where
    the true beam meets the top surface) are kept on the top surface only.

    Parameters
    ----------
    phantom : fluoguide.phantoms.Phantom
        The cylinder-tube phantom.
    fine_mm, simulate_coarse_mm : float
    n_sources : int
    source_spacing_mm : float
    progress, cancel : optional

    Returns
    -------
    SurfaceTruth
    """
    from FluoTomoLib.acquisition.tracked_scan import raster_scan
    from FluoTomoLib.meshing.shares import analytic_fractions
    from FluoTomoLib.pipelines.steps import (nodal_optics, phantom_simulation_mesh, surface_of,
                                             true_emission_fields)

    t0 = time.perf_counter()
    truth = phantom.truth()
    geo = truth["geometry"]
    optics = {int(k): v["optics"] for k, v in truth["regions"].items()}
    report(progress, 0.02, "simulation mesh (whole phantom)")
    targets = raster_targets(n_sources, source_spacing_mm)
    fine = phantom_simulation_mesh(phantom, targets, 2, fine_mm, simulate_coarse_mm, cancel)
    check_cancel(cancel)
    report(progress, 0.15, "forward simulation (true tissue)")
    true_props = nodal_optics(None, optics, analytic_fractions(
        fine, lambda p: tube_indicator(p, geo)))
    top = fine.boundary_normals[:, 2] > 0.99
    vertices, facets, nodes = surface_of(fine, top)
    # the true beams as the case aims them (its raster_scan, without tracking error)
    src_true = raster_scan(targets, np.zeros(3), np.array([0.0, 0.0, 1.0]), vertices,
                           facets)["true_points_mm"]
    fields = true_emission_fields(fine, true_props, optics[1]["n"], src_true,
                                  progress=scaled(progress, 0.15, 1.0, "forward simulation"),
                                  cancel=cancel)[nodes]
    info = {"format": FORMAT, "depth_mm": float(geo["tube_depth_mm"]),
            "phantom": phantom_key(phantom),
            "fine_mm": float(fine_mm), "simulate_coarse_mm": float(simulate_coarse_mm),
            "n_sources": int(n_sources), "source_spacing_mm": float(source_spacing_mm),
            "mesh_nodes": int(fine.n_nodes), "mesh_elements": int(fine.n_elements),
            "seconds": time.perf_counter() - t0, "source": "simulated"}
    return SurfaceTruth(vertices, facets, fields, src_true, info)


def phantom_key(phantom):
    """The parameters of a cylinder-tube phantom that its true fields depend on
    (:data:`PHANTOM_KEYS`), as plain floats."""
    return {k: float(phantom.params[k]) for k in PHANTOM_KEYS}


def _default_phantom_key():
    """:data:`PHANTOM_KEYS` of ``cylinder_tube()`` called with its defaults."""
    import inspect

    from fluoguide.phantoms import cylinder_tube

    defaults = inspect.signature(cylinder_tube).parameters
    return {k: float(defaults[k].default) for k in PHANTOM_KEYS}


def truth_file(depth_mm, root=None):
    """``root/depth_<d>mm.npz`` (root None: the stored sets)."""
    return Path(STORE if root is None else root) / f"depth_{float(depth_mm):.1f}mm.npz"


def regenerate_command(depth_mm=None):
    """The command that makes the stored sets (all the demo's depths, or one)."""
    only = "" if depth_mm is None else f" (this depth: depth_{float(depth_mm):.1f}mm.npz)"
    return ("fluo demo --simulate-truth --only tomography --out DIR (writes "
            f"DIR/tube_truth/depth_<d>mm.npz for the five depths){only}")


def write_truth(path, truth):
    """Write a :class:`SurfaceTruth` as one compressed ``.npz`` (atomically)."""
    from fluoguide import atomic

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    info = {k: v for k, v in truth.info.items() if k != "source"}

    with atomic.atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, vertices_mm=np.asarray(truth.vertices_mm, float),
                                facets=np.asarray(truth.facets, np.int32),
                                fields_per_w=np.asarray(truth.fields_per_w, FIELD_DTYPE),
                                sources_mm=np.asarray(truth.sources_mm, float),
                                info=np.array(json.dumps(info, sort_keys=True)))
    return path


def read_truth(path):
    """Read a stored :class:`SurfaceTruth`, checked to be whole and consistent;
    a bad file is refused with its name and the command that remakes it."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            info = json.loads(str(z["info"]))
            vertices = np.asarray(z["vertices_mm"], float)
            facets = np.asarray(z["facets"], np.int64)
            fields = np.asarray(z["fields_per_w"], float)
            sources = np.asarray(z["sources_mm"], float)
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise FluoInputError(f"is not a stored tube truth ({exc}; regenerate: "
                             f"{regenerate_command()})", file=str(path)) from None
    if info.get("format") != FORMAT:
        raise FluoInputError(f"stored tube truth of another layout (regenerate: "
                             f"{regenerate_command()})", file=str(path), field="format",
                             value=info.get("format"))
    ok = (vertices.ndim == 2 and vertices.shape[1] == 3 and facets.ndim == 2
          and facets.shape[1] == 3 and facets.size and facets.min() >= 0
          and facets.max() < len(vertices) and fields.shape == (len(vertices),
                                                               int(info.get("n_sources", -1)))
          and sources.shape == (fields.shape[1], 3) and np.all(np.isfinite(fields)))
    if not ok:
        raise FluoInputError(f"stored tube truth is inconsistent (vertices {vertices.shape}, "
                             f"facets {facets.shape}, fields {fields.shape}; regenerate: "
                             f"{regenerate_command()})", file=str(path), field="fields_per_w")
    return SurfaceTruth(vertices, facets, fields, sources, {**info, "source": str(path)})


def stored_truth(depth_mm, options, root=None, phantom=None):
    """The stored set of a depth when ``options`` (the case's simulation
    options, :data:`STORED_OPTIONS`' names) and the ``phantom``'s parameters
    (:data:`PHANTOM_KEYS`; None: the default phantom's) are the stored ones;
    None when they differ or no set is stored for the depth."""
    opts = {k: options.get(k, v) for k, v in STORED_OPTIONS.items()}
    if any(abs(float(opts[k]) - float(v)) > 1e-9 for k, v in STORED_OPTIONS.items()):
        return None
    path = truth_file(depth_mm, root)
    if not path.is_file():
        return None
    truth = read_truth(path)
    if abs(float(truth.info.get("depth_mm", np.nan)) - float(depth_mm)) > 1e-6 or any(
            abs(float(truth.info.get(k, np.nan)) - float(v)) > 1e-9
            for k, v in STORED_OPTIONS.items()):
        raise FluoInputError(f"is not this depth's tube truth with the stored options "
                             f"(regenerate: {regenerate_command(depth_mm)})", file=str(path),
                             field="depth_mm", value=truth.info.get("depth_mm"))
    # the first sets predate the key: they were made for the default phantom
    made_for = truth.info.get("phantom") or _default_phantom_key()
    if phantom is not None and any(
            abs(float(made_for.get(k, np.nan)) - v) > 1e-9
            for k, v in phantom_key(phantom).items()):
        return None                  # another tube, dye or voxel: simulated instead
    return truth
