"""Tomography on any label map: file formats, frames, optodes on the surface,
the region of interest, and a small end-to-end case (the issue's scene runs in
Testing/Python/test_tomo_cli.py)."""

import json

import numpy as np
import pytest

from fluoguide.errors import FluoInputError
from fluoguide.phantoms import ellipsoid_inclusion_labelmap, ellipsoid_inclusion_optics
from FluoTomoLib.tomography import (Acquisition, LabelMap, optics_from_dict, place_on_surface,
                                    read_acquisition, read_optics, write_acquisition)

OPTICS = ellipsoid_inclusion_optics()

OBLIQUE = (np.array([[np.cos(0.5), -np.sin(0.5), 0], [np.sin(0.5), np.cos(0.5), 0], [0, 0, 1.0]])
           @ np.array([[1.0, 0, 0], [0, np.cos(0.3), -np.sin(0.3)], [0, np.sin(0.3), np.cos(0.3)]]))


def small_scene(direction=((-1, 0, 0), (0, -1, 0), (0, 0, 1)), spacing=(0.8, 0.9, 1.0)):
    return ellipsoid_inclusion_labelmap(spacing_mm=spacing, direction=direction,
                                        semi_axes_mm=(14.0, 12.0, 8.0), inclusion_gap_mm=2.5,
                                        inclusion_offset_mm=(1.0, -1.0))


def _lm(sc):
    return LabelMap(sc["labels_kji"], sc["spacing_mm"], sc["origin_mm"], sc["direction"])


# ------------------------------------------------------------------ optics.json

def test_optics_file_reads_and_names_every_bad_field(tmp_path):
    p = tmp_path / "optics.json"
    p.write_text(json.dumps(OPTICS))
    o = read_optics(p)
    assert o.n == 1.37 and o.labels == [3, 7] and o.mua_per_yield[0] > 20
    assert o.excitation[7] == (0.012, 1.1) and o.emission[3] == (0.008, 0.9)
    o.check_labels([3, 7])
    with pytest.raises(FluoInputError, match=r"\[5\]"):
        o.check_labels([3, 5, 7])
    bad = [
        ({"excitation": {"3": {"mua_per_mm": -0.1, "musp_per_mm": 1}}}, "excitation.3.mua_per_mm"),
        ({"excitation": {"3": {"mua_per_mm": float("nan"), "musp_per_mm": 1}}}, "finite"),
        ({"excitation": {"3": {"mua_per_mm": 0.01, "musp": 1}}}, "unknown key"),
        ({"excitation": {"0": {"mua_per_mm": 0.01, "musp_per_mm": 1}}}, "label 0 is air"),
        ({"excitation": {"x": {"mua_per_mm": 0.01, "musp_per_mm": 1}}}, "integers"),
        ({"emission": {"3": {"mua_per_mm": 0.01, "musp_per_mm": 1}}}, "same labels"),
        ({"n": 0.5}, "n"),
        ({"fluorophore": "fluorescein"}, "fluorophore"),
        ({"colour": "red"}, "unknown key"),
        ({"boundary": "exact"}, "boundary"),
    ]
    for change, needle in bad:
        doc = json.loads(json.dumps(OPTICS))
        doc.update(change)
        with pytest.raises(FluoInputError, match=needle.replace(".", r"\.")):
            optics_from_dict(doc, file="optics.json")
    # the boundary constant: the library's default unless optics.json names one,
    # and then for every model built from it (simulation and reconstruction alike)
    assert o.boundary is None and "boundary" not in o.nodal([3, 7], np.eye(2))[0]
    emp = optics_from_dict(dict(OPTICS, boundary="empirical"))
    px, pm = emp.nodal([3, 7], np.eye(2))
    assert px["boundary"] == pm["boundary"] == "empirical"
    assert optics_from_dict(emp.to_json()).boundary == "empirical"
    p.write_text("{not json")
    with pytest.raises(FluoInputError, match="line 1"):
        read_optics(p)


# ------------------------------------------------------------------ acquisition folders

