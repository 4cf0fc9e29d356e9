"""``fluo tomo batch``: many own scenes on the run engine. Rows and files per
case, a case that fails only when it runs, the same table serially and on two
Dask workers, resuming, and bad batch files refused before any work."""

import json
from pathlib import Path

import forkserver
import numpy as np
import pytest

from fluoguide.errors import FluoInputError
from fluoguide.labelmap_io import read_volume_nrrd, write_volume_nrrd
from fluoguide.phantoms import ellipsoid_inclusion_labelmap, ellipsoid_inclusion_optics
from fluoguide.runs.store import read_table, stable_columns
from FluoTomoLib.tomography import (LabelMap, optics_from_dict, simulate_acquisition,
                                    write_acquisition)
from FluoTomoLib.tomography.batch import load_batch, run_batch

TRUTH = 2.6e-3          # yield of the inclusion (label 7) [1/mm]
SCAN = {"sources_per_side": 3, "detectors_per_side": 4, "detector_pitch_mm": 2.0}
HEADER = "name,labels,optics,acquisition,methods,target,truth\n"


def _fluo(args, cwd, timeout=300):
    """``fluo ARGS`` forked from the tests' fork server (conftest.py; one library thread)."""
    return forkserver.fluo(*args, cwd=cwd, timeout=timeout)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """A small body (12 x 10 x 7 mm semi-axes, 1 mm voxels) with a 4 mm inclusion
    2 mm deep, a dye whose absorption is not modelled (linear in the yield),
    two acquisitions simulated on the whole-map mesh with different noise seeds
    (the reconstruction meshes only the region of interest, at another size),
    and one acquisition whose optodes float 6 mm above the skin: it reads, and
    fails only when the reconstruction places the optodes on the surface."""
    d = tmp_path_factory.mktemp("scenes")
    sc = ellipsoid_inclusion_labelmap(semi_axes_mm=(12.0, 10.0, 7.0), spacing_mm=(1.0, 1.0, 1.0),
                                      inclusion_diameter_mm=4.0, inclusion_gap_mm=2.0,
                                      inclusion_offset_mm=(0.0, 0.0))
    write_volume_nrrd(d / "labels.nrrd", sc["labels_kji"], sc["spacing_mm"], sc["origin_mm"],
                      sc["direction"])
    doc = dict(ellipsoid_inclusion_optics(), fluorophore=None)
    (d / "optics.json").write_text(json.dumps(doc))
    lm = LabelMap.from_file(d / "labels.nrrd")
    optics = optics_from_dict(doc)
    for seed in (1, 2):
        acq, _ = simulate_acquisition(lm, optics, {7: TRUTH}, noise_pct=1.0, seed=seed,
                                      accuracy="fast", scan=SCAN)
        write_acquisition(d / f"acq{seed}", acq)
    up = sc["direction"] @ np.array([0.0, 0.0, 1.0])
    acq.sources_ras_mm = acq.sources_ras_mm + 6.0 * up
    acq.detectors_ras_mm = acq.detectors_ras_mm + 6.0 * up
    write_acquisition(d / "floating", acq)
    return {"dir": d, "centre": sc["inclusion_centre_ras_mm"]}


def _batch(folder, rows, name="batch.csv"):
    shared = Path(folder)
    for f in ("labels.nrrd", "optics.json"):
        if not (shared / f).exists():
            raise AssertionError(f)
    p = shared / name
    p.write_text(HEADER + "".join(rows))
    return p


GOOD = ["a,labels.nrrd,optics.json,acq1,\"NP,SP,HP\",7,0.0026\n",
        "b,labels.nrrd,optics.json,acq2,HP,,0.0026\n"]


