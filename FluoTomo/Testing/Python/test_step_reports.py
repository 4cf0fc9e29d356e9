"""Steps of a reconstruction that were silent for seconds say what they do
(issue #33: a report at least every 2 s, and a cancel honoured): a large
operator's factorisation reports its seconds from beside it, on a helper
thread; the segmentation's moved solves report one by one and stop at a
cancel; the reconstruction mesh reports its steps. The whole reconstruction's
longest gap is measured in Testing/Python/test_jobs.py (slow)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from fluoguide.errors import FluoCancelled
from fluoguide.progress import CancelToken
from fluoguide.threads import limited_threads


def _recorder():
    items = []

    def progress(fraction, message=""):
        items.append((time.monotonic(), fraction, message))

    return items, progress


def _longest_gap(t0, items, t1):
    times = [t0] + [t for t, _, _ in items] + [t1]
    return max(b - a for a, b in zip(times, times[1:]))


@pytest.fixture(scope="module")
def cube():
    """A structured cube of 21,952 nodes: just above REPORTING_NODES."""
    from FluoTomoLib.fem.operators import REPORTING_NODES
    from FluoTomoLib.meshing.voxel import mesh_labelmap_structured

    mesh = mesh_labelmap_structured(np.ones((27, 27, 27), np.uint8), (1.0, 1.0, 1.0),
                                    (0.0, 0.0, 0.0), 1.0)
    assert mesh.n_nodes >= REPORTING_NODES
    return mesh


def _operator(mesh):
    from FluoTomoLib.fem.operators import DiffusionOperator

    return DiffusionOperator(mesh, 0.01, 1.0, 1.37, name="excitation")


def _slowed(monkeypatch, seconds, threads):
    """DiffusionOperator._factorization taking ``seconds`` longer, noting its thread."""
    from FluoTomoLib.fem.operators import DiffusionOperator

    real = DiffusionOperator._factorization

    def slow(self):
        threads.append(threading.get_ident())
        time.sleep(seconds)
        return real(self)

    monkeypatch.setattr(DiffusionOperator, "_factorization", slow)


def test_a_large_factorisation_reports_its_seconds_from_beside_it(cube, monkeypatch):
    b = np.zeros(cube.n_nodes)
    b[cube.n_nodes // 2] = 1.0
    expected = _operator(cube).solve(b)          # no reporter: on this thread, silent
    threads = []
    _slowed(monkeypatch, 2.3, threads)           # a factorisation of a few seconds
    op = _operator(cube)
    items, progress = _recorder()
    t0 = time.monotonic()
    op.factorize(progress, 0.4, "emission: factorising")
    t1 = time.monotonic()
    assert threads and threads[0] != threading.get_ident()       # on a helper thread
    messages = [m for _, _, m in items]
    assert messages[0] == "emission: factorising", messages
    assert "emission: factorising, 1 s" in messages and "emission: factorising, 2 s" in messages
    assert {f for _, f, _ in items} == {0.4}
    # every second asked; the margin is for a loaded machine
    assert _longest_gap(t0, items, t1) < 1.8, items
    np.testing.assert_array_equal(op.solve(b), expected)     # the same factor, whole
    assert op.factor_seconds >= 2.3


def test_a_small_factorisation_stays_on_the_caller_s_thread(monkeypatch):
    from FluoTomoLib.meshing.voxel import mesh_labelmap_structured

    small = mesh_labelmap_structured(np.ones((8, 8, 8), np.uint8), (1.0, 1.0, 1.0),
                                     (0.0, 0.0, 0.0), 1.0)
    threads = []
    _slowed(monkeypatch, 0.0, threads)
    items, progress = _recorder()
    _operator(small).factorize(progress, 0.0, "factorising")
    assert threads == [threading.get_ident()] and items == []


def test_a_cancel_ends_the_wait_for_a_factorisation_and_keeps_nothing_of_it(cube, monkeypatch):
    threads = []
    _slowed(monkeypatch, 3.0, threads)
    op = _operator(cube)
    token, asked = CancelToken(), {}

    def cancel_at_1_s(fraction, message):
        if message.endswith(", 1 s"):
            asked["at"] = time.monotonic()
            token.cancel()

    with pytest.raises(FluoCancelled):
        op.factorize(cancel_at_1_s, 0.0, "factorising", token)
    assert time.monotonic() - asked["at"] < 1.5            # at the next report
    assert op._solve is None and op.solver_name is None    # nothing half-set
    monkeypatch.undo()
    b = np.ones(cube.n_nodes)
    assert np.all(np.isfinite(op.solve(b)))                # factorises again when asked


@pytest.fixture(scope="module")
def coarse_model(own_scene):
    """The shared own scene's TissueModel on a 2 mm mesh (a few thousand nodes:
    seconds), with its data."""
    from FluoTomoLib.tomography import LabelMap, read_acquisition, read_optics
    from FluoTomoLib.tomography.labelmap import place_on_surface
    from FluoTomoLib.tomography.model import TissueModel, reconstruction_mesh

    lm, optics = LabelMap.from_file(own_scene.labels), read_optics(own_scene.optics)
    acq = read_acquisition(own_scene.acq, lm, optics)
    src, _ = place_on_surface(lm, acq.sources_ras_mm, "sources")
    det, _ = place_on_surface(lm, acq.detectors_ras_mm, "detectors")
    items, progress = _recorder()
    mesh = reconstruction_mesh(lm.labels_kji, lm.spacing_mm, 2.0, None, target=7,
                               surface=lm.surface(), progress=progress)
    tm = TissueModel(mesh, lm.labels_kji, lm.spacing_mm, optics, src, det, acq.mask)
    return tm, acq.y(), items


def test_the_reconstruction_mesh_reports_its_steps(coarse_model):
    *_, items = coarse_model
    messages = [m for _, _, m in items]
    for step in ("cells across label 7", "resampling labels", "building tetrahedra",
                 "tissue-air nodes onto the surface"):
        assert any(m.startswith(step) for m in messages), (step, messages)
    fractions = [f for _, f, _ in items]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0


def test_the_moved_segmentation_s_solves_report_one_by_one(coarse_model):
    tm, y, _ = coarse_model
    items, progress = _recorder()
    t0 = time.monotonic()
    with limited_threads(1):    # as `fluo` runs it: 684 data, BLAS threads idle-spin
        shifts = tm.segmentation_shifts(y, "HP", 10.0, 0.5, progress=progress)
    t1 = time.monotonic()
    messages = [m for _, _, m in items]
    heads = [m.split(":")[0] for m in messages]
    # the unmoved solve, then each offset's prior and solve, in order
    order = ["as segmented"] + [f"moved by {d:+.2g} mm ({k} of 4)"
                                for k, d in enumerate(shifts["offsets_mm"], start=1)] + [
        "segmentation test done"]
    assert [h for i, h in enumerate(heads) if i == 0 or h != heads[i - 1]] == order, heads
    assert any(m.endswith("its prior") for m in messages)
    assert any("HP iteration 1:" in m for m in messages)
    assert any("HP intervals: iteration 1 of" in m for m in messages)
    fractions = [f for _, f, _ in items]
    assert fractions == sorted(fractions) and fractions[-1] <= 1.0
    print(f"segmentation shifts: {t1 - t0:.1f} s, {len(items)} reports, longest gap "
          f"{_longest_gap(t0, items, t1):.2f} s")


def test_the_rigid_moves_follow_the_offsets_in_order_where_the_noise_is_stated(
        coarse_model, monkeypatch):
    """With a stated noise (and here any fit: TRANSLATION_FIT 0) the segmentation test
    also moves each region rigidly, a step along each axis (then as combined and
    twice, where those apply), reporting each move's prior and solve after the
    offsets', the bar never going back."""
    from FluoTomoLib.tomography import model

    monkeypatch.setattr(model, "TRANSLATION_FIT", 0.0)
    tm, y, _ = coarse_model
    items, progress = _recorder()
    with limited_threads(1):
        shifts = tm.segmentation_shifts(y, "HP", 10.0, 0.5, noise_rel=0.01, progress=progress)
    moves = shifts["translations"]
    labs = [int(v) for v in tm.region_labels if int(v) != int(tm.background)]
    assert len(moves) >= 6 * len(labs) and all(t["excess_over_best"] >= 0 for t in moves)
    assert [next(iter(t["moves_mm"])) for t in moves[:6]] == [labs[0]] * 6
    messages = [m for _, _, m in items]
    rigid = [i for i, m in enumerate(messages) if m.startswith("the regions moved rigidly")]
    last_offset = max(i for i, m in enumerate(messages) if m.startswith("moved by"))
    assert rigid and min(rigid) > last_offset
    assert any(m.startswith("the regions moved rigidly: with label "
                            f"{labs[0]} moved 0.5 mm along +i (1 of ") for m in messages)
    fractions = [f for _, f, _ in items]
    assert fractions == sorted(fractions) and fractions[-1] <= 1.0


def test_the_moved_segmentation_s_solves_stop_at_a_cancel(coarse_model):
    tm, y, _ = coarse_model
    token, seen = CancelToken(), []

    def progress(fraction, message=""):
        seen.append(message)
        if message.startswith("moved by +0.5 mm (3 of 4)"):
            token.cancel()

    with pytest.raises(FluoCancelled), limited_threads(1):
        tm.segmentation_shifts(y, "HP", 10.0, 0.5, cancel=token, progress=progress)
    # the cancel came as the third offset's prior was announced: nothing after it
    assert seen[-1] == "moved by +0.5 mm (3 of 4): its prior", seen[-3:]
