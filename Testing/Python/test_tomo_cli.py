"""``fluo tomo simulate`` / ``fluo tomo reconstruct`` and ``FluoTomoLogic`` on a
label map unlike the tube (issue #17): an ellipsoidal body with a 6 mm
spherical inclusion 4 mm below its curved top, anisotropic voxels, the
direction diag(-1, -1, 1), the origin far from zero.  Bad input: one line,
exit 2, nothing written."""

import json

import numpy as np
import pytest

from fluoguide.labelmap_io import read_volume_nrrd, write_volume_nrrd
from fluoguide.phantoms import ellipsoid_inclusion_optics
from small_cases import TRUE_YIELD, write_scene

OPTICS = ellipsoid_inclusion_optics()


def _one_line_exit_2(r, needle):
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and needle in lines[0], r.stderr
    assert "Traceback" not in r.stderr and r.stdout == ""


@pytest.fixture(scope="module")
def small(own_scene):
    """The shared own scene and its acquisition (conftest.py: fast settings)."""
    return own_scene.dir, own_scene.sc, own_scene.simulated


# slow: the first test of the file to ask for the shared own scene pays for its
# simulation, close to the fast tests' time limit on a loaded machine
@pytest.mark.slow
def test_simulate_writes_a_folder_a_person_can_read(small):
    d, sc, out = small
    doc = json.loads((d / "acq" / "acquisition.json").read_text())
    assert doc["units"] == "1/mm^2" and doc["simulation"]["domain"] == "whole label map"
    assert doc["simulation"]["yield_by_label"] == {"7": 0.0026}
    rows = (d / "acq" / "data.csv").read_text().splitlines()
    assert len(rows) == out["sources"] and all(len(r.split(",")) == out["detectors"]
                                               for r in rows)
    assert sum(r.count("-") for r in rows) > 0            # near-source pairs marked unused
    # the default scan's patch lies over the one inclusion, which it sees
    assert [p["targets"] for p in out["scan_patches"]] == [[7]]
    assert out["scan_coverage"]["7"]["seen"] and out["scan_coverage"]["7"]["pairs_seeing"] > 0
    assert doc["simulation"]["scan_coverage"]["regions"]["7"] == out["scan_coverage"]["7"]


@pytest.mark.parametrize("case", ["labels-missing", "off-surface", "off-surface-detector",
                                  "bad-noise", "bad-segmentation", "bad-noise-file",
                                  "wrong-shape", "nan",
                                  "negative-log", "bad-yield", "bad-accuracy-size"])
