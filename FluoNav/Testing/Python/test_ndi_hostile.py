"""An NDI device on a pseudo-terminal that answers garbage: one clear device
error and exit 1, never a traceback and never an empty exit 0 (issue #21); and
one that misbehaves (issue #34): CRC storms are counts, not a line each; a
chaotic frame counter is a device error, not billions of missing frames; a
device that answers twice is detected, resynchronised or refused, and never
read one reply behind."""

import json

import numpy as np
import pytest

from fluoguide.errors import FluoDeviceError
from FluoNavLib.devices.ndi_client import NDIClient, parse_handle
from FluoNavLib.devices.ndi_protocol import NDIProtocolError, with_crc
from FluoNavLib.devices.ndi_simulator import Faults, NDISimulator


class GarbageDevice(NDISimulator):
    """The simulator, except that chosen commands get a well-framed garbage reply."""

    def __init__(self, garbage, **kw):
        super().__init__(**kw)
        self.garbage = garbage  # command name -> reply body

    def _handle(self, line):
        name = line.strip().partition(" ")[0].split(":")[0].upper()
        if name in self.garbage:
            return with_crc(self.garbage[name])
        return super()._handle(line)


@pytest.mark.parametrize("body", ["ZZ", "", "0", "01 ", "G1"])
def test_parse_handle_refuses_garbage(body):
    with pytest.raises(NDIProtocolError, match="port handle"):
        parse_handle(body)


def test_garbage_phrq_reply_is_a_protocol_error_not_a_traceback():
    with GarbageDevice({"PHRQ": "XYZZY"}) as dev:
        with NDIClient(dev.port) as client:
            with pytest.raises(NDIProtocolError, match="not a port handle"):
                client.initialize([b"rom" * 30])


def _run_track_cli(dev_garbage, capsys, monkeypatch):
    from fluoapp.cli import main
    from FluoNavLib.devices import ndi_simulator

    class Hostile(GarbageDevice):
        def __init__(self, **kw):
            super().__init__(dev_garbage, **kw)

    # `fluo track --sim` starts the simulator class; here it starts the hostile one
    monkeypatch.setattr(ndi_simulator, "NDISimulator", Hostile)
    rc = main(["track", "--sim", "--seconds", "1.5", "--json"])
    return rc, capsys.readouterr()


def test_cli_garbage_tracking_replies_end_with_a_device_error(capsys, monkeypatch):
    rc, out = _run_track_cli({"TX": "this is not a TX reply at all"}, capsys, monkeypatch)
    lines = out.err.strip().splitlines()
    assert rc == 1 and out.out == ""
    assert len(lines) == 1 and "delivered no frames" in lines[0] and "malformed" in lines[0]


def test_cli_garbage_phrq_is_one_line_exit_1(capsys, monkeypatch):
    rc, out = _run_track_cli({"PHRQ": "??"}, capsys, monkeypatch)
    lines = out.err.strip().splitlines()
    assert rc == 1 and len(lines) == 1 and "port handle" in lines[0]


@pytest.mark.parametrize("value", ["nan", "inf", "-1", "1e9"])
def test_cli_track_seconds_must_be_a_finite_duration(value, capsys):
    from fluoapp.cli import main

    assert main(["track", "--sim", "--seconds", value, "--json"]) == 2
    assert "--seconds" in capsys.readouterr().err


class StreamingDevice(NDISimulator):
    """Answers TX with megabytes that never end in a CR (a device in a loop)."""

    def _handle(self, line):
        if line.strip().upper().startswith("TX"):
            return b"0" * (8 * 2**20)
        return super()._handle(line)


@pytest.mark.slow      # megabytes through a pseudo-terminal: 10-30 s with CI's load
def test_a_reply_without_end_is_bounded_in_time_and_memory():
    import resource
    import time

    from FluoNavLib.devices.ndi_client import MAX_REPLY_BYTES

    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.monotonic()
    with StreamingDevice() as dev:
        with NDIClient(dev.port) as client:
            client.initialize([b"rom" * 30])
            client.start()
            # replies cut at the size limit or the time-out: counted, then one
            # protocol error once the device does not recover, or the device refused
            # when it keeps sending with no request (the stream cannot be resynchronised)
            # tracking for up to 300 s: the error must end it long before (quiet, 3 s;
            # under CI's load the cut replies took 30 s to count, once 86 s and once
            # over 150 s beside the heavy tests, the pseudo-terminal's 8 MiB a request
            # starved of CPU)
            with pytest.raises((NDIProtocolError, FluoDeviceError)) as e:
                client.track(300.0)
            assert client.stats.frames == 0
            if isinstance(e.value, FluoDeviceError):
                assert "keeps sending without a request" in str(e.value)
            else:
                assert client.stats.malformed + client.stats.timeouts >= client.max_failures
    took = time.monotonic() - t0
    grew_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    # ended by the error, never by tracking's own 300 s (CI's load once stretched the
    # counting to 123 s and once past 150 s: a bound below the limit measured the
    # machine, not the client)
    assert took < 300.0 and grew_mb < 100
    assert MAX_REPLY_BYTES <= 2**20


