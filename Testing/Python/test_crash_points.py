"""Kill -9 at named crash points (``FLUO_CRASH_AT``, ``fluoguide.atomic``): every
kill provably lands on the step it names, the result on disk is the old whole
result or the new whole one (as a loader, which rolls a journal forward, reads
it), and the next normal run, or ``--resume``, clears the debris and completes
(issue #29: the random-moment kills of issue #21 could pass without ever
interrupting a write).

Each crash runs a real ``python -m fluoapp ...`` (or a small ``python -c``
writer) with ``FLUO_CRASH_AT`` set, and asserts that it died by SIGKILL and that
its stderr names the crash point and the path it was writing."""

import json
import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fluoguide import atomic, mrml_io
from fluoguide.labelmap_io import read_volume_nrrd, write_volume_nrrd
from fluoguide.phantoms import ellipsoid_inclusion_labelmap, ellipsoid_inclusion_optics
from fluoguide.runs.store import read_table, stable_columns

HERE = Path(__file__).resolve().parent
PINNED = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
          "NUMBA_NUM_THREADS": "1"}


def _env(crash=None):
    env = {k: v for k, v in os.environ.items() if k != atomic.CRASH_ENV}
    env.update(PINNED)
    if crash is not None:
        env[atomic.CRASH_ENV] = crash
    return env


def run_to_crash(argv, point, cwd=None, timeout=120):
    """Run ``argv`` with ``FLUO_CRASH_AT=point``; assert that it died by SIGKILL at
    that point (the one stderr line naming it). Returns (the path the line
    names, the finished process)."""
    name = point.rpartition(":")[0] if re.search(r":\d+$", point) else point
    assert name.partition("@")[0] in atomic.CRASH_POINTS, point
    r = subprocess.run(argv, cwd=cwd, env=_env(point), capture_output=True, text=True,
                       timeout=timeout)
    assert r.returncode == -signal.SIGKILL, (r.returncode, r.stderr[-3000:])
    head = f"fluo: crash point {name.partition('@')[0]} reached ({atomic.CRASH_ENV}={point}): "
    hits = [line for line in r.stderr.splitlines() if line.startswith(head)]
    assert len(hits) == 1, r.stderr[-3000:]
    return Path(hits[0][len(head):]), r


def crashed(argv, point, cwd=None, timeout=120):
    """:func:`run_to_crash`'s path."""
    return run_to_crash(argv, point, cwd, timeout)[0]


def fluo(args, cwd=None, timeout=120):
    """``python -m fluoapp ARGS`` run normally (no crash point); exit 0; its JSON
    output when ``--json`` is among the args."""
    r = subprocess.run([sys.executable, "-m", "fluoapp", *map(str, args)], cwd=cwd, env=_env(),
                       capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout) if "--json" in args else None


def crashed_fluo(args, point, cwd=None):
    return crashed([sys.executable, "-m", "fluoapp", *map(str, args)], point, cwd=cwd)


def hidden(folder):
    """Names of the hidden entries (debris, journals) in ``folder``, recursively."""
    return sorted(str(p.relative_to(folder)) for p in Path(folder).rglob(".*"))


# ----------------------------------------------------------------- the crash points
NOT_POINTS = ("atomic.before_rename", "commit.renamed")     # misspelt on purpose


def test_every_crash_point_is_placed_once_and_every_point_a_test_names_exists():
    src = Path(atomic.__file__).read_text()
    placed = re.findall(r'crash_point\("([^"]+)"', src)
    assert sorted(placed) == sorted(atomic.CRASH_POINTS)      # each placed, exactly once
    named = set()
    for test in (HERE / "test_crash_points.py", HERE / "test_atomic_writes.py"):
        named |= set(re.findall(r'"((?:atomic|folder|commit)\.[a-z_]+)[@:"]', test.read_text()))
    assert not set(NOT_POINTS) & set(atomic.CRASH_POINTS)
    assert named - set(NOT_POINTS) <= set(atomic.CRASH_POINTS), named
    assert set(atomic.CRASH_POINTS) <= named, "a crash point that no test reaches"


