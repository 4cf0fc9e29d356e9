"""The seeded scene family (issue #31 item 1): each scene follows from its seed,
the family varies what it claims to vary, a segmentation error changes only
the inclusions' boundaries, and one scene goes through simulation,
reconstruction and grading (the whole family's table: docs/validation.md,
``python -m benchmarks family``)."""

from __future__ import annotations

import numpy as np
import pytest

from FluoTomoLib.validation import make_scene, summarise
from FluoTomoLib.validation.family import BODY_LABEL, INCLUSION_LABELS


def test_a_scene_follows_from_its_seed():
    a, b = make_scene(7), make_scene(7)
    assert np.array_equal(a.labels_kji, b.labels_kji) and a.description == b.description
    assert a.yield_by_label == b.yield_by_label and a.optics == b.optics
    assert not np.array_equal(make_scene(8).labels_kji.shape, a.labels_kji.shape) or \
        not np.array_equal(make_scene(8).labels_kji, a.labels_kji)


def test_the_family_varies_what_it_claims():
    scenes = [make_scene(s) for s in range(1, 31)]
    bodies = {s.description.split()[0] for s in scenes}
    assert bodies == {"ellipsoid", "dome"}
    n_inc = {len(s.inclusions) for s in scenes}
    assert {1, 2} <= n_inc
    oblique = [s for s in scenes if np.count_nonzero(np.abs(s.direction) > 1e-9) > 3]
    lps = [s for s in scenes if np.allclose(s.direction, np.diag([-1, -1, 1]))]
    assert oblique and lps
    assert any(BODY_LABEL in s.yield_by_label for s in scenes)          # dye in the background
    assert any(BODY_LABEL not in s.yield_by_label for s in scenes)
    noise = [s.noise_pct for s in scenes]
    assert 0.5 <= min(noise) < 1.0 and 2.5 < max(noise) <= 5.0
    assert len({tuple(s.spacing_mm) for s in scenes}) == len(scenes)   # anisotropic, varied
    for s in scenes:
        for inc in s.inclusions:
            lab = inc["label"]
            assert lab in INCLUSION_LABELS and np.any(s.labels_kji == lab)
            assert 1.0 <= inc["depth_mm"] <= 7.0
            assert s.yield_by_label[lab] > 0
        for table in ("excitation", "emission"):
            assert set(s.optics[table]) == {str(v) for v in np.unique(s.labels_kji) if v}


def test_a_segmentation_error_moves_only_the_inclusions():
    for seed in (3, 4, 5):
        s = make_scene(seed, segmentation_error_mm=1.0)
        truth, given = s.labels_kji, s.recon_labels_kji
        assert s.segmentation.split()[0] in ("dilated", "eroded", "shifted")
        changed = truth != given
        assert changed.any()
        assert np.all(given[truth == 0] == 0)                          # air untouched
        assert set(np.unique(given[changed])) <= {BODY_LABEL, *INCLUSION_LABELS}
        assert np.array_equal(s.labelmap(recon=False).labels_kji, truth)
        assert np.array_equal(s.labelmap().labels_kji, given)


@pytest.mark.slow      # one scene simulated (fine) and reconstructed (HP, SP): about 1 min
def test_one_scene_through_the_grading():
    from FluoTomoLib.validation import grade_scene

    scene = make_scene(4)
    rows = grade_scene(scene, accuracy="fast")
    assert {r["method"] for r in rows} == {"HP", "SP"}
    assert len(rows) == 2 * len(scene.inclusions)
    for r in rows:
        lo, hi = r["ci95_per_mm"]
        assert r["covered"] == (lo <= r["truth_per_mm"] <= hi)
        assert r["error_pct"] == pytest.approx(100 * (r["yield_per_mm"] / r["truth_per_mm"] - 1))
        # the contract: the interval holds the truth, or the result says why it may not
        assert r["covered"] or r["warned"], r
    table = summarise(rows)
    assert table["HP"]["rows"] == len(scene.inclusions)
    assert 0.0 <= table["HP"]["coverage"] <= 1.0