def test_bad_input_one_line_exit_2_nothing_written(small, tmp_path, case, fluo):
    d, sc, _ = small
    acq = tmp_path / "acq"
    import shutil

    shutil.copytree(d / "acq", acq)
    optics = d / "optics.json"
    extra = []
    needle = None
    if case == "labels-missing":
        doc = json.loads(json.dumps(OPTICS))
        del doc["excitation"]["7"], doc["emission"]["7"]
        optics = tmp_path / "optics.json"
        optics.write_text(json.dumps(doc))
        needle = "[7]"
    elif case == "off-surface":
        lines = (acq / "sources.csv").read_text().splitlines()
        x, y, z = (float(v) for v in lines[2].split(","))
        lines[2] = f"{x},{y},{z + 25.0}"               # 25 mm above the tissue (+z is up)
        (acq / "sources.csv").write_text("\n".join(lines) + "\n")
        # the point's own file, not data.csv (issue #33)
        needle = "sources.csv: sources[1]"
    elif case == "off-surface-detector":
        lines = (acq / "detectors.csv").read_text().splitlines()
        x, y, z = (float(v) for v in lines[3].split(","))
        lines[3] = f"{x},{y},{z + 25.0}"
        (acq / "detectors.csv").write_text("\n".join(lines) + "\n")
        needle = "detectors.csv: detectors[2]"
    elif case == "bad-noise":
        extra = ["--noise-pct", "0"]
        needle = "--noise-pct"
    elif case == "bad-segmentation":
        extra = ["--segmentation-mm", "-1"]
        needle = "--segmentation-mm"
    elif case == "bad-noise-file":
        doc = json.loads((acq / "acquisition.json").read_text())
        doc["noise_pct"] = "lots"
        (acq / "acquisition.json").write_text(json.dumps(doc))
        needle = "acquisition.json: noise_pct"
    elif case == "wrong-shape":
        rows = (acq / "data.csv").read_text().splitlines()
        (acq / "data.csv").write_text("\n".join(rows[:-1]) + "\n")
        needle = "one row per source"
    elif case == "nan":
        rows = (acq / "data.csv").read_text().splitlines()
        cells = rows[3].split(",")
        k = next(i for i, c in enumerate(cells) if c != "-")
        cells[k] = "nan"
        rows[3] = ",".join(cells)
        (acq / "data.csv").write_text("\n".join(rows) + "\n")
        needle = "finite"
    elif case == "negative-log":
        rows = (acq / "data.csv").read_text().splitlines()
        cells = rows[2].split(",")
        k = next(i for i, c in enumerate(cells) if c != "-")
        cells[k] = "-" + cells[k]
        rows[2] = ",".join(cells)
        (acq / "data.csv").write_text("\n".join(rows) + "\n")
        extra = ["--data-model", "log"]
        needle = "log data model"
    elif case == "bad-yield":
        r = fluo("tomo", "simulate", "--labels", d / "labels.nrrd", "--optics", optics,
                 "--yield", "7:abc", "--out", tmp_path / "out")
        _one_line_exit_2(r, "--yield")
        assert not (tmp_path / "out").exists()
        r = fluo("tomo", "simulate", "--labels", d / "labels.nrrd", "--optics", optics,
                 "--yield", "9:0.001", "--out", tmp_path / "out")
        _one_line_exit_2(r, "not in the label map")
        assert not (tmp_path / "out").exists()
        # the labels are checked by the Lib (default_scan's own check), before any work
        for bad, needle in (("9", "not in the label map"), ("7,x", "comma"),
                            ("7,7,7,7,7", "at most 4"), (",", "no target")):
            r = fluo("tomo", "simulate", "--labels", d / "labels.nrrd", "--optics", optics,
                     "--yield", "7:0.001", "--scan-targets", bad, "--out", tmp_path / "out")
            _one_line_exit_2(r, "--scan-targets")
            assert needle in r.stderr and not (tmp_path / "out").exists()
        r = fluo("tomo", "simulate", "--labels", d / "labels.nrrd", "--optics", optics,
                 "--yield", "7:0.001", "--target", "9", "--out", tmp_path / "out")
        _one_line_exit_2(r, "--target")
        assert "not in the label map" in r.stderr and not (tmp_path / "out").exists()
        return
    elif case == "bad-accuracy-size":
        extra = ["--element-mm", "-1"]
        needle = "recon_mm"
    r = fluo("tomo", "reconstruct", "--labels", d / "labels.nrrd", "--optics", optics,
             "--acquisition", acq, "--method", "HP", "--accuracy", "fast", *extra,
             "--out", tmp_path / "out", "--json")
    _one_line_exit_2(r, needle)
    assert not (tmp_path / "out").exists()