def test_a_crash_at_value_that_names_no_point_is_refused_and_others_do_not_kill(
        tmp_path, monkeypatch):
    target = tmp_path / "a.txt"
    target.write_bytes(b"old")
    for bad in (NOT_POINTS[0], "atomic.before_replace:0", "atomic.before_replace:x",
                "atomic.before_replace@", "before_replace", "atomic.before_replace:-1"):
        monkeypatch.setenv(atomic.CRASH_ENV, bad)
        with pytest.raises(ValueError, match="FLUO_CRASH_AT"):
            atomic.write_bytes(target, b"new")
        assert target.read_bytes() == b"old" and hidden(tmp_path) == []
    # a valid value for another point, or another file, lets this write through
    for other in ("commit.moved", "atomic.before_replace@b.txt", "atomic.before_replace@x/a.txt"):
        monkeypatch.setenv(atomic.CRASH_ENV, other)
        atomic.write_bytes(target, other.encode())
        assert target.read_bytes() == other.encode()
    monkeypatch.setenv(atomic.CRASH_ENV, "commit.moved")
    with pytest.raises(ValueError, match="not in atomic.CRASH_POINTS"):
        atomic.crash_point(NOT_POINTS[1])


def test_the_nth_hit_of_a_point_kills_and_names_its_path(tmp_path):
    """A small writer: a.txt, b.txt, a.txt, b.txt, each write numbered."""
    code = ("import sys; from fluoguide import atomic\n"
            "for k, name in enumerate('abab'):\n"
            "    atomic.write_text(sys.argv[1] + '/' + name + '.txt', str(k))\n"
            "    print('wrote', k, flush=True)\n")
    # value, the write it interrupts (0-3), the file, then a.txt and b.txt as left
    for point, k, path, a, b in (("atomic.before_replace:3", 2, "a.txt", "0", "1"),
                                 ("atomic.before_replace@b.txt:2", 3, "b.txt", "2", "1"),
                                 ("atomic.before_replace@a.txt", 0, "a.txt", None, None)):
        for f in tmp_path.iterdir():
            f.unlink()
        got, p = run_to_crash([sys.executable, "-c", code, str(tmp_path)], point)
        assert got == tmp_path / path
        assert p.stdout.splitlines() == [f"wrote {j}" for j in range(k)]
        state = {n: (tmp_path / f"{n}.txt").read_text() if (tmp_path / f"{n}.txt").exists()
                 else None for n in "ab"}
        assert state == {"a": a, "b": b}              # the interrupted file holds its old text
        debris = hidden(tmp_path)
        assert len(debris) == 1 and debris[0].startswith(f".{path}.tmp-"), debris
        # the debris is the complete new text, never at the final name
        assert (tmp_path / debris[0]).read_text() == str(k)
    atomic.write_text(tmp_path / "a.txt", "next")     # the next write clears the debris
    assert hidden(tmp_path) == [] and (tmp_path / "a.txt").read_text() == "next"


# ----------------------------------------------------------------- a scene save
def _save_in_child(target, version, point):
    code = (f"import sys; sys.path.insert(0, {str(HERE)!r})\n"
            "from test_scene_hostile import _scene_with\n"
            "from fluoguide import mrml_io\n"
            f"mrml_io.save_scene(_scene_with({version}), {str(target)!r})\n")
    return crashed([sys.executable, "-c", code], point)


def _files(folder):
    return {p.name: p.read_bytes() for p in Path(folder).iterdir() if not p.name.startswith(".")}