@pytest.mark.slow      # one scene simulated (fine) and reconstructed (SP): about 30 s
def test_sp_says_so_when_the_regions_as_constants_do_not_explain_the_data():
    """Scene 108 handed over with its inclusions shifted by 1 mm: SP's own fit was
    'fair' and it said nothing while its interval missed the first inclusion
    (-48 %). The hard prior on the same data (the segmentation test's unmoved solve)
    fits them far worse: SP's resolution-corrected value rests on that model, and
    now says so."""
    from FluoTomoLib.tomography import optics_from_dict
    from FluoTomoLib.tomography.reconstruct import reconstruct_labelmap_methods
    from FluoTomoLib.validation.family import simulate

    scene = make_scene(108, segmentation_error_mm=1.0)
    assert scene.segmentation.startswith("shifted")
    acq, _ = simulate(scene)
    s = reconstruct_labelmap_methods(scene.labelmap(recon=True), optics_from_dict(scene.optics),
                                     acq, methods=["SP"], accuracy="fast",
                                     target=scene.target())["SP"]["summary"]
    region_model = s["segmentation"]["region_model"]
    assert region_model["fit"]["grade"] in ("poor", "fails"), region_model
    said = [w for w in s["warnings"] if w.startswith("SP's value assumes each labelled region")]
    assert len(said) == 1, s["warnings"]
    assert "the hard prior fits them to" in said[0]


@pytest.mark.slow      # one scene simulated (fine), reconstructed twice (SP; HP, SP): ~30 s
def test_sp_asked_for_alone_is_the_sp_of_hp_and_sp_together():
    """SP asked for without HP (``fluo tomo reconstruct --method SP``) fed the dye's
    absorption back from the blind model, one pass: scene 36's 5.8 mm inclusion read
    -18.5 % that way, -2.6 % in the family's runs, where SP starts from HP's
    converged absorption. HP is now solved as its start (not reported), and the
    tests behind the interval take it as a requested HP: one SP, either way."""
    from FluoTomoLib.tomography import optics_from_dict
    from FluoTomoLib.tomography.reconstruct import reconstruct_labelmap_methods
    from FluoTomoLib.validation.family import simulate

    scene = make_scene(36)
    acq, _ = simulate(scene)
    lm, optics = scene.labelmap(recon=True), optics_from_dict(scene.optics)
    kw = dict(accuracy="fast", target=scene.target(), grading="bisection")
    alone = reconstruct_labelmap_methods(lm, optics, acq, methods=["SP"], **kw)
    both = reconstruct_labelmap_methods(lm, optics, acq, methods=["HP", "SP"], **kw)
    assert list(alone) == ["SP"]
    a, b = alone["SP"]["summary"]["regions"]["7"], both["SP"]["summary"]["regions"]["7"]
    assert a["yield_per_mm"] == pytest.approx(b["yield_per_mm"], rel=1e-9)
    np.testing.assert_allclose(a["ci95_per_mm"], b["ci95_per_mm"], rtol=1e-9)
    truth = scene.yield_by_label[7]
    assert abs(a["yield_per_mm"] / truth - 1) < 0.08, a["yield_per_mm"] / truth
    assert a["ci95_per_mm"][0] <= truth <= a["ci95_per_mm"][1]


@pytest.mark.slow      # two scenes simulated (fine) and reconstructed (HP): about 25 s
def test_a_correct_segmentation_is_not_ruled_out_by_the_dye_s_own_absorption():
    """Scenes 5 and 11, segmented correctly: the segmentation test's HP solves once
    left out the dye's absorption that the data hold, and found the inclusions
    'grown by 0.38-0.47 mm' to fit better by 112 and 261 residual variances (the
    95 % point is 3.84). On the model with the absorption as HP found it, the
    segmentation as given fits best."""
    from FluoTomoLib.tomography import optics_from_dict
    from FluoTomoLib.tomography.reconstruct import reconstruct_labelmap_methods
    from FluoTomoLib.validation.family import simulate

    for seed in (5, 11):
        scene = make_scene(seed)
        acq, _ = simulate(scene)
        s = reconstruct_labelmap_methods(scene.labelmap(recon=True),
                                         optics_from_dict(scene.optics), acq, methods=["HP"],
                                         accuracy="fast", target=scene.target())["HP"]["summary"]
        seg = s["segmentation"]
        assert seg["best_offset_mm"] == 0.0 and seg["unmoved_excess"] == 0.0, (seed, seg)
        assert not any("fit the data better" in t for t in s["notes"] + s["warnings"])


