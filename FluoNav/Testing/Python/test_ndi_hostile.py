"""An NDI device on a pseudo-terminal that answers garbage: one clear device
error and exit 1, never a traceback and never an empty exit 0 (issue #21)."""

import pytest

from FluoNavLib.devices.ndi_client import NDIClient, parse_handle
from FluoNavLib.devices.ndi_protocol import NDIProtocolError, with_crc
from FluoNavLib.devices.ndi_simulator import NDISimulator


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
            # protocol error once the device does not recover
            with pytest.raises(NDIProtocolError):
                client.track(30.0)
            assert client.stats.frames == 0
            assert client.stats.malformed + client.stats.timeouts >= client.max_failures
    took = time.monotonic() - t0
    grew_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    assert took < 20.0 and grew_mb < 100
    assert MAX_REPLY_BYTES <= 2**20