def _acq(S=3, D=4):
    src = np.array([[0, 0, 0.0], [2, 0, 0], [4, 0, 0]])[:S]
    det = np.array([[0, 1, 0.0], [2, 1, 0], [4, 1, 0], [6, 1, 0]])[:D]
    data = np.arange(1, S * D + 1, dtype=float).reshape(S, D) * 1e-6
    mask = np.ones((S, D), bool)
    mask[0, 0] = False
    return Acquisition(src, det, data, mask)


def test_acquisition_folder_round_trip_and_units(tmp_path):
    acq = _acq()
    write_acquisition(tmp_path / "acq", acq, simulation={"engine": "test"})
    back = read_acquisition(tmp_path / "acq")
    assert np.array_equal(back.mask, acq.mask)
    assert np.allclose(back.data, acq.data, rtol=1e-8)
    assert np.allclose(back.sources_ras_mm, acq.sources_ras_mm)
    assert back.meta["simulation"]["engine"] == "test"
    assert "-" in (tmp_path / "acq" / "data.csv").read_text().splitlines()[0]
    # by hand: inline points, W/mm^2 with one laser power per source, null = unused
    doc = {"units": "W/mm^2", "laser_power_w": [0.01, 0.02],
           "sources_ras_mm": [[0, 0, 0], [1, 0, 0]], "detectors_ras_mm": [[3, 0, 0], [4, 0, 0]],
           "data": [[1e-7, None], [4e-7, 8e-7]], "exclude_mm": 2.5}
    (tmp_path / "hand").mkdir()
    (tmp_path / "hand" / "acquisition.json").write_text(json.dumps(doc))
    h = read_acquisition(tmp_path / "hand")
    assert h.mask.tolist() == [[True, False], [False, True]]       # (1,3)-(0,3): 2 mm < 2.5
    assert np.isclose(h.data[0, 0], 1e-5) and np.isclose(h.data[1, 1], 4e-5)
    assert h.n_measurements == 2


@pytest.mark.parametrize("change, needle", [
    ({"data": [[1e-6, 2e-6]]}, "one row per source"),
    ({"data": [[1e-6, float("nan")], [1e-6, 1e-6]]}, "finite"),
    ({"data": [[0.0, None], [None, 0.0]]}, "every used measurement is zero"),
    ({"sources_ras_mm": [[0, 0]]}, "x, y, z"),
    ({"units": "counts"}, "refractive index"),
    ({"units": "W/mm^2"}, "laser_power_w"),
    ({"units": "lux"}, "units"),
    ({"data": "../../etc/passwd"}, "in the acquisition folder"),
    ({"bogus": 1}, "unknown key"),
    ({"format": "something-else"}, "format"),
])
def test_bad_acquisition_files_name_the_field(tmp_path, change, needle):
    doc = {"sources_ras_mm": [[0, 0, 0], [1, 0, 0]], "detectors_ras_mm": [[3, 0, 0], [4, 0, 0]],
           "data": [[1e-6, 2e-6], [3e-6, 4e-6]]}
    doc.update(change)
    (tmp_path / "acquisition.json").write_text(json.dumps(doc))
    with pytest.raises(FluoInputError, match=needle):
        read_acquisition(tmp_path)


def test_csv_data_nan_and_log_data_refused(tmp_path):
    acq = _acq()
    write_acquisition(tmp_path / "a", acq)
    f = tmp_path / "a" / "data.csv"
    rows = f.read_text().splitlines()
    f.write_text("\n".join(["nan" + rows[0][1:]] + rows[1:]) + "\n")
    with pytest.raises(FluoInputError, match="finite"):
        read_acquisition(tmp_path / "a")
    f.write_text("\n".join(["1e-6,abc,1e-6,1e-6"] + rows[1:]) + "\n")
    with pytest.raises(FluoInputError, match="line 1 is not numeric"):
        read_acquisition(tmp_path / "a")
    f.write_text("\n".join([rows[0]] + [rows[1].replace(rows[1].split(",")[1], "-1e-7")]
                           + rows[2:]) + "\n")
    neg = read_acquisition(tmp_path / "a")           # linear data may be negative (noise)
    with pytest.raises(FluoInputError, match="log data model"):
        neg.check_for_log()
    f.write_text("\n".join(rows[:2] + ["1,2"]) + "\n")
    with pytest.raises(FluoInputError, match="different lengths|one row per source"):
        read_acquisition(tmp_path / "a")