@pytest.mark.parametrize("point, seen, journal", [
    ("atomic.before_replace@.fluo-commit.json", 1, False),   # the journal's own temp file
    ("commit.before_journal", 1, False),
    ("commit.journal_written", 2, True),
    ("commit.moved:1", 2, True),              # one of four files moved in
    ("commit.moved@scene.mrml", 2, True),     # all moved, the journal still there
    ("commit.before_cleanup", 2, False),      # journal gone, staging folder left
])
def test_scene_save_killed_at_each_step_of_its_commit_reads_old_or_new(tmp_path, point, seen,
                                                                       journal):
    """save_scene over a saved scene (a journaled commit of four files, the .mrml
    last), killed at each step: the loader reads version 1 or version 2, whole."""
    from test_scene_hostile import _scene_with, _versions

    target = tmp_path / "s" / "scene.mrml"
    mrml_io.save_scene(_scene_with(1), target)
    old = _files(target.parent)
    at = _save_in_child(target, 2, point)
    assert target.parent in (at, at.parent)              # killed inside this scene's commit
    assert (target.parent / atomic.JOURNAL).exists() == journal
    assert hidden(target.parent)                         # the kill left its debris
    if seen == 1:                                        # nothing moved: the old bytes
        assert _files(target.parent) == old
    assert all(len(b) > 0 for b in _files(target.parent).values())
    assert _versions(target) == {seen}                   # the loader rolls forward; never a mix
    assert not (target.parent / atomic.JOURNAL).exists()
    assert not [h for h in hidden(target.parent) if h.startswith(atomic.STAGING_PREFIX)]
    mrml_io.save_scene(_scene_with(3), target)           # the next save: whole, and no debris
    assert _versions(target) == {3} and hidden(target.parent) == []


def test_a_scene_load_killed_while_rolling_a_commit_forward_is_finished_by_the_next(tmp_path):
    from test_scene_hostile import _scene_with, _versions

    target = tmp_path / "s" / "scene.mrml"
    mrml_io.save_scene(_scene_with(1), target)
    _save_in_child(target, 2, "commit.journal_written")
    load = (f"from fluoguide import mrml_io; mrml_io.load_scene({str(target)!r})")
    # the loader's own roll forward is killed after the second of four moves
    assert crashed([sys.executable, "-c", load], "commit.moved:2").name == "CBCTLabels.nrrd"
    assert (target.parent / atomic.JOURNAL).exists()
    assert _versions(target) == {2} and hidden(target.parent) == []


# ----------------------------------------------------------------- a phantom folder
def test_fluo_phantom_killed_before_publishing_and_mid_commit(tmp_path):
    ph = tmp_path / "ph"
    args = ["phantom", "cylinder-tube", "--out", ph, "--voxel-mm", "2", "--seed", "0"]
    assert crashed_fluo(args + ["--depth-mm", "3"], "folder.before_publish@ph") == ph
    assert not ph.exists()                               # no half phantom under its name
    debris = [p for p in tmp_path.iterdir() if p.name.startswith(".ph.stage-")]
    assert len(debris) == 1 and (debris[0] / "scene.mrml").is_file()
    fluo(args + ["--depth-mm", "3"])                     # the next run: whole, debris gone
    assert [p.name for p in tmp_path.iterdir()] == ["ph"] and hidden(ph) == []
    old = json.loads((ph / "truth.json").read_text())
    # over the old phantom: killed after truth.json moved in, scene.mrml not yet
    assert crashed_fluo(args + ["--depth-mm", "6"], "commit.moved@ph/truth.json") == (
        ph / "truth.json")
    assert (ph / atomic.JOURNAL).exists()
    sc = mrml_io.load_scene(ph / "scene.mrml")           # rolls the commit forward
    truth = mrml_io.get_json_attribute(mrml_io.get_node(sc, "CBCTLabels"), "FluoGuide.Truth")
    assert json.loads((ph / "truth.json").read_text()) == truth != old
    assert hidden(ph) == []


# ----------------------------------------------------------------- data sets
def _new_set(folder):
    """{name: bytes} of the set that the interrupted commit in ``folder`` moves in:
    the files already moved, the others still in its staging folder."""
    journal = json.loads((folder / atomic.JOURNAL).read_text())
    stage = folder / journal["stage"]
    return {n: ((stage / n) if (stage / n).exists() else folder / n).read_bytes()
            for n in journal["files"]}