@pytest.mark.slow       # one HP reconstruction of the own scene (about 15 s quiet)
def test_the_interval_holds_the_truth_and_says_what_it_is_made_of(small, tmp_path, fluo):
    """Issue #31 items 4 and 5 through the CLI: the acquisition's simulated noise
    reaches the solver (1 %), the fit is graded against it, the target's 95 %
    interval holds the true yield and names its parts; a stated noise 100x
    lower makes the fit poor, warned, and the interval no narrower."""
    d, sc, _ = small
    out = {}
    for name, extra in (("stated", []), ("understated", ["--noise-pct", "0.01"])):
        r = fluo("tomo", "reconstruct", "--labels", d / "labels.nrrd", "--optics",
                 d / "optics.json", "--acquisition", d / "acq", "--accuracy", "fast",
                 "--out", tmp_path / name, *extra, "--json")
        assert r.returncode == 0, r.stderr[-2000:]
        out[name] = json.loads(r.stdout)
    s = out["stated"]
    assert s["noise"] == {"pct": 1.0, "source": "acquisition",
                          "note": "one SD per measurement [%], tested against the fit"}
    r7 = s["regions"]["7"]
    lo, hi = r7["ci95_per_mm"]
    assert lo <= TRUE_YIELD <= hi, (lo, r7["yield_per_mm"], hi)
    assert set(r7["interval_parts"]) >= {"noise_sd_per_mm", "model_error_bound_per_mm",
                                         "resolution_corrected_per_mm",
                                         "segmentation_shift_per_mm", "prior_volume_per_mm",
                                         "forward_model_per_mm"}
    assert s["segmentation_mm"] == pytest.approx(0.5 * max(sc["spacing_mm"]))
    assert s["solver"]["diagnostics"]["fit"]["grade"] in ("good", "fair", "poor")
    u = out["understated"]
    assert u["noise"]["source"] == "given"
    assert u["solver"]["diagnostics"]["fit"]["grade"] in ("poor", "fails")
    assert any("poor fit" in w for w in u["warnings"])
    ul, uh = u["regions"]["7"]["ci95_per_mm"]
    assert uh - ul >= 0.8 * (hi - lo)


def test_help_states_every_default(fluo):
    r = fluo("tomo", "reconstruct", "--help")
    assert r.returncode == 0
    text = " ".join(r.stdout.split())
    for opt in ("--method", "--lambda", "--target", "--accuracy", "--element-mm", "--roi",
                "--truncation-pct", "--data-model"):
        assert opt in text
    from FluoTomoLib.tomography.accuracy import LEVELS

    for name, level in LEVELS.items():        # the help says what each level is
        assert f"{name} = {level['recon_mm']:g} mm" in text, name
    r = fluo("tomo", "simulate", "--help")
    text = " ".join(r.stdout.split())
    assert "(default 1.0)" in text and "(default 0)" in text and "--engine" in text
    assert all(f"{name} {level['simulate_mm']:g} / {level['simulate_coarse_mm']:g}" in text
               for name, level in LEVELS.items())


def _check(sc, summary, yield_file, method, tol):
    inc = summary["regions"]["7"]["yield_per_mm"]
    err = (inc - TRUE_YIELD) / TRUE_YIELD
    centre = sc["inclusion_centre_ras_mm"]
    cen = np.array(summary["target_centroid_ras_mm"])
    peak = np.array(summary["peak_ras_mm"])
    assert abs(err) < tol, (method, err)
    assert np.linalg.norm(cen - centre) < 1.0, (method, cen, centre)
    assert np.linalg.norm(peak - centre) <= sc["inclusion_radius_mm"], (method, peak, centre)
    if yield_file is not None:
        arr, sp, org, d = read_volume_nrrd(yield_file)
        assert arr.shape == sc["labels_kji"].shape
        assert np.allclose(sp, sc["spacing_mm"]) and np.allclose(org, sc["origin_mm"], atol=1e-4)
        assert np.allclose(d, sc["direction"], atol=1e-6)
        k, j, i = np.unravel_index(int(np.argmax(arr)), arr.shape)
        ras = org + d @ (np.array([i, j, k]) * sp)
        assert np.linalg.norm(ras - centre) <= sc["inclusion_radius_mm"], (ras, centre)
        assert sc["labels_kji"][k, j, i] == sc["inclusion_label"]
    return err


@pytest.fixture(scope="module")
def issue_scene(issue_acquisition):
    """Issue #17's scene at full resolution and its 'fine' acquisition (conftest.py)."""
    return issue_acquisition.dir, issue_acquisition.sc