def test_batch_cli_rows_files_and_a_case_that_fails_when_it_runs(scenes, tmp_path):
    """Real CLI: three cases; the floating one fails in its task (exit 1, its row
    says why), the two others are written. HP within 15 % of the true yield
    (the small-scene tolerance of test_own_scene.py: a 4 mm inclusion meshed at
    'fast' on 1 mm voxels, data from a different, finer mesh) and its
    half-maximum centroid within 3 mm (three voxels) of the inclusion's."""
    d = scenes["dir"]
    batch = _batch(d, GOOD + ["broken,labels.nrrd,optics.json,floating,HP,7,\n"], "cli.csv")
    out = tmp_path / "run"
    r = _fluo(["tomo", "batch", str(batch), "--out", str(out), "--accuracy", "fast", "--json"], d)
    assert r.returncode == 1, r.stderr[-3000:]
    assert r.stderr.strip().splitlines()[-1].startswith("fluo: error: 1 of 3 cases failed")
    doc = json.loads(r.stdout)
    assert doc["tasks"] == 3 and doc["failures"] == 1 and doc["computed"] == 3
    rows = {row["name"]: row for row in doc["rows"]}
    assert [row["name"] for row in doc["rows"]] == ["a", "b", "broken"]
    assert rows["broken"]["status"] == "failed" and "from it" in rows["broken"]["error"]
    assert any(w.startswith("broken: failed: FluoInputError") for w in doc["warnings"])
    for name in ("a", "b"):
        row = rows[name]
        assert row["status"] == "ok" and row["target"] == 7 and row["mesh_nodes"] > 1000
        assert abs(row["HP_error_pct"]) < 15.0, row
        assert row["HP_centroid_error_mm"] < 3.0
        assert np.linalg.norm(np.subtract(row["HP_centroid_ras_mm"], scenes["centre"])) < 3.0
        assert row["HP_iterations"] >= 1 and row["HP_warnings_n"] == len(
            [w for w in row["HP_warnings"].split(" | ") if w])
    assert "NP_yield_per_mm" in rows["a"] and rows["b"].get("NP_yield_per_mm") is None
    # the files: one folder per ok case and method, on the label map's grid
    lab, sp, org, direction = read_volume_nrrd(d / "labels.nrrd")
    for name, methods in (("a", ("NP", "SP", "HP")), ("b", ("HP",))):
        for m in methods:
            f = out / "cases" / name / m
            vol, sp2, org2, d2 = read_volume_nrrd(f / "yield.nrrd")
            summary = json.loads((f / "reconstruction.json").read_text())
            assert vol.shape == lab.shape and np.allclose(sp2, sp) and np.allclose(d2, direction)
            assert np.allclose(org2, org, atol=1e-4) and np.all(vol[lab == 0] == 0)
            assert summary["method"] == m and summary["target"] == 7
            assert summary["regions"]["7"]["yield_per_mm"] == rows[name][f"{m}_yield_per_mm"]
            assert vol.max() == pytest.approx(rows[name][f"{m}_peak_per_mm"], rel=1e-6)
    assert not (out / "cases" / "broken").exists()
    saved = json.loads((out / "batch.json").read_text())
    assert saved["failures"] == 1 and saved["warnings"] == doc["warnings"]
    cols, table = read_table(out / "table.csv")
    assert [t["status"] for t in table] == ["ok", "ok", "failed"] and "HP_error_pct" in cols