def _read_fresh_copy(files, folder, read):
    """``read`` of ``files`` ({name: bytes}) written into a new ``folder``."""
    folder.mkdir(parents=True)
    for name, data in files.items():
        (folder / name).write_bytes(data)
    return read(folder)


def _same(a, b):
    """Equal nested lists/tuples/dicts of arrays and plain values."""
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, np.ndarray):
        return np.array_equal(a, b)
    return a == b


@pytest.fixture(scope="module")
def light(tmp_path_factory):
    """fluo calib synth-light's three sets (stack, illumination, laser), seed 1."""
    out = tmp_path_factory.mktemp("light") / "light"
    fluo(["calib", "synth-light", "--out", out, "--seed", "1"])
    return out


def _stack(folder):
    from FluoCalibLib.radiometry.camera_response import load_stack

    frames, meta = load_stack(folder)
    return [(f.image, f.exposure_s, f.kind) for f in frames], meta


def _dataset(manifest):
    def read(folder):
        from FluoCalibLib.radiometry.datasets import read_dataset

        return read_dataset(folder, manifest)
    return read


@pytest.mark.parametrize("name, point, read", [
    ("stack", "commit.moved:1", _stack),                  # the run's first commit
    ("illumination", "commit.moved@light/illumination/illum_00.png",
     _dataset("illumination.json")),
    ("laser", "commit.moved@light/laser/laser_00.png", _dataset("laser.json")),
], ids=["stack", "illumination", "laser"])
def test_calibration_sets_killed_mid_commit_read_as_the_new_set(light, tmp_path, name, point,
                                                                read):
    """fluo calib synth-light over an earlier run's sets, killed after the first
    file of a set's commit moved in: its reader rolls the commit forward and
    reads the new set, never the old manifest with some new images."""
    out = tmp_path / "light"
    shutil.copytree(light, out)
    folder = out / name
    old = _files(folder)
    assert crashed_fluo(["calib", "synth-light", "--out", out, "--seed", "2"],
                        point).parent == folder
    new = _new_set(folder)
    assert new.keys() == old.keys() and new != old
    got = read(folder)
    assert _same(got, _read_fresh_copy(new, tmp_path / "new", read))
    assert _files(folder) == new and hidden(folder) == []


# ----------------------------------------------------------------- fluo tomo
@pytest.fixture(scope="module")
def tomo(tmp_path_factory):
    """Small fluo tomo inputs (the fuzz's own scene, smaller: 8 x 7 x 5 mm
    semi-axes at 1 mm, a 3 mm inclusion; an acquisition simulated 'fast') and a
    two-case batch file."""
    d = tmp_path_factory.mktemp("tomo")
    sc = ellipsoid_inclusion_labelmap(semi_axes_mm=(8.0, 7.0, 5.0), spacing_mm=(1.0, 1.0, 1.0),
                                      inclusion_diameter_mm=3.0, inclusion_gap_mm=1.5,
                                      inclusion_offset_mm=(0.0, 0.0))
    write_volume_nrrd(d / "labels.nrrd", sc["labels_kji"], sc["spacing_mm"], sc["origin_mm"],
                      sc["direction"])
    (d / "optics.json").write_text(json.dumps(dict(ellipsoid_inclusion_optics(),
                                                   fluorophore=None)))
    fluo(["tomo", "simulate", "--labels", "labels.nrrd", "--optics", "optics.json", "--yield",
          "7:0.0026", "--accuracy", "fast", "--element-mm", "1.5", "--out", "acq"], cwd=d)
    (d / "batch.csv").write_text("name,labels,optics,acquisition,methods,truth\n"
                                 "a,labels.nrrd,optics.json,acq,HP,0.0026\n"
                                 "b,labels.nrrd,optics.json,acq,SP,0.0026\n")
    return {"dir": d}


