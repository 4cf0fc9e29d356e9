"""The run engine end to end: the serial loop, `fluo study` options, a killed run
that resumes, and a real Dask scheduler and workers started as separate processes."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from dask_processes import DaskProcesses, stop_process
from fluoapp.cli import main
from fluoguide.errors import FluoInputError
from fluoguide.runs.engine import run_tasks
from fluoguide.runs.store import RunStore, read_table, stable_columns
from fluoguide.runs.tasks import Shared, Task

CALLS = []


def _square_plus(params, offset):
    CALLS.append(params["x"])
    if params["x"] == 3:
        raise ArithmeticError("three is refused")
    return {"y": params["x"] ** 2 + offset["value"], "note": "ok"}


def _offset(value):
    CALLS.append("offset")
    return {"value": value}


def test_serial_engine_shares_inputs_reports_failures_and_resumes(tmp_path):
    off = Shared("offset 0.5", _offset, (0.5,))
    tasks = [Task(_square_plus, {"x": x}, {"offset": off}) for x in range(5)]
    CALLS.clear()
    out = run_tasks(tasks, store=RunStore(tmp_path))
    assert CALLS.count("offset") == 1 and out["shared_inputs"] == 1
    assert [r["status"] for r in out["rows"]] == ["ok"] * 3 + ["failed", "ok"]
    assert out["rows"][3]["error"] == "ArithmeticError: three is refused"
    assert [r.get("y") for r in out["rows"]] == [0.5, 1.5, 4.5, None, 16.5]
    cols, rows = read_table(tmp_path / "table.csv")
    assert cols[:3] == ["task", "x", "y"] and rows[3]["status"] == "failed"
    # resume: the four finished tasks are reused, the failed one is tried again
    CALLS.clear()
    again = run_tasks(tasks, store=RunStore(tmp_path, resume=True))
    assert CALLS == ["offset", 3] and again["reused"] == 4 and again["computed"] == 1
    # without resume everything is computed again
    CALLS.clear()
    run_tasks(tasks, store=RunStore(tmp_path))
    assert sorted(c for c in CALLS if c != "offset") == [0, 1, 2, 3, 4]
    with pytest.raises(FluoInputError, match="same task twice"):
        run_tasks(tasks + tasks[:1])


def _cli(argv, capsys):
    rc = main(argv)
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


@pytest.mark.parametrize("argv, field", [
    (["study", "D"], "study"),
    (["study", "A", "--workers", "0"], "--workers"),
    (["study", "A", "--workers", "nan"], "--workers"),
    (["study", "A", "--workers", "100000"], "--workers"),
    (["study", "A", "--threads", "-1"], "--threads"),
    (["study", "A", "--threads", "inf"], "--threads"),
    (["study", "A", "--scheduler", "tcp://localhost:99999"], "--scheduler"),
    (["study", "A", "--scheduler", "not an address"], "--scheduler"),
    (["study", "A", "--resume"], "--resume"),
    (["study", "A", "--grid", "lambdas=1,nan"], "lambdas"),
    (["study", "A", "--grid", "noise_pct=-1"], "noise_pct"),
    (["study", "A", "--grid", "colour=1"], "--grid"),
    (["study", "A", "--grid", "recon_mm=1e9"], "recon_mm"),
    (["study", "A", "--sweep", "lambda", "--values", "1,,2"], "--values"),
    (["study", "A", "--sweep", "mesh", "--values", "0.001"], "recon_mm"),
    (["study", "A", "--target", "6"], "--target"),
])
def test_bad_options_are_one_line_and_exit_2(argv, field, capsys):
    rc, out, err = _cli(argv, capsys)
    assert rc == 2 and out == "" and field in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("name, text, field", [
    ("missing.yaml", None, "not found"),
    ("bad.json", "{ not json", "not valid JSON"),
    ("bad.yaml", "a: [1, 2\nb: 3", "not valid YAML"),
    ("list.yaml", "- 1\n- 2\n", "mapping"),
    ("unknown.yaml", "study: A\ncolour: red\n", "colour"),
    ("nan.yaml", "study: B\nlambdas: [.nan]\n", "lambdas"),
    ("seed.json", '{"study": "A", "seeds": [-1]}', "seeds"),
    ("both.yaml", "study: A\ntargets: [[6, 3]]\n", "not both"),
    ("study.txt", "study: A", "study file"),
])
def test_bad_study_files_are_one_line_and_exit_2(tmp_path, name, text, field, capsys):
    path = tmp_path / name
    if text is not None:
        path.write_text(text)
    rc, out, err = _cli(["study", str(path), "--out", str(tmp_path / "o")], capsys)
    assert rc == 2 and out == "" and field in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o" / "table.csv").exists()


def test_study_file_grid_runs_and_writes_the_run_folder(tmp_path, capsys):
    f = tmp_path / "grid.yaml"
    f.write_text("targets: [[6, 3.5]]\nmethods: [HP]\nlambdas: [1, 10]\nseeds: [0, 1]\n")
    rc, out, err = _cli(["study", str(f), "--out", str(tmp_path / "o"), "--json"], capsys)
    assert rc == 0, err
    doc = json.loads(out)
    assert doc["tasks"] == 4 and doc["shared_inputs"] == 2 and doc["executor"] == "serial"
    assert [(r["seed"], r["lambda"]) for r in doc["rows"]] == [(0, 1.0), (0, 10.0), (1, 1.0),
                                                              (1, 10.0)]
    o = tmp_path / "o"
    assert (o / "table.csv").exists() and (o / "study.json").exists()
    assert len(list((o / "tasks").glob("*.json"))) == 4 == len(list((o / "tasks").glob("*.npz")))
    assert (o / "error_vs_time.png").exists() and (o / "run.json").exists()


def _fluo(*args, env=None, timeout=400):
    return subprocess.run([sys.executable, "-m", "fluoapp", *args], capture_output=True, text=True,
                          timeout=timeout, env=env)


@pytest.mark.slow
def test_a_killed_run_resumes_without_redoing_finished_tasks(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "fluoapp", "study", "B", "--out", str(out),
                             "--json"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    try:
        deadline = time.monotonic() + 300
        while len(list((out / "tasks").glob("[!.]*.json"))) < 4:
            assert proc.poll() is None, "the run ended before it could be killed"
            assert time.monotonic() < deadline
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(30)
    finally:
        stop_process(proc)
    done = {p.stem: json.loads(p.read_text()) for p in (out / "tasks").glob("[!.]*.json")}
    assert 4 <= len(done) < 15 and all(r["pid"] == proc.pid for r in done.values())

    r = _fluo("study", "B", "--out", str(out), "--resume", "--json")
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    # a record of a task that failed is computed again, not reused (store.finished);
    # "[!.]*.json": a record the kill caught mid-write is a hidden temporary file
    # (.ID.json.tmp-PID-NS.json), not a record
    ok = [k for k, rec in done.items() if rec["status"] == "ok"]
    assert doc["reused"] == len(ok) and doc["computed"] == 15 - len(ok), {
        k: (rec["status"], rec.get("error")) for k, rec in done.items()}
    # the finished records were not rewritten; the rest came from the second process
    after = {p.stem: json.loads(p.read_text()) for p in (out / "tasks").glob("[!.]*.json")}
    assert all(after[k] == done[k] for k in ok)
    assert {v["pid"] for k, v in after.items() if k not in done} != {proc.pid}
    # and the table is the uninterrupted run's
    whole = tmp_path / "whole"
    assert _fluo("study", "B", "--out", str(whole), "--json").returncode == 0
    ca, ra = read_table(out / "table.csv")
    cb, rb = read_table(whole / "table.csv")
    keep = stable_columns(ca)
    assert ca == cb and [[x[c] for c in keep] for x in ra] == [[x[c] for c in keep] for x in rb]


@pytest.mark.slow
def test_a_sweep_on_a_dask_scheduler_and_workers_started_as_processes(tmp_path):
    """`dask scheduler` and `dask worker` (2 processes) on 127.0.0.1; the sweep goes
    there by --scheduler and by $FLUO_SCHEDULER, and gives the serial run's table."""
    sweep = ["study", "A", "--sweep", "lambda", "--values", "0.1,10", "--json"]
    with DaskProcesses(tmp_path, nworkers=2) as dask:
        address = dask.address
        r = _fluo(*sweep, "--scheduler", address, "--out", str(tmp_path / "dask"))
        assert r.returncode == 0, r.stderr
        doc = json.loads(r.stdout)
        assert doc["executor"] == "dask (scheduler)" and doc["workers"] == 2
        assert doc["scheduler"] == address and "dask: 2 workers" in r.stderr
        assert doc["tasks"] == 6 and doc["failures"] == 0 and doc["shared_inputs"] == 2
        ran_on = {row["worker"] for row in doc["rows"]}
        assert len(ran_on) == 2 and all(w.split(":")[1] != "" for w in ran_on)
        env = dict(os.environ, FLUO_SCHEDULER=address)
        r2 = _fluo(*sweep, "--out", str(tmp_path / "env"), env=env)
        assert r2.returncode == 0 and json.loads(r2.stdout)["executor"] == "dask (scheduler)"
    serial = _fluo(*sweep, "--out", str(tmp_path / "serial"))
    assert serial.returncode == 0, serial.stderr
    tables = [read_table(tmp_path / d / "table.csv") for d in ("serial", "dask", "env")]
    keep = stable_columns(tables[0][0])
    rows = [[[x[c] for c in keep] for x in t[1]] for t in tables]
    assert rows[0] == rows[1] == rows[2]
    assert dask.scheduler.poll() is not None and dask.workers.poll() is not None


def _with_arrays(params):
    rng = np.random.default_rng(params["seed"])
    return {"n": 3, "arrays": {"field": rng.normal(size=(40, 3)),
                               "mask": rng.random(7) > 0.5,
                               "index": np.arange(5, dtype="int32")}}


def test_task_arrays_round_trip_in_an_npz_numpy_reads(tmp_path):
    """A task's arrays are stored as a deflated .npz (a lighter level than numpy's own
    savez_compressed) and come back equal, dtypes kept, through the store and np.load."""
    store = RunStore(tmp_path)
    out = run_tasks([Task(_with_arrays, {"seed": 4})], store=store)
    rec = out["records"][0]
    got = store.arrays(rec)
    want = _with_arrays({"seed": 4})["arrays"]
    assert set(got) == set(want)
    for k, v in want.items():
        assert got[k].dtype == v.dtype
        np.testing.assert_array_equal(got[k], v)
    with np.load(tmp_path / "tasks" / rec["arrays"]) as z:
        np.testing.assert_array_equal(z["field"], want["field"])