def _one_mm_off(seed, kind):
    """Family scene ``seed`` with its segmentation 1 mm off (``kind``: eroded,
    dilated or shifted), simulated and reconstructed by HP and SP with the
    segmentation's accuracy stated (1 mm). Returns (scene, {method: result})."""
    from FluoTomoLib.tomography import optics_from_dict
    from FluoTomoLib.tomography.reconstruct import reconstruct_labelmap_methods
    from FluoTomoLib.validation.family import simulate

    scene = make_scene(seed, segmentation_error_mm=1.0)
    assert scene.segmentation.startswith(kind)
    acq, _ = simulate(scene)
    return scene, reconstruct_labelmap_methods(scene.labelmap(recon=True),
                                               optics_from_dict(scene.optics), acq,
                                               methods=["HP", "SP"], accuracy="fast",
                                               target=scene.target(), segmentation_mm=1.0)


@pytest.mark.slow      # one scene simulated (fine) and reconstructed (HP, SP): about 15 s
def test_an_eroded_segmentation_is_found_on_each_segmentation_s_own_absorbing_model():
    """Scene 101 handed over with its inclusion eroded by 1 mm (the reconstruction
    told it may be 1 mm off): its HP value as segmented is 3.6x the truth. Solved for
    every moved boundary on the one model with that value's absorption, the eroded
    boundary fit best and its interval missed; each boundary on its own model, fed
    back, the data rule it out by far in favour of the inclusion grown by 1 mm, and
    HP and SP quote their values there: within 10 % (HP) and 30 % (SP) of the truth
    (the segmentation's own +257 % and +142 %)."""
    scene, out = _one_mm_off(101, "eroded")
    truth = scene.yield_by_label[7]
    for method, within in (("HP", 0.1), ("SP", 0.3)):
        s = out[method]["summary"]
        seg = s["segmentation"]
        assert seg["best_offset_mm"] == 1.0 and seg["unmoved_excess"] > 25, seg
        # the data choose the grown boundary by far: its values are quoted, each
        # method re-solved on it, and the interval reaches the segmentation as given
        assert seg["quoted_offset_mm"] == 1.0, seg
        assert any("fit the data better grown by 1 mm" in w and "the values are those of "
                   "the regions grown by 1 mm" in w for w in s["warnings"]), s["warnings"]
        r = s["regions"]["7"]
        assert abs(r["yield_per_mm"] / truth - 1) < within, (method, r["yield_per_mm"] / truth)
        assert r["as_segmented_per_mm"] > 2 * truth, (method, r["as_segmented_per_mm"] / truth)
        lo, hi = r["ci95_per_mm"]
        assert lo <= truth <= hi and hi >= r["as_segmented_per_mm"], (method, r)
        assert r["segmentation_values_per_mm"][seg["offsets_mm"].index(1.0)] == pytest.approx(
            r["yield_per_mm"])


@pytest.mark.slow      # one scene simulated (fine) and reconstructed (HP, SP): about 15 s
def test_a_shifted_segmentation_is_found_by_moving_its_region_rigidly():
    """Scene 124 handed over with its inclusion shifted by 1 mm: HP as segmented is
    +73 %; of the offsets, the inclusion grown by 1 mm fits best, by 15 residual
    variances (too few to quote) and reads -34 %. Moved rigidly one step along the +i -k
    diagonal (greedily combined) it fits the data far better, the move twice worse: HP
    and SP quote the moved region's values, within 10 % of the truth, the interval
    reaching the segmentation's own value."""
    scene, out = _one_mm_off(124, "shifted")
    truth = scene.yield_by_label[7]
    for method in ("HP", "SP"):
        s = out[method]["summary"]
        seg = s["segmentation"]
        assert seg["quoted_offset_mm"] is None and seg["quoted_move_mm"], seg
        assert len(seg["rigid_moves"]) > 6 and seg["unmoved_excess"] > 25, seg
        assert any("than as segmented" in w and "the values are those of the regions with "
                   "label 7 moved" in w for w in s["warnings"]), s["warnings"]
        r = s["regions"]["7"]
        assert abs(r["yield_per_mm"] / truth - 1) < 0.1, (method, r["yield_per_mm"] / truth)
        assert r["as_segmented_per_mm"] > 1.2 * truth, (method, r["as_segmented_per_mm"] / truth)
        lo, hi = r["ci95_per_mm"]
        assert lo <= truth <= hi and hi >= r["as_segmented_per_mm"], (method, r)