@pytest.fixture(scope="module")
def batch_ref(tomo):
    """The batch run once, uninterrupted: its task ids and its table."""
    d = tomo["dir"]
    ref = fluo(["tomo", "batch", "batch.csv", "--out", "ref", "--accuracy", "fast", "--json"],
               cwd=d)
    cols, rows = read_table(d / "ref" / "table.csv")
    return {"dir": d, "ids": {r["name"]: r["task"] for r in ref["rows"]}, "cols": cols,
            "stable": [[r[c] for c in stable_columns(cols)] for r in rows]}


RECONSTRUCT = ["tomo", "reconstruct", "--labels", "labels.nrrd", "--optics", "optics.json",
               "--acquisition", "acq", "--accuracy", "fast", "--method", "HP",
               # the crash points are the subject, not the boundary test: exact boundaries
               "--segmentation-mm", "0"]


def _reconstruction(folder):
    """(summary, volume) of a reconstruction folder, checked to be one whole result."""
    summary = json.loads((folder / "reconstruction.json").read_text())
    vol = read_volume_nrrd(folder / "yield.nrrd")[0]
    assert float(vol.max()) == pytest.approx(summary["peak_yield_per_mm"], rel=1e-6)
    return summary, vol


def test_tomo_reconstruct_killed_before_publishing_its_folder(tomo, tmp_path):
    d, rec = tomo["dir"], tmp_path / "rec"
    assert crashed_fluo(RECONSTRUCT + ["--out", rec], "folder.before_publish", cwd=d) == rec
    assert not rec.exists()
    debris = [p for p in tmp_path.iterdir() if p.name.startswith(".rec.stage-")]
    assert len(debris) == 1 and sorted(p.name for p in debris[0].iterdir()) == [
        "reconstruction.json", "yield.nrrd"]
    fluo(RECONSTRUCT + ["--out", rec], cwd=d)
    assert [p.name for p in tmp_path.iterdir()] == ["rec"] and hidden(rec) == []
    assert _reconstruction(rec)[0]["method"] == "HP"


def test_tomo_reconstruct_killed_mid_commit_over_an_old_folder(tomo, tmp_path):
    from FluoTomoLib.tomography.labelmap import LabelMap
    from FluoTomoLib.tomography.reconstruct import write_reconstruction

    d, rec = tomo["dir"], tmp_path / "rec"
    # an old result, whole, written by the reconstruction's own writer
    lm = LabelMap.from_file(d / "labels.nrrd")
    write_reconstruction(rec, lm, {"summary": {"method": "old", "peak_yield_per_mm": 1.0},
                                   "yield_kji": np.ones(lm.labels_kji.shape, np.float32)})
    old = (rec / "reconstruction.json").read_bytes()
    # yield.nrrd moved in, reconstruction.json (moved last: readers open it first) not yet
    assert crashed_fluo(RECONSTRUCT + ["--out", rec], "commit.moved:1", cwd=d) == rec / "yield.nrrd"
    assert (rec / atomic.JOURNAL).exists() and (rec / "reconstruction.json").read_bytes() == old
    # what a loader sees: it rolls the journal forward (on a copy: the next run's own
    # roll forward is checked below) and reads the new result, whole
    seen = tmp_path / "seen"
    shutil.copytree(rec, seen, symlinks=True)
    assert atomic.recover(seen)
    summary, _ = _reconstruction(seen)
    assert summary["method"] == "HP" and summary["lambda"] == 10 and hidden(seen) == []
    fluo(RECONSTRUCT + ["--lambda", "3", "--out", rec], cwd=d)      # the next run completes
    assert hidden(rec) == [] and _reconstruction(rec)[0]["lambda"] == 3


