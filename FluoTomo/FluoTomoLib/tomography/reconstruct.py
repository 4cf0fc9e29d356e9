"""Reconstruction of fluorescence yield on a user's label map: any labels, any
IJK-to-RAS direction, sources, detectors and data from an acquisition.

``reconstruct_labelmap`` is what ``fluo tomo reconstruct``,
``FluoTomoLogic.reconstruct`` and the example script call:

1. optodes onto the tissue surface (moved, with the distance reported, or
   refused beyond MAX_OFFSET_MM);
2. the region of interest from the decay length, its truncation error
   estimated against the whole tissue (roi.py);
3. the reconstruction mesh, anchored at and refined across the target, and
   the model: partial-volume membership, tissue optics per node, Jacobian,
   priors (model.py);
4. NP / SP / HP, HP with the fluorophore's absorption fed back;
5. the yield volume on the label map's own grid (same origin, spacing and
   direction; zero in air) and a summary: region yields with their SD, the
   peak and its RAS position, the target's centroid, warnings, seconds.
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from fluoguide.errors import FluoInputError
from fluoguide.progress import check_cancel, report, scaled

from FluoTomoLib.recon.self_absorption import SELF_ABSORPTION, converged
from FluoTomoLib.recon.solver import SP_CORRECTION_MAX
from FluoTomoLib.tomography.labelmap import MAX_OFFSET_MM, place_on_surface
from FluoTomoLib.tomography.model import move_text

#: Jacobian-sized arrays the solver holds at once (J and R^-1 J^T for NP / SP)
_JACOBIAN_COPIES = 2
#: Jacobian-sized arrays at the peak, per method, for the memory estimate: NP and
#: SP hold J and R^-1 J^T (built block by block, solver.RINV_BLOCK); SP's one
#: self-absorption pass builds a second J and its R^-1 J^T while the first J is
#: kept; HP alone builds none (TissueModel.region_matrix). Measured with
#: simulate.RECON_BYTES_PER_NODE (its comment): SP 3.3 Jacobians above 14 kB a
#: node (228,371 nodes, 684 pairs)
_PEAK_JACOBIAN_COPIES = {"NP": 2, "HP": 0, "SP": 4}
#: largest Jacobian memory [bytes] a reconstruction may take
MAX_JACOBIAN_BYTES = 4e9
#: largest regularisation lambda (docs/reconstruction.md's trade table ends at 1e3,
#: the web app's over-regularised case is 1e6)
MAX_LAMBDA = 1e9


def nodal_to_grid(mesh, values, lm):
    """P1 values of a mesh field (local frame) at the label map's voxel centres,
    zero outside the mesh and in air (label 0); float32 (K, J, I)."""
    from FluoTomoLib.fem.locate import locator

    lo, hi = mesh.bounds()
    shape = lm.labels_kji.shape
    # the voxels in the mesh's box (on a large label map most lie outside it)
    first = np.clip(np.floor(lo / lm.spacing_mm).astype(int) - 1, 0, None)
    stop = np.minimum(np.ceil(hi / lm.spacing_mm).astype(int) + 2, np.array(shape[::-1]))
    out = np.zeros(shape, np.float32)
    if np.any(stop <= first):
        return out
    box = tuple(slice(a, b) for a, b in zip(first[::-1], stop[::-1]))
    tissue = lm.labels_kji[box] > 0
    P = locator(mesh).grid_interpolation_matrix(first * lm.spacing_mm, lm.spacing_mm,
                                                tissue.shape, select=tissue)
    sub = np.zeros(tissue.shape, np.float32)
    sub[tissue] = P @ np.asarray(values, float)
    out[box] = sub
    return out


def _half_max_centroid(vol, lm):
    """Centroid [local mm] of the voxels at or above half the peak, in the
    connected blob that holds the peak (yield-weighted)."""
    from scipy import ndimage

    peak = float(vol.max())
    if not peak > 0:
        return None
    blobs, _ = ndimage.label(vol >= 0.5 * peak)
    k, j, i = np.unravel_index(int(np.argmax(vol)), vol.shape)
    sel = blobs == blobs[k, j, i]
    kk, jj, ii = np.nonzero(sel)
    w = vol[sel].astype(float)
    ijk = np.stack([ii, jj, kk], axis=1) @ np.diag(lm.spacing_mm)
    return (w[:, None] * ijk).sum(axis=0) / w.sum()


#: the reconstruction mesh unless the caller chooses (``grading``): graded by
#: bisection, fine only at the optodes and the boundaries the data see; on the
#: 24-scene family it was as accurate as the uniform grid with a third of the
#: nodes and half the time, and under a 1 mm segmentation error as well
#: (docs/validation.md, "The graded (bisection) reconstruction mesh")
DEFAULT_GRADING = "bisection"

#: the graded mesh refines the regions' boundaries within this many decay lengths
#: (1 / mu_eff) of the optodes (farther, their data are exp(-3) of the nearest's)
SEE_DECAY_LENGTHS = 3.0


def labelmap_mesh(lm, optics, src, det, mask, target, settings, grading=False, roi_ras=None,
                  timings=None, progress=None, cancel=None):
    """The reconstruction mesh of a label map for an acquisition's optodes: the
    region of interest (``roi_ras``, a RAS box, or chosen from the light's decay
    length with its truncation error estimated), then the mesh on it.

    Parameters
    ----------
    lm : LabelMap
    optics : Optics
    src, det : (S, 3), (D, 3) optodes on the tissue surface, local mm
    mask : (S, D) bool, the pairs used
    target : label to anchor on and refine across (None: neither)
    settings : dict, ``accuracy.accuracy_settings``' (``recon_mm``,
        ``recon_coarse_mm``, ``refine_factor``, ``truncation_pct``)
    grading : False or "grid" / True (a rectilinear grid graded from the
        optodes) or "bisection" (:func:`.model.graded_reconstruction_mesh`)
    roi_ras : (x0, x1, y0, y1, z0, z1) RAS mm, optional
    timings : dict, optional; gets ``roi`` and ``meshing`` [s]
    progress, cancel : optional

    Returns
    -------
    (Mesh in the local frame, roi_info dict, warnings list)
    """
    from FluoTomoLib.tomography.roi import choose_roi, roi_from_ras

    _check_grading(grading)
    timings = {} if timings is None else timings
    notes = []
    t0 = time.perf_counter()
    if roi_ras is not None:
        roi = roi_from_ras(lm, roi_ras)
        roi_info = {"chosen": "given", "truncation_max_pct": None}
        notes.append("the region of interest was given: its truncation error is not "
                     "estimated")
    else:
        anchor = lm.region_centroid_local(target) if target is not None else None
        roi, roi_info = choose_roi(lm, optics, src, det, mask, target,
                                   settings["truncation_pct"], anchor=anchor,
                                   progress=progress, cancel=cancel)
        roi_info["chosen"] = "from the decay length"
        if (roi_info.get("truncation_max_pct") or 0) > settings["truncation_pct"]:
            notes.append(f"the region of interest changes the data by up to "
                         f"{roi_info['truncation_max_pct']:.1f} % (tolerance "
                         f"{settings['truncation_pct']:g} %)")
    timings["roi"] = time.perf_counter() - t0
    check_cancel(cancel)
    report(progress, 0.15, "reconstruction mesh")
    t0 = time.perf_counter()
    mesh = _mesh_on(lm, optics, src, det, target, settings, grading, roi, None,
                    scaled(progress, 0.15, 0.3, "reconstruction mesh"), cancel)
    timings["meshing"] = time.perf_counter() - t0
    return mesh, roi_info, notes


def _mesh_on(lm, optics, src, det, target, settings, grading, roi, anchor, progress, cancel):
    """:func:`labelmap_mesh`'s mesh on a chosen ``roi`` (local mm), its grid through
    ``anchor`` (local mm; None: the target's centre, or the roi's corner)."""
    from FluoTomoLib.tomography.accuracy import cap_at_burial
    from FluoTomoLib.tomography.model import graded_reconstruction_mesh, reconstruction_mesh

    h, mfp = cap_at_burial(settings["recon_mm"], optics, lm.labels)
    optodes = np.vstack([src, det])
    if grading == "bisection":
        return graded_reconstruction_mesh(
            lm.labels_kji, lm.spacing_mm, h, roi, optodes, settings["recon_coarse_mm"], target,
            settings["refine_factor"], surface=lm.surface(), burial_mm=mfp, anchor=anchor,
            see_mm=SEE_DECAY_LENGTHS / optics.min_mueff(lm.labels), cancel=cancel,
            progress=progress)
    return reconstruction_mesh(
        lm.labels_kji, lm.spacing_mm, h, roi, target, settings["refine_factor"],
        anchor=anchor, surface=lm.surface(), optodes=optodes,
        coarse_mm=settings["recon_coarse_mm"] if grading else None,
        optode_normals=lm.surface().closest(optodes)[1], burial_mm=mfp, cancel=cancel,
        progress=progress)


def reconstruct_labelmap(lm, optics, acquisition, method="HP", lam=None, target=None,
                         accuracy="balanced", size_mm=None, refine_factor=None, roi_ras=None,
                         truncation_pct=None, data_model="linear", self_absorption=SELF_ABSORPTION,
                         mesh=None, max_offset_mm=MAX_OFFSET_MM, grading=DEFAULT_GRADING,
                         progress=None,
                         cancel=None, noise_pct=None, segmentation_mm=None):
    """Reconstruct the yield of a label map from an acquisition.

    Parameters
    ----------
    lm : LabelMap
    optics : Optics (every label of the map listed)
    acquisition : Acquisition (sources, detectors RAS mm; data per watt)
    method : "NP", "SP" or "HP"
    lam : regularisation lambda (None: 10, the reference's)
    target : label graded and meshed finely (None: the smallest region that
        is not the largest)
    accuracy : "fast", "balanced" or "fine" (accuracy.LEVELS); ``size_mm``,
        ``refine_factor``, ``truncation_pct`` override its values
    roi_ras : (x0, x1, y0, y1, z0, z1) RAS mm instead of the automatic region
    data_model : "linear" (fit y) or "log" (fit ln y; needs positive data)
    self_absorption : methods that feed the fluorophore's absorption back (when
        optics.json names one): HP to convergence, SP one pass.  On the
        ellipsoid scene (a 6 mm sphere of 2 ug/mL ICG) SP went from -36 %
        blind to -11 % fed; the cylinder-tube study's 4.7 mm tube from 0.76 to
        0.99 of the truth (docs/tomography.md)
    mesh : a reconstruction mesh already built for this scene (local frame,
        :func:`FluoTomoLib.tomography.model.reconstruction_mesh`), e.g. the one
        the app showed; None builds it
    max_offset_mm : optodes farther from the tissue surface are refused
    grading : "bisection" (:data:`DEFAULT_GRADING`): refined by bisection
        near the optodes and the regions' boundaries only, growing to
        ``recon_coarse_mm`` away from them
        (:func:`FluoTomoLib.tomography.model.graded_reconstruction_mesh`);
        False: a uniform grid (refined in bands through the target and under
        the optodes); True: optode-aware grading of that grid,
        ``recon_coarse_mm`` cells away from the box of the optodes and the
        target (about half the nodes; the data moved by up to 11 % on the
        issue's scene, docs)
    noise_pct : the data's relative noise, one SD per measurement [%]; None: the
        acquisition's own statement (``Acquisition.noise_pct``), else unknown.
        The fit is tested against it and the intervals widen when the model
        explains the data worse than this noise allows (docs/reconstruction.md,
        "Intervals")
    segmentation_mm : how far the label map's boundaries may be off [mm] (the CBCT
        segmentation's accuracy; None: half the largest voxel size, the label
        map's own quantisation; 0: taken as exact). The regions are solved again
        with their boundaries moved by it, and the intervals reach the values found

    Returns
    -------
    dict: ``summary`` (JSON-able: method, regions, peak, centroid, warnings,
    seconds, ...), ``yield_kji`` (float32 on the label map's grid), ``mesh``
    (local frame), ``yield_nodes``, ``sources_ras_mm``, ``detectors_ras_mm``.
    """
    return reconstruct_labelmap_methods(
        lm, optics, acquisition, (method,), lam, target, accuracy, size_mm, refine_factor,
        roi_ras, truncation_pct, data_model, self_absorption, mesh, max_offset_mm, grading,
        progress, cancel, noise_pct, segmentation_mm)[str(method).upper()]


def reconstruct_labelmap_methods(lm, optics, acquisition, methods=("NP", "SP", "HP"), lam=None,
                                 target=None, accuracy="balanced", size_mm=None,
                                 refine_factor=None, roi_ras=None, truncation_pct=None,
                                 data_model="linear", self_absorption=SELF_ABSORPTION, mesh=None,
                                 max_offset_mm=MAX_OFFSET_MM, grading=DEFAULT_GRADING,
                                 progress=None,
                                 cancel=None, noise_pct=None, segmentation_mm=None):
    """:func:`reconstruct_labelmap` for several methods on one model (one mesh,
    one Jacobian).  Returns {method: result}."""
    from FluoTomoLib.fem.kernels import prepare_kernels
    from FluoTomoLib.tomography.accuracy import cap_at_burial

    _check_grading(grading)
    t_all = time.perf_counter()
    timings = {}
    methods, lam, target, settings, seg_mm, noise_pct, noise_from = _checked_request(
        lm, optics, acquisition, methods, lam, target, accuracy, size_mm, refine_factor,
        truncation_pct, data_model, noise_pct, segmentation_mm)
    # the compiled kernels before the first step that needs them: their first-run
    # compilation (~11 s) is reported as it goes, not hidden inside a step
    prepare_kernels(progress, 0.0, cancel)
    notes = []          # warnings: what may make the result wrong
    remarks = []        # notes: what was done differently from the request, harmlessly
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        src, det, d_src, d_det = _optodes_on_surface(lm, acquisition, max_offset_mm, notes,
                                                     progress)
        check_cancel(cancel)
        cut_info, coverage = _what_the_scan_sees(lm, optics, acquisition, src, det, noise_pct,
                                                 notes, progress, cancel)
        h = cap_at_burial(settings["recon_mm"], optics, lm.labels)[0]
        if h < settings["recon_mm"]:
            remarks.append(f"elements near the optodes are {h:.2g} mm, the sources' burial depth "
                           f"(asked for {settings['recon_mm']:g} mm)")
        mesh_built = mesh is None
        mesh, roi_info = _model_mesh(lm, optics, acquisition, src, det, target, settings,
                                     grading, roi_ras, mesh, timings, notes, progress, cancel)
        nodal_j = _check_jacobian_memory(acquisition, mesh, methods, h)
        check_cancel(cancel)
        tm, prior_volumes, forward_err, prior_notes = _tissue_model(
            lm, optics, acquisition, mesh, src, det, nodal_j, timings, progress)
        y = acquisition.y()
        noise_rel = None if noise_pct is None else noise_pct / 100
        # every method asked for, and HP where it was solved as SP's start: the tests
        # below take it as they take a requested HP (the same model, the same values)
        found = _solve_methods(tm, y, methods, lam, self_absorption, data_model, noise_rel,
                               progress, cancel)
        solved = {m: found[m] for m in methods}
        shifts = None
        if seg_mm > 0:
            t_seg = time.perf_counter()
            shifts = _segmentation_shifts(tm, y, found, methods, lam, seg_mm, self_absorption,
                                          data_model, noise_rel, progress, cancel)
            timings["segmentation_test"] = time.perf_counter() - t_seg
        # the methods with a prior re-solved on the boundary the data chose, where they
        # chose one by far (the mesh placement test below compares like with like: the
        # segmentation as given, on both meshes)
        on_quoted, declined = _solve_on_quoted_boundary(
            tm, y, solved, methods, lam, seg_mm, shifts, self_absorption, data_model,
            noise_rel, progress, cancel)
        placements = None
        if mesh_built and MESH_PLACEMENTS:
            t_pl = time.perf_counter()
            placements = _mesh_placements(lm, optics, acquisition, src, det, mesh, tm, target,
                                          settings, grading, y, found, lam, self_absorption,
                                          data_model, noise_rel, progress, cancel)
            timings["mesh_placement_test"] = time.perf_counter() - t_pl
        elif not mesh_built:
            remarks.append("the mesh was given: the intervals hold no part for where its "
                           "elements fall (the mesh placement test builds its own meshes)")
        as_given = _take_quoted(on_quoted, solved)
    for text in _once(str(w.message) for w in caught):
        if text not in notes:
            notes.append(text)
    t_common = time.perf_counter() - t_all - sum(r.seconds for r, _ in solved.values())
    out = {}
    for method, (res, passes) in solved.items():
        model_of = on_quoted[method][2] if method in on_quoted else tm
        out[method] = _result(lm, optics, acquisition, model_of, mesh, res, passes, method, lam,
                              target, data_model, settings, h, roi_info,
                              list(notes) + prior_notes.get(method, []),
                              dict(timings, reconstruction=res.seconds), src, det, d_src, d_det,
                              t_common + res.seconds)
        _add_run_summary(out[method]["summary"], method, settings, remarks, cut_info, coverage,
                         noise_pct, noise_from, shifts, seg_mm, prior_volumes, forward_err,
                         as_segmented=as_given.get(method))
        _add_mesh_placements(out[method]["summary"], placements)
        if method in declined:
            out[method]["summary"]["notes"].append(
                f"the segmentation test chose the regions "
                f"{move_text(_quoted_move(shifts))}, but {declined[method][2]} fits the "
                f"data no better there (residual {declined[method][0]:.3g} against "
                f"{declined[method][1]:.3g} as segmented): the values are the segmentation's "
                "own")
    report(progress, 1.0, "done")
    return out


def _check_grading(grading):
    """Refuse a mesh grading that :func:`labelmap_mesh` does not know."""
    if grading not in (False, True, None, "grid", "bisection"):
        raise FluoInputError("grading must be none, grid or bisection", field="grading",
                             value=grading)


def _checked_request(lm, optics, acquisition, methods, lam, target, accuracy, size_mm,
                     refine_factor, truncation_pct, data_model, noise_pct, segmentation_mm):
    """A reconstruction's request checked and completed before anything is computed.

    Returns
    -------
    (methods upper-case, lambda (10 when None), target label (the label map's
    default when None), accuracy settings, segmentation accuracy [mm], noise [%]
    or None, where the noise came from ("given" or "acquisition"))

    Raises
    ------
    FluoInputError
        Naming the field and value, for a segmentation accuracy outside 0..5 mm, a
        noise outside 0..100 %, an unknown method, lambda or data model, a bad
        accuracy level, optics missing a label, a target not in the label map, or
        data that the log model cannot take.
    """
    from FluoTomoLib.tomography.accuracy import accuracy_settings

    methods = [str(m).upper() for m in methods]
    seg_mm = 0.5 * float(np.max(lm.spacing_mm)) if segmentation_mm is None \
        else float(segmentation_mm)
    if not (np.isfinite(seg_mm) and 0 <= seg_mm <= 5):
        raise FluoInputError("the segmentation's accuracy must be within 0..5 mm (0: its "
                             "boundaries taken as exact)", field="segmentation_mm",
                             value=segmentation_mm)
    noise_from = "given" if noise_pct is not None else "acquisition"
    if noise_pct is None:
        noise_pct = acquisition.noise_pct()
    if noise_pct is not None and not (np.isfinite(noise_pct) and 0 < noise_pct < 100):
        raise FluoInputError("the data's relative noise must be within 0..100 % (one SD per "
                             "measurement; 0 is no noise model: leave it out)",
                             field="noise_pct", value=noise_pct)
    if not methods:
        raise FluoInputError("no method asked for: give NP, SP or HP", field="method", value=[])
    for m in methods:
        if m not in ("NP", "SP", "HP"):
            raise FluoInputError("method must be NP, SP or HP", field="method", value=m)
    lam = 10.0 if lam is None else float(lam)
    if not (np.isfinite(lam) and 0 < lam <= MAX_LAMBDA):
        raise FluoInputError(f"lambda must be a number in (0, {MAX_LAMBDA:g}] (beyond it the "
                             "prior alone decides the result)", field="lambda", value=lam)
    if data_model not in ("linear", "log"):
        raise FluoInputError("data model must be linear or log", field="data_model",
                             value=data_model)
    settings = accuracy_settings(accuracy, recon_mm=size_mm, refine_factor=refine_factor,
                                 truncation_pct=truncation_pct)
    optics.check_labels(lm.labels)
    if target is None:
        target = lm.default_target()
    elif int(target) not in lm.labels:
        raise FluoInputError("target label is not in the label map", file=lm.source,
                             field="target", value=int(target))
    if data_model == "log":
        acquisition.check_for_log()
    return methods, lam, target, settings, seg_mm, noise_pct, noise_from


def _optodes_on_surface(lm, acquisition, max_offset_mm, notes, progress):
    """The acquisition's sources and detectors moved onto the tissue surface
    (local mm) with each one's distance moved [mm]; a warning in ``notes`` when
    any moved more than 0.5 mm.  Returns (src, det, d_src, d_det)."""
    report(progress, 0.01, "optodes onto the tissue surface")
    src, d_src = place_on_surface(lm, acquisition.sources_ras_mm, "sources", max_offset_mm,
                                  acquisition.file_of("sources"))
    det, d_det = place_on_surface(lm, acquisition.detectors_ras_mm, "detectors",
                                  max_offset_mm, acquisition.file_of("detectors"))
    moved = float(max(d_src.max(), d_det.max()))
    if moved > 0.5:
        notes.append(f"optodes were moved up to {moved:.2f} mm onto the tissue surface")
    return src, det, d_src, d_det


def _what_the_scan_sees(lm, optics, acquisition, src, det, noise_pct, notes, progress, cancel):
    """Where the label map cuts the tissue short, and what the scan sees of each
    region, said before anything is solved: their warnings go into ``notes``
    (the coverage's also reported as they are found).  Returns (cut_info,
    coverage), each without its warnings."""
    from FluoTomoLib.tomography.coverage import scan_coverage
    from FluoTomoLib.tomography.roi import label_map_cut

    cut_info = label_map_cut(lm, optics, src, det, acquisition.mask, cancel=cancel)
    notes.extend(cut_info.pop("warnings"))
    coverage = scan_coverage(lm, optics, lm.to_ras(src), lm.to_ras(det), acquisition.mask,
                             1.0 if noise_pct is None else noise_pct)
    for text in coverage["warnings"]:
        report(progress, 0.02, text)
    notes.extend(coverage.pop("warnings"))
    return cut_info, coverage


def _model_mesh(lm, optics, acquisition, src, det, target, settings, grading, roi_ras, mesh,
                timings, notes, progress, cancel):
    """The reconstruction mesh: the one given (refused unless in the label map's
    frame) or one built by :func:`labelmap_mesh`; its warnings go into ``notes``.
    Returns (mesh, roi_info)."""
    if mesh is None:
        mesh, roi_info, mesh_notes = labelmap_mesh(
            lm, optics, src, det, acquisition.mask, target, settings, grading, roi_ras,
            timings, progress, cancel)
        notes.extend(mesh_notes)
    else:
        roi_info = {"chosen": "the mesh given", "truncation_max_pct": None}
        if mesh.meta.get("frame") not in (None, "local"):
            raise FluoInputError("the mesh is not in the label map's frame", field="mesh")
    notes.extend(mesh.meta.get("warnings", []))
    return mesh, roi_info


def _check_jacobian_memory(acquisition, mesh, methods, h):
    """Refuse a reconstruction whose Jacobians exceed MAX_JACOBIAN_BYTES or what
    this machine has left (``h``: the element size near the optodes [mm], named
    in the message).  Returns whether the nodal Jacobian is built up front: for NP
    (SP fed back from HP's absorption builds its own, and the blind one only where
    it needs it: ``TissueModel.nodal_J``)."""
    from FluoTomoLib.tomography.simulate import RECON_BYTES_PER_NODE, check_fem_memory

    # HP alone never builds the nodal Jacobian (TissueModel.region_matrix)
    nodal_j = any(m != "HP" for m in methods)
    one_j = acquisition.n_measurements * mesh.n_nodes * 8.0
    n_bytes = one_j * _JACOBIAN_COPIES if nodal_j else 0.0
    if n_bytes > MAX_JACOBIAN_BYTES:
        raise FluoInputError(f"{acquisition.n_measurements} measurements x {mesh.n_nodes} "
                             f"nodes need {n_bytes / 1e9:.1f} GB: use accuracy 'fast', a "
                             "larger element size or fewer pairs", field="size_mm",
                             value=h)
    # and what this machine has left, for the method that needs the most
    copies = max(_PEAK_JACOBIAN_COPIES[m] for m in methods)
    check_fem_memory(mesh.n_nodes, one_j * copies, h, per_node=RECON_BYTES_PER_NODE)
    return "NP" in methods


def _tissue_model(lm, optics, acquisition, mesh, src, det, nodal_j, timings, progress):
    """The model on the mesh (its Jacobian, progress 0.3-0.6), the priors' volumes
    against the label map's and the mesh's own error in the data.  Returns
    (TissueModel, prior_volumes, forward_err, prior_notes {method: [warning]}:
    each prior's volume warnings go to the method that uses it)."""
    from FluoTomoLib.tomography.model import TissueModel, check_prior_volumes

    report(progress, 0.3, f"Jacobian ({mesh.n_nodes} nodes, "
                          f"{acquisition.n_measurements} measurements)")
    tm = TissueModel(mesh, lm.labels_kji, lm.spacing_mm, optics, src, det,
                     acquisition.mask, source_normals=lm.surface().closest(src)[1],
                     timings=timings, cut_facets=lm.cut_facets(mesh),
                     progress=scaled(progress, 0.3, 0.6, "Jacobian"),
                     nodal_jacobian=nodal_j)
    report(progress, 0.6, "the priors' volumes and the mesh's own error in the data")
    prior_volumes, prior_notes = check_prior_volumes(
        tm.prior, mesh, mesh.meta.get("labelmap_volumes_mm3", {}))
    forward_err = _forward_error(tm, acquisition.mask)
    return tm, prior_volumes, forward_err, prior_notes


def _solve_methods(tm, y, methods, lam, self_absorption, data_model, noise_rel, progress,
                   cancel, span=(0.6, 0.94), hp=None):
    """Each method solved on the one model, HP first, sharing the progress ``span``:
    SP's absorption feedback starts from HP's converged one (``hp``, else this
    call's HP: :func:`_sp_start`; solved here too where SP is asked for without it,
    :func:`_hp_for_sp_only`). Returns {method: (result, passes)} in the order of
    ``methods``, then HP where it was solved only as SP's start."""
    solved = {}
    a, b = span
    order = sorted(methods, key=lambda m: m != "HP")
    if _hp_for_sp_only(tm, methods, self_absorption, data_model, hp):
        order = ["HP"] + order
    for i, method in enumerate(order):
        check_cancel(cancel)
        what = f"reconstruction {method}" + ("" if method in methods else " (SP's start)")
        part = scaled(progress, a + (b - a) * i / len(order),
                      a + (b - a) * (i + 1) / len(order), what)
        report(part, 0.0, "start")
        start = _sp_start(solved.get("HP", hp), self_absorption) if method == "SP" else None
        solved[method] = tm.solve(y, method, lam, self_absorption, data_model == "log",
                                  cancel, progress=part, noise_rel=noise_rel, start=start)
    return {m: solved[m] for m in [*methods, *(m for m in order if m not in methods)]}


def _hp_for_sp_only(tm, methods, self_absorption, data_model, hp):
    """Whether SP, asked for without HP, needs HP solved as its start (not reported):
    where both feed the dye's absorption back. SP alone started from the blind model,
    a different SP from the one the family grades (HP and SP together): scenes 36, 30
    and 47 read -18.5, -20.3 / -28.2 and -22.1 % alone, -2.6, -0.7 / -6.5 and +15.3 %
    from HP's absorption (docs/validation.md, "SP asked for alone")."""
    feeds = tuple(self_absorption or ())
    return ("SP" in methods and "HP" not in methods and hp is None and "HP" in feeds
            and "SP" in feeds and tm.absorbs(data_model == "log"))


def _sp_start(hp, self_absorption):
    """HP's result whose absorption SP's feedback starts from: where HP fed the
    dye's absorption back to convergence. One SP pass from the blind model left a
    quarter to a half of the truth owed (``feedback_pending_per_mm``) on the scene
    family's absorbing inclusions, SP a median 6 % low with HP within 3 %
    (docs/reconstruction.md, "SP's value"); a diverged HP feedback is no start."""
    if hp is None or "HP" not in tuple(self_absorption or ()):
        return None
    return hp[0] if converged(hp[0]) else None


def _segmentation_shifts(tm, y, solved, methods, lam, seg_mm, self_absorption, data_model,
                         noise_rel, progress, cancel):
    """HP's region values with the segmentation's boundaries moved by +-``seg_mm``
    (``TissueModel.segmentation_shifts``, progress 0.94-0.97)."""
    # HP's region values with the boundaries moved (a few region unknowns:
    # cheap), their relative change carried over to every method (NP and
    # SP re-solved cost 3 of their solves each; their region means over a
    # moved label move like HP's values, the data pinning the same total)
    # on the model with the dye's absorption as the reconstruction found it
    # (HP's where it ran, else a method that fed it back), as the data hold it
    fed = [m for m in ("HP", *methods) if m in solved and m in (self_absorption or ())]
    report(progress, 0.94, f"segmentation moved by +-{seg_mm:.2g} mm")
    return tm.segmentation_shifts(
        y, "HP", lam, seg_mm, data_model == "log", noise_rel, cancel,
        progress=scaled(progress, 0.94, 0.96, f"segmentation moved by "
                        f"+-{seg_mm:.2g} mm"),
        absorbing_yield=solved[fed[0]][0].yield_per_mm
        if fed and data_model != "log" else None,
        feedback=not (fed and solved[fed[0]][0].diverged),
        at_fixed_point=bool(fed) and fed[0] == "HP" and converged(solved["HP"][0]))


def _solve_on_quoted_boundary(tm, y, solved, methods, lam, seg_mm, shifts, self_absorption,
                              data_model, noise_rel, progress, cancel):
    """HP and SP (the methods with a prior) solved again, as they were, on the
    segmentation with its boundaries moved to the offset, or its regions by the rigid
    move, the segmentation test chose (:func:`_quoted_move`, progress 0.96-0.97): the
    boundary estimated with the yield, where HP's fit confirms it
    (:func:`_judged_solves`). On the family 1 mm
    off, quoting the chosen boundary's values took HP's median |error| from 66 % to
    33 % and SP's from 64 % to 20 % (docs/validation.md, "The boundary the data choose,
    quoted"). Returns ({method: (result, passes, the moved model)}, {method declined:
    (residual there, residual as segmented, the method whose residuals they are)});
    both empty where nothing was quoted."""
    q = _quoted_move(shifts)
    again = [m for m in methods if m in ("HP", "SP") and m in solved]
    if q is None or not again:
        return {}, {}
    report(progress, 0.96, f"the regions {move_text(q)}: their priors")
    moved = tm.with_boundaries_moved(q, seg_mm)
    on_moved = {}

    def solve_one(method, i, n):
        span = (0.96 + 0.01 * i / n, 0.96 + 0.01 * (i + 1) / n)
        on_moved[method] = _solve_methods(moved, y, [method], lam, self_absorption,
                                          data_model, noise_rel, progress, cancel, span=span,
                                          hp=on_moved.get("HP"))[method]
        return on_moved[method]

    done, declined = _judged_solves(again, solved, solve_one)
    return {m: (res, passes, moved) for m, (res, passes) in done.items()}, declined


def _quoted_move(shifts):
    """The move whose values are quoted (``TissueModel.segmentation_shifts``): an
    offset [mm], a rigid move {label: (di, dj, dk) mm}, or None."""
    if not shifts:
        return None
    if shifts.get("quoted_translation") is not None:
        return shifts["translations"][shifts["quoted_translation"]]["moves_mm"]
    return shifts.get("quoted_offset_mm")


def _judged_solves(methods, solved, solve_one):
    """``solve_one(method, i, n)`` -> (result, passes) of each of ``methods`` on the
    chosen boundary, HP first: where HP (the regions-as-constants fit the test
    compares; without it the one method itself) fits the data no better there than as
    segmented (``solved``), the test's choice is not confirmed, nothing more is solved
    and every method keeps the segmentation's values. On the family those were the
    shifted segmentations 103 and 111, whose HP read -69 % and +178 % on the grown
    boundary; no eroded or dilated one. SP's own, damped fit does not tell boundaries
    apart: by it, the eroded scene 105 kept +419 % where the grown boundary gave +28 %.
    Returns ({method: (result, passes)}, {method declined: (residual there, residual as
    segmented, the judging method)})."""
    order = sorted(methods, key=lambda m: m != "HP")
    done = {}
    for i, method in enumerate(order):
        done[method] = solve_one(method, i, len(order))
        if i == 0 and not done[method][0].residual < solved[method][0].residual:
            why = (done[method][0].residual, solved[method][0].residual, method)
            return {}, {m: why for m in methods}
    return done, {}


def _take_quoted(on_quoted, solved):
    """The re-solves on the chosen boundary (``on_quoted``, from
    :func:`_solve_on_quoted_boundary`) into ``solved``. Returns {method: its values on
    the segmentation as given}."""
    from FluoTomoLib.tomography.model import region_values

    as_given = {}
    for method, (res, passes, _) in on_quoted.items():
        as_given[method] = region_values(solved[method][0])
        # the method's own solve time is both its solves'
        res.seconds += solved[method][0].seconds
        solved[method] = (res, passes)
    return as_given


#: the mesh placement test: the grid's anchor moved by these fractions of the
#: element size across the target (docs/reconstruction.md, Intervals,
#: ``mesh_placement_per_mm``); () turns it off
MESH_PLACEMENTS = ((0.5, 0.5, 0.5),)
#: self-absorption passes of each placement's HP from the unmoved HP's absorbing
#: model (the segmentation test's moved boundaries take as many)
PLACEMENT_PASSES = 1


def _mesh_placements(lm, optics, acquisition, src, det, mesh, tm0, target, settings, grading,
                     y, solved, lam, self_absorption, data_model, noise_rel, progress, cancel):
    """HP's region values on meshes whose grid is shifted by MESH_PLACEMENTS
    (fractions of the element size across the target) against the mesh used
    (progress 0.97-0.999). The same data, optics, scan and element sizes: what
    moves the values is the discretisation alone (where the elements fall on the
    light's steep near field and on the absorbing target), an error the residual
    does not show when it looks like a change of yield. On the family (fast) the
    value moved by 3-44 % between five placements, and scene 12's +15 % HP value
    sat outside an interval that held no part for it. Each placement's HP starts
    from the model with the dye's absorption of the unmoved HP's values and feeds
    it back PLACEMENT_PASSES times, as the segmentation test's moved segmentations
    do. Returns {"shifts_mm": [...], "values_per_mm": {label: [unmoved, moved...]}}
    or None."""
    from FluoTomoLib.recon.self_absorption import absorbing_model
    from FluoTomoLib.tomography.model import TissueModel, region_values

    def values_of(res):
        return None if res.diverged else region_values(res)

    log_data = data_model == "log"
    if "HP" in solved:
        base = values_of(solved["HP"][0])
    else:
        base = values_of(tm0.solve(y, "HP", lam, self_absorption, log_data, cancel,
                                   noise_rel=noise_rel)[0])
    if base is None:
        return None
    feed = "HP" in tuple(self_absorption or ()) and tm0.absorbs(log_data)
    roi = np.asarray(mesh.meta["roi"], float)
    h = float(mesh.meta.get("size_mm"))
    h_t = h if target is None else min(h, float(settings["refine_factor"] or 1.0) * h)
    anchor = (lm.region_centroid_local(target) if target is not None
              else roi[[0, 2, 4]])
    values = {lab: [v] for lab, v in base.items()}
    moved = []
    n = len(MESH_PLACEMENTS)
    for i, frac in enumerate(MESH_PLACEMENTS):
        check_cancel(cancel)
        part = scaled(progress, 0.97 + 0.029 * i / n, 0.97 + 0.029 * (i + 1) / n,
                      f"mesh placement {i + 1} of {n}")
        shift = np.asarray(frac, float) * h_t
        m = _mesh_on(lm, optics, src, det, target, settings, grading, roi, anchor + shift,
                     scaled(part, 0.0, 0.4), cancel)
        tm = TissueModel(m, lm.labels_kji, lm.spacing_mm, optics, src, det, acquisition.mask,
                         source_normals=tm0.source_normals, cut_facets=lm.cut_facets(m),
                         progress=scaled(part, 0.4, 0.5), nodal_jacobian=False,
                         fields=not feed, soft_prior=False)
        step = scaled(part, 0.5, 1.0)
        if feed:
            start = tm.prior.K() @ np.array([base[int(lab)] for lab in tm.prior.labels])
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")     # said by the unmoved model already
                model = absorbing_model(tm.make_model, start, (0.0, 0.0), 0.0,
                                        optics.mua_per_yield, step, cancel)
            res = tm.hp_fed_back(y, lam, model, PLACEMENT_PASSES, noise_rel=noise_rel,
                                 cancel=cancel, progress=step)
        else:
            res, _ = tm.solve(y, "HP", lam, (), log_data, cancel, progress=step,
                              noise_rel=noise_rel)
        got = values_of(res)
        if got is None:
            continue
        moved.append(shift.tolist())
        for lab in values:
            values[lab].append(got.get(lab))
    return {"shifts_mm": moved, "values_per_mm": values}


def _add_mesh_placements(summary, placements):
    """The mesh placement test's part of each region's 95 % interval: the largest
    relative change of HP's value between the placements, carried over to this
    method's value (as the segmentation test's is) and added on both sides: the
    unmoved mesh's own error is of either sign."""
    if not placements or not placements["shifts_mm"]:
        return
    summary["mesh_placement"] = placements
    worst = 0.0
    for lab, r in summary["regions"].items():
        vals = placements["values_per_mm"].get(int(lab))
        v = r.get("yield_per_mm")
        if not vals or v is None or vals[0] is None or not vals[0] > 0:
            continue
        rel = max((abs(x / vals[0] - 1.0) for x in vals[1:] if x is not None), default=0.0)
        r["interval_parts"]["mesh_placement_per_mm"] = float(rel * v)
        r["ci95_per_mm"] = _widen(r.get("ci95_per_mm"), rel * v, rel * v)
        worst = max(worst, rel)
    summary["notes"].append(
        f"the regions' values move by up to {100 * worst:.2g} % with the mesh's grid "
        f"shifted by half an element: the mesh's own error, counted in the 95 % "
        f"intervals (interval_parts.mesh_placement_per_mm)")


def _add_run_summary(summary, method, settings, remarks, cut_info, coverage, noise_pct,
                     noise_from, shifts, seg_mm, prior_volumes, forward_err, as_segmented=None):
    """What the run found before and beside the solve, into one method's summary:
    the label map's cut, the scan's coverage, the noise and where it came from,
    the notes, and the segmentation's, priors' and forward model's parts of the
    intervals."""
    summary["label_map_cut"] = cut_info
    summary["scan_coverage"] = coverage
    summary["noise"] = {
        "pct": noise_pct, "source": None if noise_pct is None else noise_from,
        "note": "one SD per measurement [%], tested against the fit" if noise_pct
        is not None else "not stated: the fit is judged from its own residual"}
    summary["notes"] = list(remarks) + _fit_notes(summary, settings)
    if noise_pct is None:
        # a note, not a warning: every tracked-frames acquisition (the demo's cases)
        # lacks a statement, and its fit is still judged (MISFIT_WARN)
        summary["notes"].append(
            "the data's noise is not stated (acquisition.json's noise_pct, or "
            "--noise-pct): the 95 % intervals count the whole misfit both as noise and "
            "as the model's own error (interval_parts.model_error_bound_per_mm); a "
            "stated noise narrows them")
    _add_segmentation(summary, shifts, seg_mm, method, as_segmented)
    _add_prior_volume(summary, prior_volumes, method)
    _add_forward_error(summary, forward_err)


def _widen(ci, down, up):
    """An interval [1/mm] widened by ``down`` below and ``up`` above (each >= 0: the
    parts add, as noise and bias do), clipped at zero (a yield is not negative);
    None stays None (no interval could be given)."""
    return None if ci is None else [max(ci[0] - down, 0.0), ci[1] + up]


def _with_feedback(ci, pending):
    """The interval reaching on towards where the self-absorption feedback, stopped
    after its passes (SP: one), was still heading (``pending`` [1/mm], signed)."""
    if not pending:
        return ci
    return _widen(ci, max(-pending, 0.0), max(pending, 0.0))


def _forward_error(tm, mask):
    """The reconstruction mesh's own error in the data, relative: the median over
    the used pairs of the estimated median-case errors of the excitation and the
    emission fields (``FluorescenceModel.accuracy``, the measured tables of
    fem.resolution), added. A scale error of the model's data is absorbed by the
    yield whole, the fit showing nothing of it (the family: +3 % at a perfect fit,
    docs/validation.md); None when it cannot be estimated."""
    try:
        acc = tm.model.accuracy(wavelengths=("excitation", "emission"))
    except FluoInputError:
        return None
    parts = []
    for w in ("excitation", "emission"):
        med = acc["estimated_rel_err"].get(w, {}).get("median_case")
        if med is None:
            return None
        med = np.asarray(med, float).reshape(mask.shape)
        parts.append(np.where(np.isfinite(med), med, np.nan))
    total = (np.abs(parts[0]) + np.abs(parts[1]))[mask]
    return float(np.nanmedian(total)) if np.isfinite(total).any() else None


def _add_forward_error(summary, rel):
    """The forward model's own error (:func:`_forward_error`) in every interval."""
    summary["forward_model_rel_err"] = rel
    if rel is None:
        return
    for r in summary["regions"].values():
        v, ci = r.get("yield_per_mm"), r.get("ci95_per_mm")
        if v is None:
            continue
        r["interval_parts"]["forward_model_per_mm"] = float(rel * v)
        r["ci95_per_mm"] = _widen(ci, rel * v, rel * v)


def _add_prior_volume(summary, volumes, method):
    """The prior's own discretisation in each region's interval: a region whose
    prior (HP: the partial-volume basis; NP, SP: the node regions) holds a volume
    off the label map's by e % carries the yield that the data ask for spread over
    that volume, so its value may be off by about as much (a 3 mm inclusion on a
    'fast' mesh: +3 % with an interval of +-1 % before this part)."""
    key = "hard_prior_mm3" if method == "HP" else "soft_prior_mm3"
    for lab, r in summary["regions"].items():
        vol = (volumes or {}).get(int(lab))
        v, ci = r.get("yield_per_mm"), r.get("ci95_per_mm")
        if not vol or not vol["labelmap_mm3"] > 0 or v is None:
            continue
        rel = abs(vol[key] / vol["labelmap_mm3"] - 1.0)
        r["interval_parts"]["prior_volume_per_mm"] = float(rel * v)
        r["ci95_per_mm"] = _widen(ci, rel * v, rel * v)


def _add_segmentation(summary, seg, seg_mm, method="HP", as_segmented=None):
    """The segmentation's part of each region's 95 % interval: it reaches the
    values the region takes with its boundaries moved by the offsets, and its
    regions moved by the rigid moves, that the data do not rule out
    (``TissueModel.segmentation_shifts``: HP's relative changes, carried over to
    every method); a warning when the segmentation as given fits worse than a moved
    one, and for SP (:func:`_region_model_warning`) when the regions as constants do
    not explain the data. ``as_segmented`` ({label: 1/mm}, not None): this method's
    values were solved on the boundary the test chose (``quoted_offset_mm`` or
    ``quoted_translation``, :func:`_solve_on_quoted_boundary`) and these are its
    values on the segmentation as given; the interval then reaches them
    (``as_segmented_per_mm``) and half-way to the value at the next offset out, or
    at the rigid move twice (the boundary is known to a step: opening an eroded
    inclusion by the step does not give back its corners)."""
    summary["segmentation_mm"] = seg_mm
    if not seg:
        return
    q = _quoted_move(seg) if as_segmented is not None else None
    quoted = _quoted_shifts(seg, q)
    kept = [d for d, k in zip(seg["offsets_mm"], seg["kept"]) if k]
    trans = seg.get("translations") or []
    summary["segmentation"] = {"offsets_mm": seg["offsets_mm"], "not_ruled_out_mm": kept,
                               "best_offset_mm": seg["best_offset_mm"],
                               "best_move": seg.get("best_move", seg["best_offset_mm"]),
                               "unmoved_excess": seg.get("unmoved_excess"),
                               "excess_over_best": seg.get("excess_over_best"),
                               "optode_gains": seg.get("optode_gains", False),
                               "best_fit_over_noise": seg.get("best_fit_over_noise"),
                               "boundaries_explain_data": seg.get("boundaries_explain_data",
                                                                  True),
                               "region_model": seg.get("region_model"),
                               "best_at_edge": seg.get("best_at_edge", False),
                               "quoted_offset_mm": None if isinstance(q, dict) else q,
                               "rigid_moves": [{k: t[k] for k in ("moves_mm", "kept",
                                                                  "excess_over_best")}
                                               for t in trans],
                               "quoted_move_mm": q if isinstance(q, dict) else None}
    _segmentation_warnings(summary, seg, method, q)
    # HP's values on the boundary this method's value stands on
    ref = {lab: b + (0.0 if quoted is None else quoted[0][lab])
           for lab, b in seg["base"].items()}
    if method == "SP":
        _reach_region_fit(summary, ref)
    for lab, r in summary["regions"].items():
        base, at = seg["base"].get(int(lab)), ref.get(int(lab))
        v = r.get("yield_per_mm")
        if base is None or v is None or (q is None and not base > 0):
            continue
        # the region's value with its boundaries at each offset: this method's value
        # moved by HP's relative change from the boundary it stands on (a change of
        # HP's value where that is not positive). Not quoted unless the data choose
        # the boundary by far (SEGMENTATION_QUOTE_EXCESS): on correctly segmented
        # scenes the model's own error made a boundary moved by a third of a
        # millimetre fit better, and its value was 2.4x (docs/validation.md,
        # "Estimating the boundary with the yield")
        scale = v / at if at > 0 else 1.0

        def value(dv):
            return v + (base + dv - at) * scale

        vals = [value(dv) for dv in seg["shifts"][int(lab)]]
        r["segmentation_values_per_mm"] = vals
        moved = [value(dv) - v for dv, k in zip(seg["shifts"][int(lab)], seg["kept"]) if k]
        if trans:
            r["rigid_move_values_per_mm"] = [value(t["shifts"][int(lab)]) for t in trans]
            moved += [value(t["shifts"][int(lab)]) - v for t in trans if t["kept"]]
        if q is not None:
            given = as_segmented.get(int(lab), value(0.0))
            r["as_segmented_per_mm"] = given
            outer = (_outer_value(seg["offsets_mm"], seg["offsets_mm"].index(q), vals, given)
                     if quoted[1] is None else value(quoted[1][int(lab)]))
            moved += [given - v, 0.5 * (outer - v)]
        lo, hi = min([0.0] + moved), max([0.0] + moved)
        r["interval_parts"]["segmentation_shift_per_mm"] = [lo, hi]
        # added to the other parts (as they are to each other): a boundary off moves
        # the value whatever the noise did
        r["ci95_per_mm"] = _widen(r.get("ci95_per_mm"), -lo, hi)


def _quoted_shifts(seg, q):
    """HP's change at the quoted move ``q`` ({label: 1/mm}) and, for a rigid move, at
    the same move twice ({label: 1/mm}; None for an offset); None where nothing is
    quoted."""
    if q is None:
        return None
    if not isinstance(q, dict):
        iq = seg["offsets_mm"].index(q)
        return {lab: sh[iq] for lab, sh in seg["shifts"].items()}, None
    trans = seg["translations"]
    it = seg["quoted_translation"]
    outer = [t for t in trans if t["outer_of"] == it]
    return trans[it]["shifts"], outer[0]["shifts"]


def _segmentation_warnings(summary, seg, method, q):
    """The segmentation test's warnings: SP's regions-as-constants model
    (:func:`_region_model_warning`), no boundary tried explaining the data, and the
    segmentation as given ruled out (``q``: the move whose values are quoted)."""
    if method == "SP":
        text = _region_model_warning(seg.get("region_model"))
        if text:
            summary["warnings"].append(text)
    moves = ("moved by up to "
             f"{max(abs(d) for d in seg['offsets_mm']):.2g} mm"
             + (" or shifted by a step along each axis" if seg.get("translations") else ""))
    if seg.get("boundaries_explain_data") is False:
        summary["warnings"].append(
            f"no boundary the segmentation test tried ({moves}) explains the data, even "
            f"with each optode's gain fitted ({seg['best_fit_over_noise']:.2g} times the "
            "stated noise at best): the segmentation (shifted, missed or false "
            "inclusions), the optical properties or dye outside the labels may be off; "
            "none is ruled out, and the intervals reach the values of them all")
    if seg["unmoved_ruled_out"]:
        # a warning at any fit grade: on the model with the dye's absorption the
        # test no longer rules out correct segmentations at fair fits (docs/
        # reconstruction.md, "The segmentation test runs on the model with the dye's
        # absorption")
        how = move_text(seg.get("best_move", seg["best_offset_mm"]))
        summary["warnings"].append(
            f"the prior's regions fit the data better {how} than as segmented: the "
            "segmentation is likely off (or the model is: see the fit); " + (
                f"the values are those of the regions {how} (as_segmented_per_mm: the "
                "segmentation's own), and " if q is not None else "") +
            ("it is the last of those tried, so the data's best lies beyond them: none "
             "is ruled out, and the intervals reach the values of them all "
             if seg.get("best_at_edge") else
             "the intervals reach the values of the segmentations the data allow ") +
            "(segmentation_values_per_mm, rigid_move_values_per_mm)")


def _outer_value(offsets, iq, values, given):
    """The value at the offset next out from ``offsets[iq]`` (away from the
    segmentation as given; ``values`` per offset, ``given`` at 0); past the last
    offset, the value as far again as the step in."""
    q = offsets[iq]
    step = 1 if q > 0 else -1
    j = iq + step
    if 0 <= j < len(offsets) and (offsets[j] - q) * step > 0:
        return values[j]
    k = iq - step
    inner = values[k] if 0 <= k < len(offsets) and offsets[k] * q > 0 else given
    return 2.0 * values[iq] - inner


def _reach_region_fit(summary, base):
    """SP's interval reaching the regions-as-constants fit of the same data (HP's
    value in the segmentation test's unmoved solve, ``base`` {label: 1/mm}).
    SP's value is its image resolution-corrected under that very model (docs/
    reconstruction.md, "SP's value"), so where the two differ by more than the
    noise, the model's error shows in how each estimator reads it, and neither
    difference is noise: the demo's tube (balanced) had SP 16-29 % low with HP
    within 2-20 %, and SP's interval at 5.7 mm ended below the truth with no
    warning. The part is the signed difference HP - SP [1/mm]."""
    for lab, r in summary["regions"].items():
        hp, v = base.get(int(lab)), r.get("yield_per_mm")
        if hp is None or v is None or not np.isfinite(hp):
            continue
        d = float(hp - v)
        r["interval_parts"]["region_fit_difference_per_mm"] = d
        r["ci95_per_mm"] = _widen(r.get("ci95_per_mm"), max(-d, 0.0), max(d, 0.0))


def _region_model_warning(region_model):
    """SP quotes the value that its damped image would have come from under the
    regions-as-constants model (docs/reconstruction.md, "SP's value"); HP is that
    model's fit of the same data (the segmentation test's unmoved solve). Where
    that fit is poor, or a region's data ask for a negative yield, the model is
    wrong for these data (a segmentation off, optics, or dye the regions miss)
    and SP's value and interval inherit it, whatever SP's own, more flexible, fit
    says: the family's SP misses with a 1 mm segmentation error and no warning
    were all such scenes (docs/validation.md). Returns the warning, or None."""
    if not region_model:
        return None
    fit = region_model.get("fit") or {}
    poor = fit.get("grade") in ("poor", "fails")
    negative = region_model.get("negative_regions") or []
    if not poor and not negative:
        return None
    why = []
    if poor:
        why.append(f"the hard prior fits them to {fit['residual_over_noise']:.2g} times "
                   "the stated noise")
    if negative:
        why.append(f"region(s) {negative} would need a negative yield")
    return ("SP's value assumes each labelled region holds one yield, and that model does "
            f"not explain these data ({'; '.join(why)}): the "
            "segmentation, the optical properties or dye outside the labelled regions may "
            "be off, and the value may be off by more than its interval says")


def _fit_notes(summary, settings):
    """Notes on a fit the solver graded "fair" (its residual 2-5 times the stated
    noise: the model's own error shows, and the intervals count it), and where
    the fit is worse than good at a coarse level, the level that models the light
    more closely."""
    fit = summary["solver"]["diagnostics"].get("fit")
    if not fit or fit["grade"] == "good":
        return []
    out = []
    ratio = fit["residual_over_noise"]
    if fit["grade"] == "fair":
        out.append(f"the model explains the data to {ratio:.2g} times the stated noise: its own "
                   "error is counted in the 95 % intervals (interval_parts."
                   "model_error_bound_per_mm)")
    if settings.get("level") in ("fast", "balanced"):
        out.append(f"accuracy '{settings['level']}': a finer level meshes the light's paths "
                   "more finely; the mesh's own error is a likely part of the misfit")
    return out


def _once(texts):
    """Warnings caught during a reconstruction, each said once: the diffusion
    validity warning of each wavelength comes from every model the passes build
    (self-absorption feedback), so only its lowest musp/mua is kept."""
    import re

    out, worst = [], {}
    for text in texts:
        m = re.match(r"^(\w+): musp/mua = ([0-9.eE+-]+) < 10", text)
        if m:
            key, ratio = m.group(1), float(m.group(2))
            if key not in worst or ratio < worst[key][0]:
                worst[key] = (ratio, text)
            continue
        if text not in out:
            out.append(text)
    return [t for _, t in worst.values()] + out


def _result(lm, optics, acquisition, tm, mesh, res, passes, method, lam, target, data_model,
            settings, h, roi_info, notes, timings, src, det, d_src, d_det, seconds):
    """The summary and volumes of one method's solution."""
    vol = nodal_to_grid(mesh, res.yield_per_mm, lm)
    # a diverged run says so once: unless a warning of the result opens with the
    # stop reason (the self-absorption feedback's), the reason is a note of its own
    if res.diverged and not res.stop_warned:
        notes.append(res.stop_reason)
    # the solver's own diagnostics (under-determination, fit, damping): a
    # result it warns about may be far from the truth, for the reasons given
    for w in res.warnings:
        if w not in notes:
            notes.append(w)
    # One definition of a region's yield: the volume-weighted mean over the label
    # (its voxels inside the reconstruction's region) of the reconstructed yield:
    # for HP its region value (the partial-volume model is that value over the
    # label), for NP and SP the yield volume's mean over the label; the SD is of
    # that same number (TissueModel.region_weights). The volume itself is the P1
    # field at the voxel centres: for HP its mean over a small label is lower (the
    # rim is shared with the neighbours), so the summary names both.
    conf = res.region_confidence
    inclusions = set(lm.inclusion_labels())
    regions = {}
    for lab in tm.region_labels:
        vox = lm.labels_kji == lab
        c = conf.get(int(lab), {})
        regions[str(int(lab))] = {
            "yield_per_mm": c.get("mean_yield_per_mm"),
            "sd_per_mm": c.get("sd_yield_per_mm"),
            "ci95_per_mm": _with_feedback(c.get("ci95_yield_per_mm"),
                                          c.get("feedback_pending_per_mm")),
            "interval_parts": {"noise_sd_per_mm": c.get("sd_yield_per_mm"),
                               "feedback_pending_per_mm": c.get("feedback_pending_per_mm"),
                               "resolution_corrected_per_mm":
                               c.get("resolution_corrected_per_mm"),
                               "model_error_bound_per_mm": c.get("model_error_bound_per_mm")},
            "volume_mean_per_mm": float(vol[vox].mean()) if vox.any() else None,
            "name": optics.names.get(int(lab)),
        }
        if "sp_value" in c:
            regions[str(int(lab))].update({"image_mean_per_mm": c["image_mean_yield_per_mm"],
                                           "value_from": c["sp_value"]})
            # said for the inclusions: a background's yield near zero makes any
            # ratio meaningless there (its value is the image's mean, silently)
            ratio = c["sp_correction_refused"]
            if ratio is not None and int(lab) in inclusions:
                w = (f"SP: label {int(lab)}'s soft-prior image and its region-wise constant "
                     f"correction disagree (the resolution correction, {ratio:.3g}x, is beyond "
                     f"{SP_CORRECTION_MAX:g}x): the segmentation may be off; its yield is the "
                     "image's mean over the label")
                if w not in notes:
                    notes.append(w)
    k, j, i = np.unravel_index(int(np.argmax(vol)), vol.shape)
    peak_local = np.array([i, j, k], float) * lm.spacing_mm
    cen = _half_max_centroid(vol, lm)
    summary = {
        "method": method, "lambda": lam, "data_model": data_model,
        "target": target,
        "regions": regions,
        "regions_note": ("yield_per_mm: the region's yield, the volume-weighted mean over its "
                         "label (HP: the region's value; SP: that mean corrected for the "
                         "soft prior's smoothing across the region's rim, value_from and "
                         "image_mean_per_mm say which and what the image holds), and "
                         "sd_per_mm its standard deviation "
                         "from the noise; ci95_per_mm its 95 % interval (the noise, what the "
                         "damped solver leaves unresolved, the model's error bound: "
                         "interval_parts; docs/reconstruction.md, 'Intervals'); "
                         "volume_mean_per_mm: the yield volume's mean over the label (the P1 "
                         "field at voxel centres; for HP lower than the region's value where "
                         "the label is small: quote yield_per_mm); "
                         "segmentation_values_per_mm: the value with the label's boundaries "
                         "moved by each of segmentation.offsets_mm; "
                         "rigid_move_values_per_mm: with the regions moved by each of "
                         "segmentation.rigid_moves; as_segmented_per_mm: "
                         "where the values stand on the boundary the data chose "
                         "(segmentation.quoted_offset_mm or quoted_move_mm), the value as "
                         "segmented"),
        "peak_yield_per_mm": float(vol.max()),
        "peak_ras_mm": lm.to_ras(peak_local)[0].tolist(),
        "peak_label": int(lm.labels_kji[k, j, i]),
        "target_centroid_ras_mm": None if cen is None else lm.to_ras(cen)[0].tolist(),
        "target_label_centroid_ras_mm": None if target is None else
        lm.to_ras(lm.region_centroid_local(target))[0].tolist(),
        "warnings": notes,
        "measurements": acquisition.n_measurements,
        "sources": len(src), "detectors": len(det),
        "moved_to_surface_mm": {"sources_max": float(d_src.max()),
                                "detectors_max": float(d_det.max())},
        "accuracy": dict(settings, grading="bisection" if mesh.meta.get("method") == "bisection"
                         else bool(mesh.meta.get("coarse_mm", h) > h + 1e-9)),
        "region_of_interest": roi_info,
        "mesh": {"nodes": mesh.n_nodes, "elements": mesh.n_elements, "element_mm": h,
                 "coarse_element_mm": mesh.meta.get("coarse_mm"),
                 "volume_error_pct": mesh.meta.get("volume_error_pct", {}),
                 "surface_fit_mm": mesh.meta.get("surface_fit_mm")},
        "solver": {"iterations": res.iterations, "stop_reason": res.stop_reason,
                   "clipped_fraction": res.clipped_fraction,
                   "self_absorption_peaks": passes,
                   "residual_ss": res.residual, "initial_residual_ss": res.residual_history[0],
                   "diagnostics": dict(res.diagnostics)},
        "timings": timings,
        "seconds": seconds,
    }
    return {"summary": summary, "yield_kji": vol, "mesh": mesh, "yield_nodes": res.yield_per_mm,
            "sources_ras_mm": lm.to_ras(src), "detectors_ras_mm": lm.to_ras(det),
            "result": res, "model": tm}


def write_reconstruction(out_dir, lm, result):
    """``out_dir/yield.nrrd`` (the yield volume on the label map's grid: same
    origin, spacing and direction; float32, 1/mm) and ``reconstruction.json``
    (the summary), written as one transaction: a reader sees the old folder or
    the new one, never half of it.  Returns the summary with ``output``."""
    from pathlib import Path

    from fluoguide import atomic
    from fluoguide.jsonable import dumps
    from fluoguide.labelmap_io import write_volume_nrrd

    out = Path(out_dir)
    summary = dict(result["summary"])
    summary["output"] = str((out / "yield.nrrd").resolve())
    try:
        with atomic.staged_folder(out, last=("reconstruction.json",)) as stage:
            write_volume_nrrd(stage / "yield.nrrd", result["yield_kji"], lm.spacing_mm,
                              lm.origin_mm, lm.direction)
            (stage / "reconstruction.json").write_text(dumps(summary), encoding="utf-8")
    except OSError as exc:
        raise atomic.output_error(exc, out) from None
    return summary