# ------------------------------------------------ devices that misbehave (issue #34)
def _track_sim(fluo, kinds, seconds="2.5"):
    """``fluo track --sim --inject-faults KINDS --json`` as a process of its own (its
    stderr is the process's: log lines a user would see are seen here)."""
    return fluo("track", "--sim", "--seconds", seconds, "--inject-faults", kinds, "--json",
                timeout=60)


def test_cli_a_crc_storm_is_a_count_not_a_line_per_fault(fluo):
    """Every reply's CRC corrupted for 0.3 s in every second: each storm costs a
    recovery, and each recovery printed a line (226-329 lines in a longer run);
    now stderr stays empty and the JSON counts them."""
    r = _track_sim(fluo, "crc-storm", "3.2")
    assert r.returncode == 0 and r.stderr == "", r.stderr[-2000:]
    doc = json.loads(r.stdout)
    assert doc["recovered"] >= 2 and doc["crc_errors"] >= 2 * 3, doc
    assert doc["crc_errors"] == doc["simulator"]["crc_corrupted"]   # every one counted
    assert doc["lost_unreported"] == 0 and doc["frames"] > 20


def test_cli_a_storm_that_outlasts_recovery_is_one_line_naming_the_port(capsys, monkeypatch):
    """A CRC storm from 0.2 s to the end: the recovery attempts fail, and the run ends
    with one line naming the port and the counts (it was "fluo: error: CRC mismatch")."""
    rc, out = _run_with_faults(Faults(crc_storms=((0.2, 3600.0),)), capsys, monkeypatch)
    lines = out.err.strip().splitlines()
    assert rc == 1 and out.out == "" and len(lines) == 1, out.err
    assert lines[0].startswith("fluo: error: tracker on /dev/") and "did not recover" in lines[0]
    assert "CRC errors" in lines[0]


def test_cli_a_chaotic_frame_counter_is_a_device_error_not_billions_missing(fluo):
    """TX frame numbers at random in [0, 2^32): was `missing: 257,698,030,200` and exit 0."""
    r = _track_sim(fluo, "chaotic-frames")
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 1 and r.stdout == "" and len(lines) == 1, (r.stdout, r.stderr)
    assert lines[0].startswith("fluo: error: tracker on /dev/")
    assert "frame counter jumped implausibly" in lines[0]


def test_cli_a_device_that_answers_twice_is_refused(fluo):
    """Every TX reply sent twice (the copy 2 ms later): the replies can no longer be
    matched to requests; the device is refused with one line."""
    r = _track_sim(fluo, "duplicate-replies")
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 1 and r.stdout == "" and len(lines) == 1, (r.stdout, r.stderr)
    assert "answers requests more than once" in lines[0] and "/dev/" in lines[0]


def _run_with_faults(faults, capsys, monkeypatch):
    from fluoapp.cli import main
    from FluoNavLib.devices import ndi_simulator

    class Faulty(NDISimulator):
        def __init__(self, **kw):
            kw["faults"] = faults
            super().__init__(**kw)

    monkeypatch.setattr(ndi_simulator, "NDISimulator", Faulty)
    rc = main(["track", "--sim", "--seconds", "2", "--json"])
    return rc, capsys.readouterr()


class LoggingDevice(NDISimulator):
    """The simulator, keeping (time handled, reply body) of every TX it answers."""

    def __init__(self, **kw):
        super().__init__(**kw)
        self.tx_log = []

    def _tx(self, now):
        body = super()._tx(now)
        self.tx_log.append((now, body))
        return body


def _stale(delivered, made, dev):
    """The frames of the poses ``delivered`` ((poll time, reply)) that are older than the
    frame the device ``dev`` was on when that poll began, or that it never ``made``
    ((time, reply)): answers to earlier requests. (A reply made before the poll, in the
    frame the device is still on, is as current as any answer can be: a device that
    counts 60 frames/s answers with the last frame it sampled.)"""
    stale = []
    for t_poll, reply in delivered:
        pose = reply.tools[1]
        made_it = any(r.tools[1].frame == pose.frame and np.array_equal(
            r.tools[1].translation_mm, pose.translation_mm) for _, r in made)
        if not made_it or pose.frame < dev._frame(t_poll):
            stale.append(pose.frame)
    return stale