def _seg_record(quoted):
    """A segmentation test's record: the inclusion (7) worth 0.004 as segmented in
    HP, 0.002 grown by 1 mm (ruled in by far), 0.008 and 0.016 shrunk; the
    background (3) 0 as segmented, 1e-5 grown."""
    return {"offsets_mm": [-2.0, -1.0, 1.0, 2.0], "kept": [False, False, True, False],
            "shifts": {7: [0.012, 0.004, -0.002, -0.003], 3: [0.0, 0.0, 1e-5, 2e-5]},
            "base": {7: 0.004, 3: 0.0}, "best_offset_mm": 1.0, "unmoved_excess": 40.0,
            "excess_over_best": [900.0, 300.0, 0.0, 60.0], "unmoved_ruled_out": True,
            "quoted_offset_mm": quoted, "region_model": None}


@pytest.mark.parametrize("quoted", [False, True])
def test_the_segmentation_part_reaches_the_segmentation_as_given_when_a_moved_one_is_quoted(
        quoted):
    """Unquoted, the value is the segmentation's and the interval reaches the kept
    offsets' values (HP's relative change); quoted, the value is the one solved on
    the grown boundary, the interval reaches the method's value on the segmentation
    as given (``as_segmented_per_mm``) and half-way to the boundary grown a step
    further, and the warning says which boundary the values stand on."""
    from FluoTomoLib.tomography.reconstruct import _add_segmentation

    v7, v3 = (0.0021, 1.2e-5) if quoted else (0.0042, 0.0)
    summary = {"warnings": [], "regions": {
        "7": {"yield_per_mm": v7, "ci95_per_mm": [v7 - 1e-4, v7 + 1e-4], "interval_parts": {}},
        "3": {"yield_per_mm": v3, "ci95_per_mm": [0.0, v3 + 1e-6], "interval_parts": {}}}}
    _add_segmentation(summary, _seg_record(1.0), 1.0, "HP",
                      {7: 0.0045, 3: 0.0} if quoted else None)
    r7, r3 = summary["regions"]["7"], summary["regions"]["3"]
    assert summary["segmentation"]["quoted_offset_mm"] == (1.0 if quoted else None)
    said = [w for w in summary["warnings"] if "fit the data better grown by 1 mm" in w]
    assert len(said) == 1 and (("the values are those of the regions grown by 1 mm" in said[0])
                               == quoted)
    if quoted:
        # relative to HP's 0.002 on the grown boundary: shrunk 1 mm 4x, grown 2 mm 0.5x;
        # the value as segmented is the method's own solve there
        assert r7["as_segmented_per_mm"] == 0.0045
        assert r7["segmentation_values_per_mm"] == pytest.approx(
            [8 * v7, 4 * v7, v7, 0.5 * v7])
        # up to the value as given, down half-way to the boundary grown 2 mm
        assert r7["ci95_per_mm"] == pytest.approx([0.75 * v7 - 1e-4, 0.0045 + 1e-4])
        assert r3["as_segmented_per_mm"] == 0.0
        assert r3["ci95_per_mm"][0] == 0.0
    else:
        assert "as_segmented_per_mm" not in r7
        assert r7["segmentation_values_per_mm"] == pytest.approx(
            [4 * v7, 2 * v7, 0.5 * v7, 0.25 * v7])
        assert r7["ci95_per_mm"] == pytest.approx([0.5 * v7 - 1e-4, v7 + 1e-4])
        assert "segmentation_values_per_mm" not in r3       # no positive value to scale


def _fake_result(residual, value, seconds=1.0):
    from types import SimpleNamespace

    return SimpleNamespace(residual=residual, seconds=seconds,
                           region_confidence={7: {"mean_yield_per_mm": value}})