def test_batch_resumes_computing_only_the_missing_case(scenes, tmp_path):
    batch = _batch(scenes["dir"], GOOD + ["# c,labels.nrrd,optics.json,acq1,HP,,\n"],
                   "resume.csv")                          # a comment line is not a case
    cases = load_batch(batch, accuracy="fast")
    assert [c["name"] for c in cases] == ["a", "b"]
    first = run_batch(cases, tmp_path / "run")
    assert first["computed"] == 2 and first["failures"] == 0
    cols, rows1 = read_table(tmp_path / "run" / "table.csv")
    b = next(r for r in first["rows"] if r["name"] == "b")
    (tmp_path / "run" / "tasks" / f"{b['task']}.json").unlink()      # as if killed before b
    vol_a = (tmp_path / "run" / "cases" / "a" / "SP" / "yield.nrrd").read_bytes()
    again = run_batch(cases, tmp_path / "run", resume=True)
    assert again["computed"] == 1 and again["reused"] == 1 and again["failures"] == 0
    cols2, rows2 = read_table(tmp_path / "run" / "table.csv")
    keep = stable_columns(cols)
    assert cols2 == cols and [[r[c] for c in keep] for r in rows2] == [
        [r[c] for c in keep] for r in rows1]
    # the reused case's files are written again from its stored arrays, unchanged
    assert (tmp_path / "run" / "cases" / "a" / "SP" / "yield.nrrd").read_bytes() == vol_a
    # an input changed under the same name is a new task, not a stale reuse
    (scenes["dir"] / "optics2.json").write_text(json.dumps(dict(
        ellipsoid_inclusion_optics(), fluorophore=None, n=1.4)))
    changed = load_batch(_batch(scenes["dir"], [GOOD[0].replace("optics.json", "optics2.json")],
                                "changed.csv"), accuracy="fast")
    assert changed[0]["inputs_sha1"] != cases[0]["inputs_sha1"]


@pytest.mark.slow
def test_batch_gives_the_same_table_serially_and_on_two_workers(scenes, tmp_path):
    """Real CLI, serial and on a 2-worker local cluster (12.5 s in all on a quiet
    2-core machine, 24 s loaded: slow): the stable columns of the tables and the
    volumes are identical."""
    d = scenes["dir"]
    batch = _batch(d, GOOD, "workers.csv")
    runs = {}
    for name, extra in (("serial", []), ("dask", ["--workers", "2", "--no-dashboard"])):
        r = _fluo(["tomo", "batch", str(batch), "--out", str(tmp_path / name), "--accuracy",
                   "fast", "--json", *extra], d)
        assert r.returncode == 0, r.stderr[-3000:]
        runs[name] = json.loads(r.stdout)
    assert runs["dask"]["workers"] == 2 and runs["serial"]["workers"] == 1
    ca, ra = read_table(tmp_path / "serial" / "table.csv")
    cb, rb = read_table(tmp_path / "dask" / "table.csv")
    assert ca == cb
    keep = stable_columns(ca)
    assert [[r[c] for c in keep] for r in ra] == [[r[c] for c in keep] for r in rb]
    assert all(r["worker"] != ra[0]["worker"] for r in rb)
    for m in ("NP", "SP", "HP"):
        assert (tmp_path / "serial" / "cases" / "a" / m / "yield.nrrd").read_bytes() == (
            tmp_path / "dask" / "cases" / "a" / m / "yield.nrrd").read_bytes()


@pytest.mark.parametrize("rows, needle", [
    (["a,labels.nrrd,optics.json,,HP,7,\n"], "line 2, acquisition: missing"),
    (["a,labels.nrrd,optics.json,nowhere,HP,7,\n"], "line 2, acquisition: folder not found"),
    (["a,../labels.nrrd,optics.json,acq1,HP,7,\n"], "inside the batch file's folder"),
    (GOOD[:1] + ["a,labels.nrrd,optics.json,acq2,HP,7,\n"], "line 3, name: duplicate case name"),
    (["a,labels.nrrd,optics.json,acq1,\"HP,XP\",7,\n"], "line 2, methods: methods are NP, SP"),
    (["a,labels.nrrd,optics.json,acq1,HP,5,\n"], "line 2, target: target label is not"),
    (["a,labels.nrrd,optics.json,acq1,HP,7,nan\n"], "line 2, truth"),
    (["a/b,labels.nrrd,optics.json,acq1,HP,7,\n"], "line 2, name"),
    (["a,optics.json,optics.json,acq1,HP,7,\n"], "line 2, labels"),
])
def test_bad_batch_rows_are_refused_before_any_work(scenes, tmp_path, rows, needle):
    batch = _batch(scenes["dir"], rows, "bad.csv")
    with pytest.raises(FluoInputError) as exc:
        load_batch(batch)
    text = str(exc.value)
    assert needle in text and "bad.csv" in text and "\n" not in text


