"""docs/reconstruction.md's accuracy/speed tables are what the code gives.

A subset of the lambda and noise sweeps (study B's 6 mm disc, top 3.5 mm,
2D, seed 0) is recomputed and compared with the tables: peak and centroid
errors within 0.5 percentage points (the runs are seeded; what is left is
BLAS summation order, amplified by up to 40 iterations), and the same kinds
of warnings.  Times are not checked (no timing assertions).
"""

import re
from pathlib import Path

import pytest

from FluoTomoLib.studies.run import run_case
from FluoTomoLib.studies.thesis import study_meshes

DOC = Path(__file__).resolve().parents[3] / "docs" / "reconstruction.md"
TOL_PP = 0.5


def _table(kind):
    """{(value, method): (peak %, centroid %, warning kinds)} of the doc's table."""
    rows = {}
    header = f"| {kind} | method |"
    lines = DOC.read_text(encoding="utf-8").splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(header))
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip("|").split("|")]
        warns = set() if cells[6] == "-" else {w.strip() for w in cells[6].split(",")}
        rows[(float(cells[0]), cells[1])] = (float(cells[2]), float(cells[3]), warns)
    return rows


def _kinds(warnings):
    return {re.split(r":| \(", w)[0] for w in warnings}


@pytest.fixture(scope="module")
def meshes():
    return study_meshes()


@pytest.mark.parametrize("kind,value", [("lambda", 0.001), ("lambda", 10.0),
                                        ("lambda", 1000.0), ("noise", 5.0)])
def test_trade_table_rows(meshes, kind, value):
    table = _table(kind)
    kw = dict(diameter_mm=6.0, top_depth_mm=3.5, seed=0, meshes=meshes)
    if kind == "lambda":
        kw["lambdas"] = {m: [value] for m in ("NP", "SP", "HP")}
    else:
        kw["noise_pct"] = value
    rows, _ = run_case(f"{kind} = {value:g}", **kw)
    for row in rows:
        peak, centroid, warns = table[(value, row["method"])]
        assert row["peak_error_pct"] == pytest.approx(peak, abs=TOL_PP), row["method"]
        assert row["centroid_error_pct"] == pytest.approx(centroid, abs=TOL_PP), row["method"]
        assert _kinds(row["warnings"]) == warns, row["method"]
