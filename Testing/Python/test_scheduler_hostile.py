"""A ``--scheduler`` that is not a well-behaved Dask scheduler (issue #34): one that
accepts and never answers, one that sends random bytes, one that closes at once,
and a real scheduler stopped (SIGSTOP) in the middle of a run. Each run ends
within its time limit ($FLUO_SCHEDULER_TIMEOUT, short here) with one line
``fluo: error: ...`` naming the address and what was awaited, exit code 1."""

import json
import os
import signal
import threading
import time

import pytest

import forkserver
from dask_processes import DaskProcesses
from hostile_peers import TCPPeer, close_at_once, random_bytes, silent

LIMIT_S = 2.0        # $FLUO_SCHEDULER_TIMEOUT in these tests [s]
ENV = dict(os.environ, FLUO_SCHEDULER_TIMEOUT=str(LIMIT_S))
STUDY = ("study", "A", "--target", "6,3.5")


def _one_line(r, alone=True):
    """The one error line of a failed run (``alone``: the only line on stderr; else
    the last, after the cluster's announcement and the progress bar)."""
    lines = r.stderr.strip().splitlines()
    errors = [ln for ln in lines if ln.startswith("fluo: ")]
    assert r.returncode == 1 and len(errors) == 1 and lines[-1] == errors[0], \
        (r.returncode, r.stderr)
    assert errors[0].startswith("fluo: error: ") and (len(lines) == 1 or not alone), r.stderr
    assert "Traceback" not in r.stderr and r.stdout.strip() == ""
    return errors[0]


@pytest.mark.parametrize("behaviour, needle", [
    (silent, "did not answer within 2 s (waited for the Dask handshake"),
    (random_bytes, "is not a Dask scheduler"),
    (close_at_once, "closed the connection"),
])
def test_a_hostile_scheduler_is_one_line_exit_1_in_bounded_time(behaviour, needle, tmp_path):
    """The peer accepts the connection, then: says nothing for ever / sends 4 kB of
    random bytes and holds / closes. ``fluo study A --scheduler`` ends in a few
    limits (it hung for ever, or gave a TimeoutError traceback after 68 s), and
    writes no run folder."""
    with TCPPeer(behaviour) as peer:
        t0 = time.monotonic()
        r = forkserver.fluo(*STUDY, "--scheduler", peer.address, "--out", tmp_path / "run",
                            env=ENV, timeout=60)
        took = time.monotonic() - t0
    line = _one_line(r)
    assert peer.address in line and needle in line, line
    assert took < 5 * LIMIT_S + 5, took
    assert not (tmp_path / "run").exists()


def test_a_port_nobody_listens_on_is_one_line_within_the_limit(tmp_path):
    """Refused connections are tried again (a scheduler may be starting) for the limit,
    not Dask's own 30 s, then one line."""
    import socket

    with socket.socket() as s:      # a port that was free a moment ago: nobody listens
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.monotonic()
    r = forkserver.fluo(*STUDY, "--scheduler", f"tcp://127.0.0.1:{port}", "--out",
                        tmp_path / "run", env=ENV, timeout=60)
    took = time.monotonic() - t0
    line = _one_line(r)
    assert f"nothing accepts connections at the Dask scheduler address tcp://127.0.0.1:{port}" \
        in line and took < 5 * LIMIT_S + 5, (line, took)


def test_a_scheduler_host_that_does_not_resolve_is_bad_input(tmp_path):
    r = forkserver.fluo(*STUDY, "--scheduler", "tcp://no-such-host.invalid:8786", "--out",
                        tmp_path / "run", env=ENV, timeout=60)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and "does not resolve" in lines[0], r.stderr


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf", "1e9", "soon"])
def test_a_bad_scheduler_time_limit_is_refused_before_any_work(value, tmp_path):
    r = forkserver.fluo(*STUDY, "--scheduler", "tcp://127.0.0.1:9", "--out", tmp_path / "run",
                        env=dict(os.environ, FLUO_SCHEDULER_TIMEOUT=value), timeout=60)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and "FLUO_SCHEDULER_TIMEOUT" in lines[0], \
        r.stderr
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGSTOP, signal.SIGKILL], ids=["stopped", "killed"])
def test_a_scheduler_that_stops_answering_mid_run_ends_the_run(sig, tmp_path):
    """A real scheduler and one worker; once the first task's record is written the
    scheduler is stopped (SIGSTOP: its connections stay open, nothing answers) or
    killed (its connections close). The run ends with one line naming the address
    and the tasks not done, in a few limits; the finished task stays in the run
    folder for --resume."""
    out = tmp_path / "run"
    box = {}
    with DaskProcesses(tmp_path, nworkers=1) as dask:
        address = dask.address
        # nine tasks (three lambdas): far more than finish before the stop
        argv = ("study", "A", "--sweep", "lambda", "--values", "0.1,1,10", "--scheduler",
                address, "--out", out, "--json")
        t = threading.Thread(target=lambda: box.update(
            r=forkserver.fluo(*argv, env=ENV, timeout=240)), daemon=True)
        t.start()
        deadline = time.monotonic() + 180
        while not (out / "tasks").is_dir() or not list((out / "tasks").glob("*.json")):
            assert t.is_alive() and time.monotonic() < deadline, box
            time.sleep(0.02)
        os.kill(dask.scheduler.pid, sig)
        stopped = time.monotonic()
        t.join(120)
        took = time.monotonic() - stopped
    r = box["r"]
    line = _one_line(r, alone=False)
    assert address in line and "during the run" in line and "tasks not done" in line, line
    assert ("a sign of life" if sig == signal.SIGSTOP else "lost the connection") in line, line
    assert took < 10 * LIMIT_S + 10, took
    # what finished is kept for --resume, and no task is recorded as failed for the
    # scheduler's fault (a killed scheduler's client gives its futures up as cancelled)
    records = [json.loads(f.read_text()) for f in (out / "tasks").glob("*.json")]
    assert records and all(rec["status"] == "ok" for rec in records), records