def test_bad_batch_files_exit_2_with_one_line_and_write_nothing(scenes, tmp_path):
    d = scenes["dir"]
    cases = {
        "nocol.csv": ("name,labels,optics\na,labels.nrrd,optics.json\n", "acquisition: missing"),
        "extra.csv": ("name,labels,optics,acquisition,colour\n", "unknown column"),
        "dup.json": (json.dumps({"cases": [{"name": "x", "labels": "labels.nrrd", "optics":
                                            "optics.json", "acquisition": "acq1"}] * 2}),
                     "cases[1], name: duplicate"),
        "list.yaml": ("- labels: labels.nrrd\n", "a batch file holds a mapping"),
    }
    for name, (text, needle) in cases.items():
        (d / name).write_text(text)
        out = tmp_path / name
        r = _fluo(["tomo", "batch", str(d / name), "--out", str(out)], d)
        assert r.returncode == 2, (name, r.stderr)
        assert needle in r.stderr and name in r.stderr, (name, r.stderr)
        assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr
        assert not out.exists()


def test_yaml_batch_with_defaults_and_derived_names(scenes, tmp_path):
    d = scenes["dir"]
    (d / "b.yaml").write_text("methods: [SP]\naccuracy: fast\ncases:\n"
                              "  - {labels: labels.nrrd, optics: optics.json, acquisition: acq1}\n"
                              "  - {labels: labels.nrrd, optics: optics.json, acquisition: acq1,"
                              " methods: 'np,hp', lambda: 3}\n")
    cases = load_batch(d / "b.yaml")
    assert [c["name"] for c in cases] == ["labels-acq1", "labels-acq1-2"]
    assert [c["methods"] for c in cases] == ["SP", "NP,HP"]     # the file's default, the row's
    assert [c["lambda"] for c in cases] == [None, 3.0]
    assert {c["accuracy"] for c in cases} == {"fast"} and {c["target"] for c in cases} == {7}
    # the command line's values override the file's defaults, never a row's own value
    cases = load_batch(d / "b.yaml", methods="HP", accuracy="balanced")
    assert [c["methods"] for c in cases] == ["HP", "NP,HP"]
    assert {c["accuracy"] for c in cases} == {"balanced"}
    with pytest.raises(FluoInputError, match=r"^--lambda: .*\(got -1.0\)$"):
        load_batch(d / "b.yaml", lam=-1.0)          # the command line's value, named as such


@pytest.mark.parametrize("behaviour, needle", [
    ("silent", "did not answer within 2 s (waited for the Dask handshake"),
    ("random_bytes", "is not a Dask scheduler"),
])
def test_batch_on_a_hostile_scheduler_is_one_line_exit_1_in_bounded_time(behaviour, needle,
                                                                       scenes, tmp_path):
    """``--scheduler`` names a TCP peer on 127.0.0.1 that accepts and never answers
    (the batch hung until killed at 150 s), or sends 4 kB of random bytes and holds
    (a TimeoutError traceback after 68 s): one line naming the address, exit 1,
    within a few of the 2 s limits set by $FLUO_SCHEDULER_TIMEOUT, nothing written."""
    import os
    import time

    import hostile_peers

    d = scenes["dir"]
    batch = _batch(d, GOOD[1:], "hostile.csv")
    out = tmp_path / "run"
    with hostile_peers.TCPPeer(getattr(hostile_peers, behaviour)) as peer:
        t0 = time.monotonic()
        r = forkserver.fluo("tomo", "batch", batch, "--accuracy", "fast", "--out", out,
                            "--scheduler", peer.address, cwd=d, timeout=60,
                            env=dict(os.environ, FLUO_SCHEDULER_TIMEOUT="2"))
        took = time.monotonic() - t0
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 1 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert lines[0].startswith("fluo: error: ") and peer.address in lines[0], lines
    assert needle in lines[0], lines
    assert took < 15.0, took
    assert not out.exists()