@pytest.mark.parametrize("delay_s", [0.0, 0.002, 0.012],
                         ids=["copy at once", "copy 2 ms later", "copy after the next request"])
def test_duplicate_replies_are_detected_and_no_stale_pose_is_delivered(delay_s):
    """Every TX answered twice, the copy at once, 2 ms later, or 12 ms later (after the
    client's next request, at 120 polls/s): a client that reads one reply behind takes
    the answer to an earlier request for the answer to this one. Every reply delivered
    must be no older than the frame the device was on when its poll began; the device
    is refused."""
    import time

    from FluoNavLib.devices.ndi_protocol import parse_tx

    faults = Faults(duplicate_replies=("TX",), duplicate_delay_s=delay_s)
    delivered = []
    with LoggingDevice(faults=faults) as dev:
        with NDIClient(dev.port) as client:
            client.initialize([b"rom" * 30])
            client.start()
            t0 = time.monotonic()
            refused = None
            try:
                client.track(3.0, on_frame=lambda reply, t: delivered.append((t, reply)))
            except FluoDeviceError as exc:
                refused = str(exc)
            took = time.monotonic() - t0
        made = [(t, parse_tx(body)) for t, body in dev.tx_log]
    stale = _stale(delivered, made, dev)
    # (read one reply behind, 86 of 90 poses delivered were stale with the copy 12 ms late)
    assert not stale, f"{len(stale)} of {len(delivered)} poses delivered were stale"
    assert refused and "answers requests more than once" in refused, refused
    assert took < 2.0 and client.stats.duplicate_replies >= 3


class CopyWithTheNextRequest(LoggingDevice):
    """Answers each TX with a copy of its last TX reply first, then, 5 ms later, with
    the new one: the copy comes long after any drain of the line has ended."""

    def __init__(self, **kw):
        super().__init__(**kw)
        self.last = None

    def _send(self, reply, name=""):
        import time

        if name == "TX" and self.last is not None:
            super()._send(self.last, name)
            time.sleep(0.005)
        super()._send(reply, name)
        if name == "TX":
            self.last = reply


def test_a_late_copy_of_a_reply_drained_unused_is_not_delivered():
    """The reply to request k is found before request k+1 (unrequested: drained); its copy
    then answers request k+1 with a frame newer than any delivered. The drained reply's
    frame is remembered and the copy is not delivered; the device is refused."""
    from FluoNavLib.devices.ndi_protocol import parse_tx

    delivered = []
    with CopyWithTheNextRequest() as dev:
        with NDIClient(dev.port) as client:
            client.initialize([b"rom" * 30])
            client.start()
            with pytest.raises(FluoDeviceError, match="answers requests more than once"):
                client.track(3.0, on_frame=lambda reply, t: delivered.append((t, reply)))
        made = [(t, parse_tx(body)) for t, body in dev.tx_log]
    # (the old client delivered frame 3 or 4 in every unloaded run, so did it under load
    # 3 runs in 4; whether the copy or the drain comes first then depends on the load)
    assert not _stale(delivered, made, dev)


class OneDuplicate(NDISimulator):
    """Answers the 20th TX twice (a glitch), every other request once."""

    def __init__(self, **kw):
        super().__init__(**kw)
        self.tx = 0

    def _send(self, reply, name=""):
        super()._send(reply, name)
        if name == "TX":
            self.tx += 1
            if self.tx == 20:
                super()._send(reply, name)


def _track_for(device_class, seconds):
    """Set up a client on a ``device_class`` simulator, track for ``seconds``; the stats
    after the client closed (its open segment closed too)."""
    with device_class() as dev:
        with NDIClient(dev.port) as client:
            client.initialize([b"rom" * 30])
            client.start()
            client.track(seconds)
    return client.stats


def test_one_duplicate_reply_is_resynchronised_and_tracking_goes_on():
    stats = _track_for(OneDuplicate, 1.0)
    assert stats.duplicate_replies == 1 and stats.frames > 20
    assert stats.lost_unreported() == 0 and stats.counter_jumps == 0


class CounterJump(NDISimulator):
    """The frame counter jumps by 2^31 once, after the 30th TX (then counts on)."""

    def __init__(self, **kw):
        super().__init__(**kw)
        self.tx = 0

    def _frame(self, now):
        f = super()._frame(now)
        return f + 2**31 if self.tx > 30 else f

    def _tx(self, now):
        self.tx += 1
        return super()._tx(now)


def test_one_counter_jump_is_counted_not_two_billion_missing_frames():
    stats = _track_for(CounterJump, 1.0)
    assert stats.counter_jumps == 1 and stats.missing < 100
    # two segments (closed with the client): before the jump and after it
    assert stats.lost_unreported() == 0 and len(stats.segments) == 2