def test_a_method_that_fits_no_better_on_the_chosen_boundary_keeps_the_segmentation_s_values():
    """HP is solved first and judges: fitting better on the chosen boundary, both
    re-solves are taken (SP's own damped fit, worse there, does not decide). HP no
    better there: both declined, with HP's residuals, and SP is not solved at all.
    Without HP, SP's own fit decides."""
    from FluoTomoLib.tomography.reconstruct import _judged_solves, _take_quoted

    def solver(results):
        calls = []

        def solve_one(method, i, n):
            calls.append((method, i, n))
            return results[method]
        return solve_one, calls

    solved = {"HP": (_fake_result(4.0, 0.006), []), "SP": (_fake_result(2.0, 0.005), [])}
    solve_one, calls = solver({"HP": (_fake_result(1.0, 0.002), [0.1]),
                               "SP": (_fake_result(2.5, 0.003), [])})
    done, declined = _judged_solves(["SP", "HP"], solved, solve_one)
    assert calls == [("HP", 0, 2), ("SP", 1, 2)] and declined == {}
    as_given = _take_quoted({m: (*done[m], "moved") for m in done}, solved)
    assert as_given == {"HP": {7: 0.006}, "SP": {7: 0.005}}
    assert solved["HP"][0].region_confidence[7]["mean_yield_per_mm"] == 0.002
    assert solved["HP"][0].seconds == 2.0 and solved["HP"][1] == [0.1]
    assert solved["SP"][0].residual == 2.5

    solved = {"HP": (_fake_result(4.0, 0.006), []), "SP": (_fake_result(2.0, 0.005), [])}
    solve_one, calls = solver({"HP": (_fake_result(5.0, 0.002), []),
                               "SP": (_fake_result(1.5, 0.003), [])})
    done, declined = _judged_solves(["SP", "HP"], solved, solve_one)
    assert calls == [("HP", 0, 2)] and done == {}
    assert declined == {"HP": (5.0, 4.0, "HP"), "SP": (5.0, 4.0, "HP")}

    solve_one, calls = solver({"SP": (_fake_result(2.5, 0.003), [])})
    assert _judged_solves(["SP"], {"SP": (_fake_result(2.0, 0.005), [])}, solve_one) == (
        {}, {"SP": (2.5, 2.0, "SP")})


def test_the_outer_value_is_the_next_offset_out_or_as_far_again_as_the_step_in():
    from FluoTomoLib.tomography.reconstruct import _outer_value

    offsets, values = [-2.0, -1.0, 1.0, 2.0], [40.0, 20.0, 5.0, 3.0]
    assert _outer_value(offsets, 2, values, 10.0) == 3.0        # +1 -> +2
    assert _outer_value(offsets, 1, values, 10.0) == 40.0       # -1 -> -2
    assert _outer_value(offsets, 3, values, 10.0) == 1.0        # +2: 3 - (5 - 3)
    assert _outer_value(offsets, 0, values, 10.0) == 60.0       # -2: 40 + (40 - 20)
    assert _outer_value([-1.0, 1.0], 1, [20.0, 5.0], 10.0) == 0.0   # +1: 5 - (10 - 5)


def test_the_mesh_placement_part_is_hp_s_largest_move_on_both_sides():
    """The placement test's values (unmoved first) become each region's
    ``mesh_placement_per_mm``: the largest relative move times this method's own
    value, added below and above; a region the test has no value for is left."""
    from FluoTomoLib.tomography.reconstruct import _add_mesh_placements

    summary = {"notes": [], "regions": {
        "7": {"yield_per_mm": 0.002, "ci95_per_mm": [0.0019, 0.0021], "interval_parts": {}},
        "3": {"yield_per_mm": 1e-5, "ci95_per_mm": [0.0, 2e-5], "interval_parts": {}},
        "9": {"yield_per_mm": 0.004, "ci95_per_mm": [0.0039, 0.0041], "interval_parts": {}}}}
    _add_mesh_placements(summary, {"shifts_mm": [[0.2, 0.2, 0.2]],
                                   "values_per_mm": {7: [0.004, 0.0036], 3: [1e-5, 1.1e-5]}})
    r = summary["regions"]["7"]
    assert r["interval_parts"]["mesh_placement_per_mm"] == pytest.approx(0.1 * 0.002)
    assert r["ci95_per_mm"] == pytest.approx([0.0017, 0.0023])
    assert summary["regions"]["3"]["ci95_per_mm"][0] == 0.0         # clipped at zero
    assert "mesh_placement_per_mm" not in summary["regions"]["9"]["interval_parts"]
    assert summary["mesh_placement"]["shifts_mm"] == [[0.2, 0.2, 0.2]]
    assert "10 %" in summary["notes"][-1]