# ------------------------------------------------------------------ geometry

@pytest.mark.parametrize("direction", [np.eye(3), np.diag([-1.0, -1, 1]), OBLIQUE])
def test_frames_and_optodes_on_the_surface(direction):
    sc = small_scene(direction)
    lm = _lm(sc)
    p = np.array([[1.0, 2.0, 3.0], [-4.0, 5.0, 6.0]]) + sc["origin_mm"]
    assert np.allclose(lm.to_ras(lm.to_local(p)), p)
    top = sc["surface_point_ras_mm"]
    # the surface point above the inclusion is on the surface (voxel-scale offset)
    q, dist = place_on_surface(lm, top[None], "sources")
    assert dist[0] < 0.6 and np.allclose(lm.to_ras(q)[0], top, atol=0.6)
    # 1 mm above it: moved back, the distance reported
    normal = direction @ np.array([0, 0, 1.0])
    q, dist = place_on_surface(lm, (top + 1.0 * normal)[None], "sources")
    assert 0.4 < dist[0] < 1.6
    # 5 mm off: refused, naming the point and the distance
    with pytest.raises(FluoInputError, match=r"detectors\[1\].*mm from it"):
        place_on_surface(lm, np.stack([top, top + 5.0 * normal]), "detectors")
    # the centroid of the inclusion, in RAS
    assert np.allclose(lm.to_ras(lm.region_centroid_local(7))[0], sc["inclusion_centre_ras_mm"],
                       atol=0.3)
    assert lm.default_target() == 7


def test_label_maps_refused_with_the_field():
    with pytest.raises(FluoInputError, match="no tissue"):
        LabelMap(np.zeros((3, 3, 3), np.uint8), (1, 1, 1), (0, 0, 0))
    with pytest.raises(FluoInputError, match="orthonormal"):
        LabelMap(np.ones((3, 3, 3), np.uint8), (1, 1, 1), (0, 0, 0), np.diag([1.0, 2.0, 1.0]))
    with pytest.raises(FluoInputError, match="spacing"):
        LabelMap(np.ones((3, 3, 3), np.uint8), (1, 0, 1), (0, 0, 0))
    with pytest.raises(FluoInputError, match=">= 0"):
        LabelMap(-np.ones((3, 3, 3), np.int16), (1, 1, 1), (0, 0, 0))


def test_region_of_interest_grows_until_the_cut_is_within_tolerance():
    """The cut faces are Robin boundaries: their estimated effect on the data
    is within the tolerance, and a tighter tolerance never gives a smaller
    region (graded against the whole tissue, not against itself)."""
    from FluoTomoLib.tomography import choose_roi, default_scan

    sc = ellipsoid_inclusion_labelmap(spacing_mm=(1.0, 1.0, 1.0), semi_axes_mm=(30, 24, 9),
                                      inclusion_gap_mm=2.0)
    lm = _lm(sc)
    optics = optics_from_dict(OPTICS)
    s, d, _ = default_scan(lm, 7)
    src, _ = place_on_surface(lm, s, "s")
    det, _ = place_on_surface(lm, d, "d")
    mask = np.linalg.norm(s[:, None] - d[None], axis=2) > 3
    loose, info_l = choose_roi(lm, optics, src, det, mask, 7, tol_pct=5.0)
    tight, info_t = choose_roi(lm, optics, src, det, mask, 7, tol_pct=0.5)
    for info, tol in ((info_l, 5.0), (info_t, 0.5)):
        assert info["whole_tissue"] or info["truncation_max_pct"] <= tol, info
    assert info_t["margin_mm"] >= info_l["margin_mm"]
    vol = lambda r: np.prod(r[1::2] - r[0::2])  # noqa: E731
    assert vol(tight) >= vol(loose)
    t_lo, t_hi = lm.tissue_bounds_local()
    assert np.all(loose[0::2] >= t_lo - 1e-9) and np.all(loose[1::2] <= t_hi + 1e-9)