@pytest.mark.heavy(gb=6.5)     # SP at the balanced level on issue #17's scene: 5.2 GB measured
@pytest.mark.slow
def test_issue_scene_through_the_cli(issue_scene, fluo):
    """HP within 15 %, SP within 30 %, the half-maximum centroid within 1 mm of
    the inclusion's centre and the volume's peak inside it, in RAS, from the
    written yield.nrrd (on the label map's grid)."""
    d, sc = issue_scene
    errors = {}
    for method, tol in (("HP", 0.15), ("SP", 0.30)):
        r = fluo("tomo", "reconstruct", "--labels", d / "labels.nrrd", "--optics",
                 d / "optics.json", "--acquisition", d / "acq", "--method", method,
                 "--out", d / f"out-{method}", "--json")
        assert r.returncode == 0, r.stderr[-3000:]
        summary = json.loads(r.stdout)
        for key in ("method", "regions", "peak_yield_per_mm", "peak_ras_mm",
                    "target_centroid_ras_mm", "warnings", "seconds", "output"):
            assert key in summary
        errors[method] = _check(sc, summary, d / f"out-{method}" / "yield.nrrd", method, tol)
        assert summary["region_of_interest"]["truncation_max_pct"] is not None
    print("issue scene, CLI:", {m: f"{100 * e:+.1f} %" for m, e in errors.items()})


@pytest.mark.heavy(gb=6.5)     # the same reconstructions as the CLI test: 5.5 GB measured
@pytest.mark.slow
def test_issue_scene_through_the_logic(issue_scene):
    """The same through FluoTomoLogic with node objects; the mesh the app would
    show is the one used (a second run's own output node: test_scene_conventions.py,
    on the small scene)."""
    from fluoguide import mrml_io
    from FluoTomo import FluoTomoLogic

    d, sc = issue_scene
    scene = mrml_io.new_scene()
    logic = FluoTomoLogic(scene)
    lab = logic.loadLabelMap(d / "labels.nrrd")
    geo = mrml_io.volume_geometry(lab)
    assert np.allclose(geo["direction"], sc["direction"])
    mesh = logic.buildMesh(lab, sizeMm=1.0, acquisition=d / "acq", optics=d / "optics.json")
    vols = logic.meshRegionVolumes(mesh)
    assert all(abs(err) < 1.0 for _, _, err in vols.values()), vols
    s_hp, n_hp = logic.reconstruct(lab, d / "optics.json", d / "acq", method="HP",
                                   meshNode=mesh)
    s_sp, n_sp = logic.reconstruct(lab, d / "optics.json", d / "acq", method="SP")
    assert s_hp["mesh"]["nodes"] == mrml_io.get_json_attribute(mesh, "FluoTomo.Mesh")["nodes"]
    e_hp = _check(sc, s_hp, None, "HP", 0.15)
    e_sp = _check(sc, s_sp, None, "SP", 0.30)
    for node in (n_hp, n_sp):
        g = mrml_io.volume_geometry(node)
        assert np.allclose(g["direction"], sc["direction"]) and np.allclose(g["origin"],
                                                                            sc["origin_mm"])
        arr = mrml_io.volume_array(node)
        k, j, i = np.unravel_index(int(np.argmax(arr)), arr.shape)
        assert sc["labels_kji"][k, j, i] == sc["inclusion_label"]
    print("issue scene, logic:", {"HP": f"{100 * e_hp:+.1f} %", "SP": f"{100 * e_sp:+.1f} %"})