@pytest.mark.slow      # one scene simulated (fine) and reconstructed (HP): about 10 s
def test_hp_s_interval_counts_where_the_mesh_falls():
    """Scene 12: an inclusion 1.1 mm under an oblique surface, 'fast'. HP is +15 %
    off with a fair fit (3x the noise) and its interval, +-13 % without the mesh's
    own part, ended below the truth with no warning. With the grid shifted by half
    an element across the target the value moves by about 10 %; that move is in
    the interval, which holds the truth."""
    from FluoTomoLib.tomography import optics_from_dict
    from FluoTomoLib.tomography.reconstruct import reconstruct_labelmap_methods
    from FluoTomoLib.validation.family import simulate

    scene = make_scene(12)
    acq, _ = simulate(scene)
    s = reconstruct_labelmap_methods(scene.labelmap(recon=True), optics_from_dict(scene.optics),
                                     acq, methods=["HP"], accuracy="fast",
                                     target=scene.target())["HP"]["summary"]
    truth = scene.yield_by_label[7]
    r = s["regions"]["7"]
    assert r["yield_per_mm"] > 1.1 * truth
    moved = s["mesh_placement"]["values_per_mm"][7]
    part = r["interval_parts"]["mesh_placement_per_mm"]
    assert part == pytest.approx(abs(moved[1] / moved[0] - 1) * r["yield_per_mm"])
    assert part > 0.05 * r["yield_per_mm"]
    assert r["ci95_per_mm"][0] <= truth <= r["ci95_per_mm"][1], (r["ci95_per_mm"], truth)


@pytest.mark.slow      # one scene simulated (fine) and reconstructed (HP): about 10 s
def test_the_optodes_coupling_is_no_change_of_boundary():
    """Scene 9, segmented correctly, 'fast': the model reads each optode a few per
    cent off (94-99 % of its error in the data is one gain per source and per
    detector), and an inclusion shrunk by 0.49 mm mimicked part of that: the
    segmentation was ruled out by 166 residual variances and HP's interval (value
    -2.7 %) reached +277 %. Compared on the fits with each optode's gain as an
    unknown, the segmentation as given fits best, and the interval is narrow and
    holds the truth; the value is the plain fit's, as before."""
    from FluoTomoLib.tomography import optics_from_dict
    from FluoTomoLib.tomography.reconstruct import reconstruct_labelmap_methods
    from FluoTomoLib.validation.family import simulate

    scene = make_scene(9)
    acq, _ = simulate(scene)
    s = reconstruct_labelmap_methods(scene.labelmap(recon=True), optics_from_dict(scene.optics),
                                     acq, methods=["HP"], accuracy="fast",
                                     target=scene.target())["HP"]["summary"]
    seg = s["segmentation"]
    assert seg["optode_gains"] and seg["best_offset_mm"] == 0.0, seg
    assert not any("fit the data better" in t for t in s["warnings"])
    truth = scene.yield_by_label[7]
    r = s["regions"]["7"]
    lo, hi = r["ci95_per_mm"]
    assert lo <= truth <= hi and (hi - lo) / 2 < 0.2 * truth, (lo, hi, truth)
    # the fit the value comes from still misses the data by the optodes' gains
    assert s["solver"]["diagnostics"]["fit"]["residual_over_noise"] > 4


def test_a_region_moved_rigidly_takes_the_background_s_voxels_only():
    """Moves are rounded to whole voxels of the anisotropic grid; a moved region
    hands the voxels it left to the background, keeps off air and the other
    regions, and a move that leaves it nothing is refused (None)."""
    from FluoTomoLib.tomography.model import translate_regions

    lab = np.full((6, 8, 10), 3, np.int16)                 # (k, j, i); background 3
    lab[:, :, 0] = 0                                       # air at i = 0
    lab[2:4, 3:5, 1:3] = 7
    lab[2:4, 3:5, 5:7] = 8
    sp = (0.5, 1.0, 1.0)                                   # mm along i, j, k
    out = translate_regions(lab, sp, {7: (1.0, 0.0, 0.0)}, 3)        # 2 voxels along +i
    assert (out[2:4, 3:5, 3:5] == 7).all() and (out[2:4, 3:5, 1:3] == 3).all()
    assert (out == 7).sum() == 8 and (out == 8).sum() == 8 and (out == 0).sum() == 48
    out = translate_regions(lab, sp, {7: (-0.5, 0.0, 0.0)}, 3)       # 1 voxel into the air
    assert (out == 7).sum() == 4 and (out[:, :, 0] == 0).all()
    out = translate_regions(lab, sp, {8: (0.0, 0.0, 1.2)}, 3)        # 1 voxel along +k
    assert (out[3:5, 3:5, 5:7] == 8).all() and (out[2, 3:5, 5:7] == 3).all()
    assert translate_regions(lab, sp, {7: (2.0, 0.0, 0.0)}, 3) is None   # onto label 8
    assert translate_regions(lab, sp, {7: (0.0, 0.0, 0.4)}, 3)[2, 3, 1] == 7   # rounds to 0


