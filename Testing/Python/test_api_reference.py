"""The API reference (``docs/api``, ``make docs``) builds from the docstrings with
every Sphinx warning an error, as CI builds it (issue #30).

Sphinx runs as its own process (``python -m sphinx`` is ``sphinx-build``) on the
tree under test: docs/api/conf.py puts the checkout and the module folders first
on ``sys.path``. A failure shows Sphinx's warnings, each with the docstring and
line it comes from.
"""

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SOURCE = ROOT / "docs" / "api"
# one object of each page, so an empty page (an import that documented nothing) fails
EXPECTED = {
    "logic": ["FluoCalib.FluoCalibLogic", "FluoNav.FluoNavLogic", "FluoTomo.FluoTomoLogic"],
    "fluoguide": ["fluoguide.errors.FluoInputError", "fluoguide.runs.run_tasks"],
    "fluocaliblib": ["FluoCalibLib.geometry.CameraModel",
                     "FluoCalibLib.radiometry.IlluminationCone"],
    "fluonavlib": ["FluoNavLib.devices.LiveLoop", "FluoNavLib.mapping.SurfaceCaster"],
    "fluotomolib": ["FluoTomoLib.tomography.LabelMap", "FluoTomoLib.meshing.Mesh",
                    "FluoTomoLib.fem.FluorescenceModel"],
}


def build(out):
    """``sphinx-build -W --keep-going -b html docs/api OUT``: (return code, warnings)."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
           "OPENBLAS_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
    r = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-E",
                        "-b", "html", "-d", str(out / "doctrees"), str(SOURCE), str(out / "html")],
                       capture_output=True, text=True, timeout=600, cwd=ROOT, env=env)
    return r.returncode, (r.stderr + r.stdout).strip()


@pytest.mark.slow  # ~8 s alone on 2 cores (it imports every Lib); more under CI's load
def test_the_api_reference_builds_without_warnings(tmp_path):
    rc, said = build(tmp_path)
    assert "No module named sphinx" not in said, \
        "Sphinx is missing: make venv (pyproject.toml's test extra pins it)"
    assert rc == 0 and not said, f"sphinx-build -W failed (exit {rc}):\n{said}"
    for page, names in EXPECTED.items():
        html = (tmp_path / "html" / f"{page}.html").read_text()
        missing = [n for n in names if f'id="{n}"' not in html]
        assert not missing, f"docs/api/{page}.rst documents none of {missing}"