def _mixed_meshes(tmp_path):
    from FluoTomoLib.meshing.mesh import Mesh
    from FluoTomoLib.meshing.structured import box_mesh
    from FluoTomoLib.meshing.vtu_io import write_vtu

    # 1 mm cells: the resolution guard refuses mueff h > 1 (the ICG makes mueff 0.52 /mm)
    m = box_mesh(np.linspace(-10, 10, 21), np.linspace(-10, 10, 21), np.linspace(-8, 0, 9))
    c = m.nodes_mm[m.elements].mean(axis=1)
    reg = np.where(np.linalg.norm(c - [0, 0, -4], axis=1) < 3.0, 7, 3)
    good = Mesh(m.nodes_mm, m.elements, reg).oriented()
    el = good.elements.copy()
    flip = np.arange(len(el)) % 3 == 0               # every third element the other way round
    el[flip, 0], el[flip, 1] = good.elements[flip, 1], good.elements[flip, 0]
    write_vtu(good, tmp_path / "good.vtu")
    write_vtu(Mesh(good.nodes_mm, el, reg), tmp_path / "mixed.vtu")
    el2 = good.elements.copy()
    el2[5, 3] = el2[5, 2]                             # a degenerate element
    write_vtu(Mesh(good.nodes_mm, el2, reg), tmp_path / "degenerate.vtu")
    (tmp_path / "src.csv").write_text("x,y,z\n-3,0,0\n3,0,0\n")
    (tmp_path / "det.csv").write_text("0,0,0\n6,0,0\n-6,2,0\n")
    (tmp_path / "optics.json").write_text(json.dumps(OPTICS))
    return int(flip.sum())


def test_forward_multi_region_either_orientation_and_yield(tmp_path, fluo):
    """``fluo forward``: regions from the mesh with optics.json, --yield gives the
    fluorescence data and the yield Jacobian; a mesh with mixed element
    orientation gives the same numbers and says how many it turned; only a
    degenerate element is refused, in one line that names the file."""
    flipped = _mixed_meshes(tmp_path)
    outs = {}
    for name in ("good", "mixed"):
        r = fluo("forward", "--mesh", tmp_path / f"{name}.vtu", "--optics",
                 tmp_path / "optics.json", "--sources", tmp_path / "src.csv", "--detectors",
                 tmp_path / "det.csv", "--yield", "7:0.0026", "--jacobian", "--json")
        assert r.returncode == 0, r.stderr
        outs[name] = json.loads(r.stdout)
    assert outs["good"]["reoriented_elements"] == 0
    assert outs["mixed"]["reoriented_elements"] == flipped
    assert outs["mixed"]["regions"] == [3, 7]
    assert np.allclose(outs["mixed"]["fluorescence"], outs["good"]["fluorescence"], rtol=1e-10)
    assert np.allclose(outs["mixed"]["detector_fluence"], outs["good"]["detector_fluence"])
    assert outs["good"]["jacobian_yield_shape"] == [6, outs["good"]["nodes"]]
    assert np.all(np.array(outs["good"]["fluorescence"]) > 0)
    # the homogeneous shortcut still works on a multi-region mesh
    r = fluo("forward", "--mesh", tmp_path / "mixed.vtu", "--mua", "0.01", "--musp", "1",
             "--sources", tmp_path / "src.csv", "--detectors", tmp_path / "det.csv", "--json")
    assert r.returncode == 0, r.stderr
    r = fluo("forward", "--mesh", tmp_path / "degenerate.vtu", "--optics",
             tmp_path / "optics.json", "--sources", tmp_path / "src.csv", "--detectors",
             tmp_path / "det.csv")
    _one_line_exit_2(r, "degenerate.vtu")
    assert "Mesh." not in r.stderr and "()" not in r.stderr
    doc = json.loads(json.dumps(OPTICS))
    del doc["excitation"]["7"], doc["emission"]["7"]
    (tmp_path / "o2.json").write_text(json.dumps(doc))
    r = fluo("forward", "--mesh", tmp_path / "good.vtu", "--optics", tmp_path / "o2.json",
             "--sources", tmp_path / "src.csv", "--detectors", tmp_path / "det.csv")
    _one_line_exit_2(r, "[7]")


