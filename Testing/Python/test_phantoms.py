"""Digital phantoms: geometry, volumes, CBCT values, and the written scene."""

import json

import numpy as np
import pytest

from fluoguide import mrml_io
from fluoguide.errors import FluoInputError
from fluoguide.phantoms import PHANTOMS, make_phantom, write_phantom


@pytest.mark.parametrize("name", list(PHANTOMS))
def test_region_volumes_match_analytic(name):
    ph = make_phantom(name)
    truth = ph.truth()
    for label, region in truth["regions"].items():
        assert abs(region["volume_error_pct"]) < 2.0, (name, label, region)
    # HU-like values: air near -1000, tissue near 0..200
    assert np.median(ph.cbct_hu[ph.labels == 0]) < -900
    assert -100 < np.median(ph.cbct_hu[ph.labels == 1]) < 250


@pytest.mark.parametrize("depth", [2.7, 4.7, 6.7])
def test_tube_at_requested_depth(depth):
    ph = make_phantom("cylinder-tube", depth_mm=depth)
    k, j, i = np.nonzero(ph.labels == 2)
    z = ph.origin_mm[2] + k * ph.spacing_mm[2]
    y = ph.origin_mm[1] + j * ph.spacing_mm[1]
    assert abs(z.mean() + depth) < 0.25
    assert abs(y.mean()) < 0.25
    assert abs(ph.truth()["regions"]["2"]["volume_error_pct"]) < 2.0


def test_tube_outside_liquid_is_rejected():
    with pytest.raises(FluoInputError, match="depth_mm"):
        make_phantom("cylinder-tube", depth_mm=0.5)
    with pytest.raises(FluoInputError, match="depth_mm"):
        make_phantom("cylinder-tube", depth_mm=19.5)


def test_unknown_phantom():
    with pytest.raises(FluoInputError, match="unknown phantom"):
        make_phantom("liver")


def test_noise_is_seeded():
    a = make_phantom("slab", voxel_mm=2.0, seed=1).cbct_hu
    b = make_phantom("slab", voxel_mm=2.0, seed=1).cbct_hu
    c = make_phantom("slab", voxel_mm=2.0, seed=2).cbct_hu
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_written_scene_loads_back_identically(tmp_path):
    ph = make_phantom("cylinder-tube", depth_mm=3.7)
    path = write_phantom(ph, tmp_path / "cyl")
    truth = json.loads((tmp_path / "cyl" / "truth.json").read_text())
    scene = mrml_io.load_scene(path)
    names = sorted(n["name"] for n in mrml_io.node_summary(scene))
    assert names == ["CBCT", "CBCTLabels"]
    cbct = mrml_io.get_node(scene, "CBCT")
    labels = mrml_io.get_node(scene, "CBCTLabels")
    assert labels.IsA("vtkMRMLLabelMapVolumeNode")
    assert np.array_equal(mrml_io.volume_array(cbct), ph.cbct_hu)
    assert np.array_equal(mrml_io.volume_array(labels), ph.labels)
    geo = mrml_io.volume_geometry(labels)
    np.testing.assert_allclose(geo["spacing"], ph.spacing_mm)
    np.testing.assert_allclose(geo["origin"], ph.origin_mm)
    assert mrml_io.get_json_attribute(labels, "FluoGuide.Truth") == truth
    # label-map volumes of the loaded scene against the analytic volumes
    arr = mrml_io.volume_array(labels)
    vox = float(np.prod(geo["spacing"]))
    for label, region in truth["regions"].items():
        vol = np.count_nonzero(arr == int(label)) * vox
        assert abs(vol - region["analytic_volume_mm3"]) / region["analytic_volume_mm3"] < 0.02


def test_failed_write_leaves_nothing(tmp_path):
    ph = make_phantom("slab", voxel_mm=2.0)
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(FluoInputError, match="not a folder"):
        write_phantom(ph, blocker)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


@pytest.mark.parametrize("name", PHANTOMS)
def test_optics_json_plus_the_dye_of_each_yield_is_the_truth(name, tmp_path):
    """optics.json beside the scene holds each region without its ICG; adding
    ICG's absorption per unit yield times truth.json's yield gives back the
    truth's coefficients (what fluo tomo simulate / reconstruct do)."""
    from fluoguide.optics_table import icg_absorption_per_yield

    ph = make_phantom(name, voxel_mm=2.0)
    write_phantom(ph, tmp_path / "p")
    doc = json.loads((tmp_path / "p" / "optics.json").read_text())
    truth = json.loads((tmp_path / "p" / "truth.json").read_text())["regions"]
    per_x, per_m = icg_absorption_per_yield()
    assert set(doc["excitation"]) == set(doc["emission"]) == set(truth)
    assert doc["fluorophore"] == ("ICG" if ph.yields_per_mm() else None)
    for k, r in truth.items():
        o, y = r["optics"], r["optics"]["yield_per_mm"]
        assert doc["names"][k] == r["name"] and doc["n"] == o["n"]
        assert doc["excitation"][k]["mua_per_mm"] + per_x * y == pytest.approx(o["mua_x_per_mm"])
        assert doc["emission"][k]["mua_per_mm"] + per_m * y == pytest.approx(o["mua_m_per_mm"])
        assert doc["excitation"][k]["musp_per_mm"] == o["musp_x_per_mm"]
        assert doc["emission"][k]["mua_per_mm"] >= 0
