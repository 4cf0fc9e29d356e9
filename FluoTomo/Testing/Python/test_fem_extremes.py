"""The extremes matrix (issue 18): mua 1e-6..2 /mm, musp 0.05..200 /mm, n 1..1.6,
element size h 0.25..4 mm, source-detector distance rho 0.5..60 mm.

Every cell either meets its stated error (the resolution guard's worst-case
estimate, plus what the test box's own sides can change: half_space_check's
bound, since the exact reference is the half-space), or says in its warnings
that it may not, or is refused with a one-line message.  Never a NaN, never a
traceback, never a silent wrong number.  The analytic model's cells are checked
the same way through `fluo analytic`."""

import itertools
import json
import warnings

import numpy as np
import pytest

from fluoapp.cli import main
from fluoguide.errors import FluoInputError
from FluoTomoLib.analytic import log_robin_surface_fluence
from FluoTomoLib.fem.forward import FluorescenceModel
from FluoTomoLib.fem.halfspace import half_space_check
from FluoTomoLib.meshing.structured import box_mesh, optode_axis
from FluoTomoLib.optics import mueff

MUA = (1e-6, 0.01, 0.1, 2.0)
MUSP = (0.05, 1.0, 10.0, 200.0)
N = (1.0, 1.37, 1.6)
H = (0.25, 1.0, 4.0)
RHO = (0.5, 5.0, 20.0, 60.0)


def _cell_mesh(mua, musp, h, rho):
    """A box graded to the optodes: elements h at the source (origin) and at
    the detectors (+x, +y, -x), growing by 1.2 per step to 4h (at least 4 mm)."""
    me = float(mueff(mua, musp))
    pad = min(3.0 / me, 25.0) + 2 * h
    depth = max(pad, 3.0 / (mua + musp), 3 * h)
    xs = [0.0] + [r for k, r in enumerate(rho) if k % 3 == 0] + [-r for k, r in enumerate(rho)
                                                                 if k % 3 == 2]
    ys = [0.0] + [r for k, r in enumerate(rho) if k % 3 == 1]
    coarse = max(4.0 * h, 4.0)
    axes = [optode_axis(min(xs) - pad, max(xs) + pad, xs, h, coarse),
            optode_axis(-pad, max(ys) + pad, ys, h, coarse),
            optode_axis(-depth, 0.0, [0.0], h, coarse)]
    det = [[r, 0, 0] if k % 3 == 0 else ([0, r, 0] if k % 3 == 1 else [-r, 0, 0])
           for k, r in enumerate(rho)]
    return box_mesh(*axes), np.array([[0.0, 0.0, 0.0]]), np.array(det, float)


def run_cell(mua, musp, n, h, rho=RHO, max_nodes=150_000):
    """One cell of the matrix; checks the contract and returns its outcome
    ("met": every pair within its estimate, "warned": some pairs named in the
    warnings, the others met, "refused", "skipped": too large a mesh for this
    test) and the number of pairs checked against their estimate (or the
    refusal's text, or the mesh size)."""
    mesh, src, det = _cell_mesh(mua, musp, h, rho)
    if mesh.n_nodes > max_nodes:
        return "skipped", mesh.n_nodes
    p = dict(mua_per_mm=mua, musp_per_mm=musp, n=n)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")        # their text is in accuracy()'s lists
            fm = FluorescenceModel(mesh, p, p, src, det)
            acc = fm.accuracy()
    except FluoInputError as exc:                  # e.g. a source buried deeper than the box
        text = str(exc)
        assert text and "\n" not in text and "Traceback" not in text
        return "refused", text
    y = fm.excitation_data()[0]
    assert np.all(np.isfinite(y)), (mua, musp, n, h)
    if acc["refuse"]:
        return "refused", acc["refuse"][0]
    worst = np.array([np.inf if v is None else v
                      for v in acc["estimated_rel_err"]["excitation"]["worst_case"][0]])
    exact = log_robin_surface_fluence(np.asarray(rho), mua, musp, n)
    actual = np.abs(np.log(np.maximum(y, 1e-300)) - exact)
    sides = half_space_check(mesh, mua, musp, n, src, det, tol=np.inf)["boundary_effect_bound"]
    quiet = worst <= 0.05                           # pairs the guard does not warn about
    # a pair the guard calls accurate must be, within the box's own effect
    assert np.all(actual[quiet] <= np.log1p(worst[quiet]) + sides + 1e-3), (
        mua, musp, n, h, actual, worst, sides)
    if np.all(quiet):
        return "met", int(quiet.sum())
    assert any("may be off by more than 5 %" in w for w in acc["warnings"]), acc["warnings"]
    return "warned", int(quiet.sum())


FAST = [(0.01, 1.0, 1.37, 0.25), (0.01, 1.0, 1.37, 1.0), (2.0, 200.0, 1.6, 1.0),
        (1e-6, 0.05, 1.0, 4.0), (0.1, 10.0, 1.0, 4.0), (0.06, 10.0, 1.37, 1.0)]


@pytest.mark.parametrize("mua, musp, n, h", FAST)
def test_forward_extremes_sample(mua, musp, n, h):
    outcome, _ = run_cell(mua, musp, n, h, rho=(0.5, 5.0) if h < 1 else (0.5, 5.0, 20.0))
    assert outcome in ("met", "warned", "refused")


@pytest.mark.slow
def test_forward_extremes_matrix():
    outcomes, checked = {}, 0
    for mua, musp, n, h in itertools.product(MUA, MUSP, (1.0, 1.6), H):
        outcome, detail = run_cell(mua, musp, n, h)
        outcomes[(mua, musp, n, h)] = outcome
        checked += detail if outcome in ("met", "warned") else 0
    counts = {k: sum(v == k for v in outcomes.values()) for k in ("met", "warned", "refused",
                                                                  "skipped")}
    # every cell has rho = 0.5 mm, within an element or two of its source, so
    # none is "met" as a whole; the pairs the guard calls accurate were checked
    # (2026-11-24: 32 cells warned, 60 refused, 4 skipped, 10 pairs checked)
    assert counts["warned"] and counts["refused"] and checked >= 5, (counts, checked)
    assert counts["skipped"] <= len(outcomes) // 10, counts


def test_analytic_extremes_matrix(capsys):
    """`fluo analytic` over the matrix: exit 0, finite numbers (values below
    1e-308 print as 0 with their exact logs and a warning), diffusion's
    validity flagged where musp/mua < 10 and near the source."""
    rho = ",".join(str(r) for r in RHO)
    for mua, musp, n in itertools.product(MUA, MUSP, (1.0, 1.6)):
        assert main(["analytic", "--mua", str(mua), "--musp", str(musp), "--n", str(n),
                     "--rho", rho, "--yield", "1e-3", "--json"]) == 0
        out = json.loads(capsys.readouterr().out)
        for key in ("Rd", "F", "mueff", "D"):
            assert np.isfinite(out[key]) and out[key] > 0, (mua, musp, n, key)
        phi = np.array(out["robin_surface_fluence"])
        logs = np.array(out["ln_robin_surface_fluence"])
        assert np.all(np.isfinite(logs)) and np.all(phi >= 0) and np.all(np.isfinite(phi))
        if np.any(phi == 0):
            assert any("below 1e-308" in w for w in out["warnings"])
        assert out["diffusion_valid"] == (musp >= 10 * mua)
        if musp < 10 * mua:
            assert any("musp/mua" in w for w in out["warnings"])
        near = np.array(RHO) < 4 / (mua + musp)
        assert out["rho_diffusive"] == (~near).tolist()
