"""docs/fem.md's measured tables are the code's: the resolution table is the one the
guard uses (fem/_resolution_table.py, itself re-measured in
test_fem_resolution.py), and one row of the accuracy-versus-time table is
recomputed here (errors to 0.05 percentage points: the computation is
deterministic up to summation order; times are not compared)."""

from pathlib import Path

import numpy as np
import pytest

DOC = Path(__file__).resolve().parents[3] / "docs" / "fem.md"


def _table(marker):
    """Rows (lists of cell strings) of the markdown table after ``marker``."""
    lines = DOC.read_text().splitlines()
    start = lines.index(marker) + 1
    rows = []
    for line in lines[start:]:
        if not line.startswith("|"):
            if rows:
                break
            continue
        rows.append([c.strip() for c in line.strip().strip("|").split("|")])
    return rows[0], rows[2:]


def test_resolution_table_in_the_docs_is_the_guards():
    from FluoTomoLib.fem import _resolution_table as T

    head, rows = _table("<!-- resolution-table n=1.37 -->")
    assert [float(v) for v in head[2:]] == list(T.RHO_H)
    a = list(T.N).index(1.37)
    seen = 0
    for row in rows:
        j, i = list(T.MUTP_H).index(float(row[0])), list(T.MUEFF_H).index(float(row[1]))
        for k, cell in enumerate(row[2:]):
            worst, median = (v.strip() for v in cell.split("/"))
            for text, table in ((worst, T.WORST), (median, T.MEDIAN)):
                value = table[a, j, i, k]
                if text == "neg.":
                    assert np.isinf(value)
                else:
                    assert float(text) == pytest.approx(100 * value, abs=0.051)
        seen += 1
    assert seen == len(T.MUTP_H) * len(T.MUEFF_H)


def test_trade_table_row_recomputed():
    from functools import partial

    from benchmarks.bench_fem import _slab, trade_row

    from FluoTomoLib.fem import _resolution_table as T
    from FluoTomoLib.optics import boundary_method

    head, rows = _table("<!-- trade-table -->")
    row = next(r for r in rows if r[0] == "uniform h 3.0")
    # measured with the empirical boundary constant, as the guard's table (docs/fem.md)
    with boundary_method(T.BOUNDARY):
        got = trade_row(partial(_slab, 3.0), repeats=1)
    assert int(row[1].replace(",", "")) == got["nodes"]
    for col, key in ((2, "median_err_pct"), (3, "max_err_pct")):
        assert float(row[col]) == pytest.approx(got[key], abs=0.05), key
    for col, key in ((4, "guard_worst_max_pct"), (5, "guard_median_max_pct")):
        assert float(row[col]) == pytest.approx(got[key], abs=0.1), key