# ------------------------------------------------------------------ end to end, small

def test_small_scene_simulated_and_reconstructed_in_any_direction(tmp_path):
    """A quick end-to-end check on a small body (the issue's scene and its
    tolerances: test_tomo_cli.py, slow): simulate on the whole-map mesh,
    reconstruct HP on another mesh of the region of interest; the yield volume
    lies on the label map's grid and peaks inside the inclusion in RAS."""
    from fluoguide.labelmap_io import read_volume_nrrd
    from FluoTomoLib.tomography import (reconstruct_labelmap, simulate_acquisition,
                                        write_reconstruction)

    sc = small_scene(OBLIQUE, spacing=(0.9, 0.8, 1.0))
    lm = _lm(sc)
    # a dye whose absorption is not modelled: the problem is linear in the yield
    # (an absorbing 2 ug/mL ICG sphere this close to the surface is nearly
    # saturated: docs/tomography-own-scene.md)
    optics = optics_from_dict(dict(OPTICS, fluorophore=None))
    acq, info = simulate_acquisition(lm, optics, {7: 2.6e-3}, noise_pct=1.0, seed=2,
                                     accuracy="fast", scan={"sources_per_side": 3,
                                                            "detectors_per_side": 5,
                                                            "detector_pitch_mm": 2.0})
    assert info["domain"] == "whole label map" and info["engine"] == "fem"
    out = reconstruct_labelmap(lm, optics, acq, method="HP", accuracy="fast")
    s = out["summary"]
    err = (s["regions"]["7"]["yield_per_mm"] - 2.6e-3) / 2.6e-3
    assert abs(err) < 0.15, s["regions"]
    assert s["peak_label"] == 7
    assert np.linalg.norm(np.array(s["peak_ras_mm"]) - sc["inclusion_centre_ras_mm"]) <= 3.0
    summary = write_reconstruction(tmp_path / "out", lm, out)
    arr, sp, org, d = read_volume_nrrd(tmp_path / "out" / "yield.nrrd")
    assert arr.shape == lm.labels_kji.shape
    assert np.allclose(sp, lm.spacing_mm) and np.allclose(org, lm.origin_mm, atol=1e-4)
    assert np.allclose(d, lm.direction, atol=1e-6)
    assert np.all(arr[lm.labels_kji == 0] == 0) and arr.max() == pytest.approx(
        s["peak_yield_per_mm"], rel=1e-5)
    assert json.loads((tmp_path / "out" / "reconstruction.json").read_text())["method"] == "HP"
    assert summary["output"].endswith("yield.nrrd")


@pytest.mark.parametrize("grading", [False, "bisection"])
def test_the_logic_builds_the_mesh_the_reconstruction_uses(tmp_path, grading):
    """FluoTomoLogic.buildMesh with an acquisition builds the mesh reconstruct()
    would build for it (one set-up: reconstruct.labelmap_mesh), the graded one
    too; a graded mesh without the optodes it is graded from is refused."""
    from fluoguide import mrml_io
    from fluoguide.labelmap_io import write_volume_nrrd
    from FluoTomo import FluoTomoLogic
    from FluoTomoLib.tomography import default_scan
    from FluoTomoLib.tomography.accuracy import accuracy_settings
    from FluoTomoLib.tomography.reconstruct import labelmap_mesh

    sc = small_scene()
    lm = _lm(sc)
    write_volume_nrrd(tmp_path / "labels.nrrd", sc["labels_kji"], sc["spacing_mm"],
                      sc["origin_mm"], sc["direction"])
    (tmp_path / "optics.json").write_text(json.dumps(OPTICS))
    src, det, _ = default_scan(lm, 7)            # RAS mm
    mask = np.linalg.norm(src[:, None] - det[None], axis=2) > 3
    write_acquisition(tmp_path / "acq", Acquisition(src, det, np.where(mask, 1e-6, 0), mask))
    logic = FluoTomoLogic(mrml_io.new_scene())
    lab = logic.loadLabelMap(tmp_path / "labels.nrrd")
    node = logic.buildMesh(lab, acquisition=tmp_path / "acq", optics=tmp_path / "optics.json",
                           accuracy="fast", grading=grading)
    built = mrml_io.get_json_attribute(node, "FluoTomo.Mesh")
    acq = read_acquisition(tmp_path / "acq")
    ps, _ = place_on_surface(lm, acq.sources_ras_mm, "sources")
    pd, _ = place_on_surface(lm, acq.detectors_ras_mm, "detectors")
    mesh, _, _ = labelmap_mesh(lm, optics_from_dict(OPTICS), ps, pd, acq.mask, 7,
                               accuracy_settings("fast"), grading)
    assert built["nodes"] == mesh.n_nodes and built["elements"] == mesh.n_elements
    assert (mesh.meta.get("method") == "bisection") == (grading == "bisection")
    with pytest.raises(FluoInputError, match="graded from the optodes"):
        logic.buildMesh(lab, grading="bisection")