def test_mesh_fast_reports_region_volumes_and_warns(tmp_path, fluo):
    """``fluo mesh --fast`` on a flipped, anisotropic label map: region volumes
    against the label map within 1 %; a region too small for the cells is in
    the JSON's warnings."""
    sc = write_scene(tmp_path, semi_axes_mm=(14.0, 12.0, 8.0), spacing_mm=(0.8, 0.9, 1.0))
    r = fluo("mesh", tmp_path / "labels.nrrd", "--fast", "--size", "1.0", "--out",
             tmp_path / "m.vtu", "--json")
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    assert doc["warnings"] == []
    for region in doc["regions"].values():
        assert abs(region["volume_error_pct"]) < 1.0, doc["regions"]
    lab = sc["labels_kji"].copy()
    lab[lab == 7] = 3
    lab[10, 20, 20] = 9                               # one voxel: 0.72 mm^3
    write_volume_nrrd(tmp_path / "tiny.nrrd", lab, sc["spacing_mm"], sc["origin_mm"],
                      sc["direction"])
    r = fluo("mesh", tmp_path / "tiny.nrrd", "--fast", "--size", "2.0", "--out",
             tmp_path / "t.vtu", "--json")
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    assert any("region 9" in w for w in doc["warnings"]), doc["warnings"]


def test_optics_in_1_per_cm_are_refused_naming_the_unit(own_scene, tmp_path, fluo):
    """Optics written in 1/cm (ten times the 1/mm values) were refused for the
    mesh they implied ('size_mm: about 3.22e+07 cells'), nothing said of the
    optics or their units (issue #33): now the file, the label, the value and the
    likely mistake, before any work."""
    doc = json.loads(own_scene.optics.read_text())
    for table in ("excitation", "emission"):
        for entry in doc[table].values():
            entry["mua_per_mm"] *= 10.0
            entry["musp_per_mm"] *= 10.0
    cm = tmp_path / "optics_cm.json"
    cm.write_text(json.dumps(doc))
    for args in (["tomo", "simulate", "--labels", own_scene.labels, "--optics", cm, "--yield",
                  "7:0.0026", "--out", tmp_path / "out"],
                 ["tomo", "reconstruct", "--labels", own_scene.labels, "--optics", cm,
                  "--acquisition", own_scene.acq, "--element-mm", "1.5", "--out",
                  tmp_path / "out"]):
        r = fluo(*args)
        _one_line_exit_2(r, "optics_cm.json")
        line = r.stderr.strip()
        assert "musp_per_mm" in line and "1/cm" in line and "label 3" in line, line
        assert "cells" not in line
        assert not (tmp_path / "out").exists()


def test_logic_forward_refuses_a_mesh_too_coarse_for_its_optics_unless_forced(tmp_path):
    """``FluoTomoLogic.forward`` applies the resolution guard ``fluo forward``
    applies: a 4 mm mesh of tissue with mueff ~1.7 /mm (mueff h ~8: the fluence
    oscillates) is refused naming the size, and computed with ``force=True``."""
    from fluoguide import mrml_io
    from fluoguide.errors import FluoInputError
    from FluoTomo import FluoTomoLogic
    from small_cases import OWN_SCENE

    sc = write_scene(tmp_path, **OWN_SCENE)
    optics = json.loads((tmp_path / "optics.json").read_text())
    for label in ("3", "7"):
        optics["excitation"][label] = {"mua_per_mm": 0.3, "musp_per_mm": 3.0}
    logic = FluoTomoLogic(mrml_io.new_scene())
    lab = logic.loadLabelMap(tmp_path / "labels.nrrd")
    top = np.asarray(sc["surface_point_ras_mm"])
    sources = [top]
    detectors = [top + [4.0, 0.0, -0.5], top + [0.0, 5.0, -0.5]]
    with pytest.raises(FluoInputError, match="force=True") as refused:
        logic.forward(lab, optics, sources, detectors, sizeMm=4.0)
    assert refused.value.field == "sizeMm" and refused.value.value == 4.0
    forced = logic.forward(lab, optics, sources, detectors, sizeMm=4.0, force=True)
    assert forced["excitation"].shape == (1, 2) and forced["fluorescence"] is None