def test_tomo_simulate_killed_mid_commit_reads_as_the_new_acquisition(tomo, tmp_path):
    """fluo tomo simulate over an old acquisition, killed after data.csv moved in
    (acquisition.json not yet): the reader rolls the commit forward."""
    from FluoTomoLib.tomography.acquisition_file import read_acquisition

    def read(folder):
        acq = read_acquisition(folder)
        return [acq.sources_ras_mm, acq.detectors_ras_mm, acq.data, acq.mask]

    d, acq = tomo["dir"], tmp_path / "acq"
    shutil.copytree(d / "acq", acq)
    old = _files(acq)
    assert crashed_fluo(["tomo", "simulate", "--labels", "labels.nrrd", "--optics",
                         "optics.json", "--yield", "7:0.004", "--accuracy", "fast",
                         "--element-mm", "1.5", "--out", acq], "commit.moved:1",
                        cwd=d) == acq / "data.csv"
    new = _new_set(acq)
    assert new["data.csv"] != old["data.csv"] and new["acquisition.json"] != old[
        "acquisition.json"]
    got = read(acq)
    assert _same(got, _read_fresh_copy(new, tmp_path / "new", read))
    assert _files(acq) == new and hidden(acq) == []


def _batch_whole(out, ref, computed, reused, result):
    assert result["computed"] == computed and result["reused"] == reused
    assert result["failures"] == 0
    cols, rows = read_table(out / "table.csv")
    assert cols == ref["cols"]                                        # as uninterrupted
    assert [[r[c] for c in stable_columns(cols)] for r in rows] == ref["stable"]
    for name, m in (("a", "HP"), ("b", "SP")):
        summary, _ = _reconstruction(out / "cases" / name / m)
        assert summary["method"] == m
    assert hidden(out) == []                                          # no debris anywhere


@pytest.mark.slow      # a batch killed and resumed: 20.7 s under CI's load (2026-11-27)
def test_tomo_batch_killed_writing_a_case_record_resumes_to_the_same_table(batch_ref, tmp_path):
    d, out, ids = batch_ref["dir"], tmp_path / "runs", batch_ref["ids"]
    batch = ["tomo", "batch", "batch.csv", "--out", out, "--accuracy", "fast"]
    rec_b = f"{ids['b']}.json"
    # case a finished; case b's record complete in its temporary file, not renamed
    assert crashed_fluo(batch, f"atomic.before_replace@{rec_b}", cwd=d) == out / "tasks" / rec_b
    tasks = out / "tasks"
    assert json.loads((tasks / f"{ids['a']}.json").read_text())["status"] == "ok"
    assert not (tasks / rec_b).exists()
    assert [h for h in hidden(tasks) if h.startswith(f".{rec_b}.tmp-")]
    cols, rows = read_table(out / "table.csv")               # the table so far, whole
    assert [r["name"] for r in rows] == ["a"]
    _batch_whole(out, batch_ref, 1, 1, fluo(batch + ["--resume", "--json"], cwd=d))


def test_tomo_batch_killed_writing_the_table_and_the_case_folders_resumes(batch_ref, tmp_path):
    d, out = batch_ref["dir"], tmp_path / "runs"
    batch = ["tomo", "batch", "batch.csv", "--out", out, "--accuracy", "fast"]
    # every record written; the final table (the 4th write of table.csv: empty,
    # after a, after b with b's new columns, final) complete in its temporary file
    table = out / "table.csv"
    assert crashed_fluo(batch, "atomic.before_replace@table.csv:4", cwd=d) == table
    cols, rows = read_table(table)                           # the appended table, whole
    assert [r["name"] for r in rows] == ["a", "b"] and all(r["status"] == "ok" for r in rows)
    assert not (out / "cases").exists()
    # resumed (nothing to compute): killed after case a's folder, before case b's appears
    resume = batch + ["--resume"]
    assert crashed_fluo(resume, "folder.before_publish@b/SP", cwd=d) == out / "cases" / "b" / "SP"
    assert _reconstruction(out / "cases" / "a" / "HP")[0]["method"] == "HP"
    assert not (out / "cases" / "b" / "SP").exists()
    assert [p.name for p in (out / "cases" / "b").iterdir() if p.name.startswith(".SP.stage-")]
    _batch_whole(out, batch_ref, 0, 2, fluo(resume + ["--json"], cwd=d))
    assert json.loads((out / "batch.json").read_text())["reused"] == 2