# ------------------------------------------------------------------ the Monte Carlo engine

@pytest.mark.slow
def test_monte_carlo_engine_agrees_with_the_fem_engine():
    """``simulate_acquisition(engine="mc")`` (MCX-CL photon transport on the
    voxels, emission by reciprocity, exitance x 2A) against the FEM engine on
    its own finer mesh, on a flat-topped block (no staircase under the optodes)
    with labels 3 and 7 (MCX's media are 1..L), cubic 1 mm voxels, the
    direction diag(-1, -1, 1) and an origin far from zero.  Tolerance: 12 %
    (the diffusion model near a 4 mm fluorescent cube 2 mm under the surface,
    as FluoTomoLib.montecarlo's own small-case test) plus 2.5 photon-noise
    standard errors of the two MC runs."""
    from FluoTomoLib.montecarlo.engine import engine_available
    from FluoTomoLib.tomography import simulate_acquisition

    if not engine_available("mcxcl"):
        pytest.skip("MCX-CL is not installed (the 'mc' extra, `make system-deps`)")
    nx, ny, nz = 36, 24, 14
    lab = np.full((nz + 2, ny, nx), 3, np.int16)
    lab[nz:] = 0                       # air above the skin: the top is skin, not a cut
    lab[nz - 6:nz - 2, ny // 2 - 2:ny // 2 + 2, nx // 2 - 2:nx // 2 + 2] = 7
    d = np.diag([-1.0, -1.0, 1.0])
    origin = np.array([240.0, 130.0, -410.0])
    lm = LabelMap(lab, np.ones(3), origin, d)
    top = origin[2] + (nz - 0.5)
    centre = origin + d @ np.array([(nx - 1) / 2, (ny - 1) / 2, 0.0])
    src = np.array([[centre[0] - 6.0, centre[1], top]])
    det = np.array([[centre[0] + 2.0, centre[1], top], [centre[0] + 5.0, centre[1] + 1.0, top]])
    optics = optics_from_dict(OPTICS)
    kw = dict(noise_pct=0.0, seed=5, exclude_mm=0.0)
    mc, info = simulate_acquisition(lm, optics, {7: 0.01}, src, det, engine="mc",
                                    photons=20_000, **kw)
    fem, _ = simulate_acquisition(lm, optics, {7: 0.01}, src, det, engine="fem",
                                  accuracy="fine", **kw)
    assert info["engine"] == "mc" and info["runs"] == 2 and info["photons_per_run"] == 20_000
    assert not any("staircase" in w for w in info["warnings"]), info["warnings"]
    se = np.array(info["photon_noise_pct"]["max"]) / 100
    rel = np.abs(fem.clean / mc.clean - 1)
    assert np.all(rel <= 0.12 + 2.5 * se), (rel, se)


@pytest.mark.parametrize("methods, needle", [((), "no method"), (("HP", "XP"), "NP, SP or HP")])
def test_a_request_without_a_known_method_is_refused_before_any_work(methods, needle):
    from FluoTomoLib.tomography import reconstruct_labelmap_methods

    sc = small_scene()
    with pytest.raises(FluoInputError, match=needle):
        reconstruct_labelmap_methods(_lm(sc), optics_from_dict(ellipsoid_inclusion_optics()),
                                     _acq(), methods=methods)