def _fit(rss, value):
    """A segmentation-test solve: its fit with the optodes' gains (``rss``, against a
    stated noise) and its region 7's value."""
    from types import SimpleNamespace

    res = SimpleNamespace(residual=10 * rss, diagnostics={"effective_parameters": 2.0},
                          coupling=SimpleNamespace(rss=rss, residual_over_noise=1.5,
                                                   parameters=10))
    return res, {7: value}


@pytest.mark.parametrize("outer_rss", [30.0, 5.0])
def test_a_rigid_move_is_quoted_only_where_the_same_move_twice_fits_worse(outer_rss):
    """The offsets fit worse than the segmentation as given, a move of the inclusion
    by 1 mm along -k far better (79 residual variances): it is the best move, and its
    values are quoted where the move twice fits worse (the data's best move lies
    inside those tried); where twice fits better still, it is the best, at the edge
    of the moves tried: nothing is quoted and nothing ruled out (no bracket)."""
    from FluoTomoLib.tomography.model import _shift_summary

    res0, base = _fit(100.0, 0.004)
    moved = [_fit(r, 0.004 + d) for r, d in ((200, 0.004), (150, 0.002), (120, -0.001),
                                             (300, -0.002))]
    one, twice = {7: (0.0, 0.0, -1.0)}, {7: (0.0, 0.0, -2.0)}
    translated = [{"moves_mm": one, "outer_of": None, "result": _fit(10.0, 0.003)},
                  {"moves_mm": {7: (1.0, 0.0, 0.0)}, "outer_of": None,
                   "result": _fit(90.0, 0.0045)},
                  {"moves_mm": twice, "outer_of": 0, "result": _fit(outer_rss, 0.0025)}]
    s = _shift_summary(res0, base, moved, [-2.0, -1.0, 1.0, 2.0], 100, translated)
    assert s["best_offset_mm"] == 0.0 and s["quoted_offset_mm"] is None
    assert s["unmoved_ruled_out"]
    assert [t["shifts"][7] for t in s["translations"]] == pytest.approx([-0.001, 0.0005,
                                                                         -0.0015])
    if outer_rss > 10:
        assert s["best_move"] == one and s["quoted_translation"] == 0
        assert s["unmoved_excess"] == pytest.approx(90 / (100 / 88))
        assert [t["kept"] for t in s["translations"]] == [True, False, False]
        assert s["kept"] == [False] * 4 and not s["best_at_edge"]
    else:
        assert s["best_move"] == twice and s["quoted_translation"] is None
        assert s["best_at_edge"] and s["kept"] == [True] * 4
        assert [t["kept"] for t in s["translations"]] == [True] * 3


