"""NIRFAST mesh files: exact round trip, parameters, clear errors."""

import numpy as np
import pytest

from fluoguide.errors import FluoInputError
from fluoguide.phantoms import make_phantom
from FluoTomoLib.meshing.nirfast_io import read_nirfast, write_nirfast
from FluoTomoLib.optics import diffusion_coefficient
from FluoTomoLib.meshing.voxel import mesh_labelmap_structured


@pytest.fixture(scope="module")
def mesh():
    ph = make_phantom("cylinder-tube", depth_mm=3.7)
    m = mesh_labelmap_structured(ph.labels, ph.spacing_mm, ph.origin_mm, 1.6,
                                 roi=(-8, 8, -8, 8, -10, 0))
    # element regions that follow NIRFAST's node-based rule (max of node regions)
    m.element_region = m.node_region[m.elements].max(axis=1)
    return m


def test_round_trip_is_exact(mesh, tmp_path):
    kappa = diffusion_coefficient(0.01, 1.0)
    params = {"muax": 0.03, "kappax": kappa, "ri": 1.33, "muam": 0.02, "kappam": kappa,
              "muaf": np.where(mesh.node_region == 2, 0.065, 0.0), "eta": 0.04, "tau": 0.0}
    stem = write_nirfast(mesh, tmp_path / "tube", "fluor", params)
    back = read_nirfast(stem)
    assert np.array_equal(back.nodes_mm, mesh.nodes_mm)
    assert np.array_equal(back.elements, mesh.elements)
    assert np.array_equal(back.element_region, mesh.element_region)
    assert np.array_equal(back.meta["node_region"], mesh.node_region)
    assert back.meta["param_type"] == "fluor"
    np.testing.assert_array_equal(back.meta["params"]["muaf"], params["muaf"])
    assert set(np.flatnonzero(back.meta["bndvtx"])) == set(mesh.boundary_nodes.tolist())
    text = (tmp_path / "tube.elem").read_text().split()
    assert min(int(v) for v in text) == 1  # 1-based, as NIRFAST expects


def test_corrupt_files_are_named(mesh, tmp_path):
    stem = write_nirfast(mesh, tmp_path / "m")
    (tmp_path / "m.elem").write_text("1 2 3 x\n")
    with pytest.raises(FluoInputError, match="m.elem"):
        read_nirfast(stem)
    write_nirfast(mesh, tmp_path / "m")
    (tmp_path / "m.region").write_text("1\n2\n")
    with pytest.raises(FluoInputError, match="regions for"):
        read_nirfast(stem)
    with pytest.raises(FluoInputError, match="not found"):
        read_nirfast(tmp_path / "missing")
    with pytest.raises(FluoInputError, match="params.eta"):
        write_nirfast(mesh, tmp_path / "p", "fluor", {"muax": 0.1, "kappax": 0.3, "ri": 1.33,
                                                       "muam": 0.1, "kappam": 0.3, "muaf": 0.0})