def test_a_quoted_rigid_move_s_interval_reaches_the_segmentation_and_half_way_to_twice():
    """Quoted at the inclusion moved 1 mm along -k (HP 0.003 there, 0.004 as
    segmented, 0.0025 moved twice): the value is the method's own on the moved
    segmentation, the interval reaches its value as given and half-way to the move
    twice (HP's relative change), and the warning names the move."""
    from FluoTomoLib.tomography.reconstruct import _add_segmentation

    rec = _seg_record(None)
    rec.update(kept=[False] * 4, best_offset_mm=0.0, best_move={7: [0.0, 0.0, -1.0]},
               quoted_translation=0, translations=[
                   {"moves_mm": {7: [0.0, 0.0, -1.0]}, "outer_of": None, "kept": True,
                    "excess_over_best": 0.0, "shifts": {7: -0.001, 3: 0.0}},
                   {"moves_mm": {7: [0.0, 0.0, -2.0]}, "outer_of": 0, "kept": False,
                    "excess_over_best": 30.0, "shifts": {7: -0.0015, 3: 0.0}}])
    v7 = 0.0033
    summary = {"warnings": [], "regions": {
        "7": {"yield_per_mm": v7, "ci95_per_mm": [v7 - 1e-4, v7 + 1e-4], "interval_parts": {}},
        "3": {"yield_per_mm": 0.0, "ci95_per_mm": [0.0, 1e-6], "interval_parts": {}}}}
    _add_segmentation(summary, rec, 1.0, "HP", {7: 0.0045, 3: 0.0})
    seg, r7 = summary["segmentation"], summary["regions"]["7"]
    assert seg["quoted_move_mm"] == {7: [0.0, 0.0, -1.0]} and seg["quoted_offset_mm"] is None
    assert r7["as_segmented_per_mm"] == 0.0045
    # relative to HP's 0.003 on the moved segmentation: twice 0.0025 / 0.003 of the value
    assert r7["rigid_move_values_per_mm"] == pytest.approx([v7, v7 * 2.5 / 3])
    assert r7["ci95_per_mm"] == pytest.approx([v7 - 0.5 * v7 / 6 - 1e-4, 0.0045 + 1e-4])
    said = [w for w in summary["warnings"] if "fit the data better with label 7 moved 1 mm "
            "along -k than as segmented" in w]
    assert len(said) == 1 and "the values are those of the regions with label 7 moved" in said[0]


@pytest.mark.parametrize("edge, gains", [(False, True), (True, True), (True, False)])
def test_a_best_offset_at_the_edge_of_those_tried_rules_nothing_out(edge, gains):
    """The segmentation as given ruled out by the inclusion grown 1 mm (inside the
    offsets tried): the chi^2 rule keeps the offsets near the best. Grown 2 mm, the
    last offset tried, fitting best: the data's best lies beyond, none is ruled out
    (the intervals reach every offset's value) and nothing is quoted. Without the
    gains' fits against a stated noise (the plain residuals: the demo's tubes) the
    chi^2 rule stands, as before."""
    from FluoTomoLib.tomography.model import _shift_summary

    def fit(rss, value):
        res, values = _fit(rss, value)
        if not gains:
            res.coupling, res.residual = None, rss
        return res, values

    res0, base = fit(100.0, 0.004)
    rss = [300, 200, 10, 60] if not edge else [300, 200, 60, 10]
    moved = [fit(r, 0.004 - 0.001 * k) for k, r in enumerate(rss)]
    s = _shift_summary(res0, base, moved, [-2.0, -1.0, 1.0, 2.0], 100)
    assert s["unmoved_ruled_out"] and s["best_at_edge"] == (edge and gains)
    assert s["best_offset_mm"] == (2.0 if edge else 1.0) == s["best_move"]
    assert s["kept"] == ([True] * 4 if edge and gains else
                         [False, False, False, True] if edge else [False, False, True, False])
    assert s["quoted_offset_mm"] == (None if edge else 1.0)


@pytest.mark.parametrize("plain, asks", [(1.3, False), (9.0, True), (None, False)])
def test_a_poor_plain_fit_asks_for_the_rigid_moves_where_the_gains_fit_well(plain, asks):
    """The segmentation as given fits best with the optodes' gains, at 1.5x the noise,
    and the offsets are ruled out: nothing else asks for the moves. Where the regions
    as segmented fit the data without the gains worse than "fair" (9x the noise), the
    gains may be absorbing a shift (fresh scenes 162, 163): the moves run."""
    from FluoTomoLib.tomography.model import _leaves_a_question, _shift_summary

    res0, base = _fit(10.0, 0.004)
    res0.diagnostics["fit"] = None if plain is None else {"residual_over_noise": plain}
    moved = [_fit(r, 0.004 - 0.001 * k) for k, r in enumerate([300, 200, 150, 400])]
    s = _shift_summary(res0, base, moved, [-2.0, -1.0, 1.0, 2.0], 100)
    assert not s["unmoved_ruled_out"] and s["best_offset_mm"] == 0.0
    assert s["boundaries_explain_data"] and s["best_fit_over_noise"] == 1.5
    assert _leaves_a_question(s) is asks
