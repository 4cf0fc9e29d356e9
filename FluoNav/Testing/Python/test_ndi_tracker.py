"""NDI serial protocol: CRC, parsers (fuzzed), and the client against the
protocol-faithful simulator on a pseudo-terminal, with injected faults."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from FluoNavLib.devices.ndi_client import NDIClient
from FluoNavLib.devices.ndi_protocol import (
    NDIProtocolError,
    check_reply,
    crc16,
    format_phsr,
    format_tx,
    parse_phsr,
    parse_tx,
    with_crc,
)
from FluoNavLib.devices.ndi_simulator import Faults, NDISimulator


def test_crc_matches_the_device_replies():
    assert with_crc("OKAY") == b"OKAYA896\r"
    assert with_crc("RESET") == b"RESETBE6F\r"
    assert crc16(b"") == 0


def test_tx_round_trip_and_states():
    q = np.array([0.5, 0.5, -0.5, 0.5])
    body = format_tx([(1, "OK", q, (12.34, -1500.0, 7.5), 0.1234, 0x31),
                      (2, "MISSING", None, None, None, 0x71),
                      (3, "DISABLED", None, None, None, 0)], frame=0x1234)
    reply = parse_tx(check_reply(with_crc(body)))
    t1 = reply.tools[1]
    assert t1.state == "OK" and t1.frame == 0x1234
    np.testing.assert_allclose(t1.quaternion, q, atol=1e-4)
    np.testing.assert_allclose(t1.translation_mm, (12.34, -1500.0, 7.5), atol=1e-9)
    m = t1.matrix()
    np.testing.assert_allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-6)
    assert reply.tools[2].state == "MISSING" and reply.tools[2].out_of_volume
    assert reply.tools[3].state == "DISABLED" and reply.tools[3].matrix() is None
    assert parse_phsr(format_phsr({1: 0x31, 10: 0x01})) == {1: 0x31, 10: 0x01}


def test_bad_replies_are_named():
    with pytest.raises(NDIProtocolError) as e:
        check_reply(b"OKAYA897\r")
    assert e.value.kind == "crc"
    with pytest.raises(NDIProtocolError) as e:
        check_reply(b"OKAYA89")
    assert e.value.kind == "truncated"
    with pytest.raises(NDIProtocolError, match="port handle") as e:
        check_reply(with_crc("ERROR08"))
    assert e.value.kind == "error"
    body = format_tx([(1, "OK", (1, 0, 0, 0), (0, 0, 0), 0.1, 0x31)], 5)
    with pytest.raises(NDIProtocolError):
        parse_tx(body[:-9] + "\n0000")           # truncated record
    with pytest.raises(NDIProtocolError, match="announces"):
        parse_tx("02" + body[2:])                 # count says 2, one record
    with pytest.raises(NDIProtocolError, match="quaternion norm"):
        parse_tx(format_tx([(1, "OK", (0.1, 0, 0, 0), (0, 0, 0), 0.1, 0x31)], 5))


@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=200))
def test_fuzzed_raw_replies_never_crash(raw):
    try:
        body = check_reply(raw)
        parse_tx(body)
    except NDIProtocolError:
        pass


@settings(max_examples=300, deadline=None)
@given(st.text(alphabet="0123456789ABCDEF+-MISNGDABLE\n", max_size=160))
def test_fuzzed_tx_bodies_never_crash(body):
    try:
        r = parse_tx(body)
        for p in r.tools.values():
            if p.state == "OK":
                assert np.all(np.isfinite(p.matrix()))
    except NDIProtocolError:
        pass


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.integers(1, 255), st.floats(-1e5, 1e5), st.floats(-1e5, 1e5),
                          st.floats(-1e5, 1e5)), min_size=1, max_size=4, unique_by=lambda t: t[0]),
       st.integers(0, 2 ** 32 - 1))
def test_out_of_range_numbers_saturate_not_crash(tools, frame):
    recs = [(h, "OK", (1.0, 0.0, 0.0, 0.0), (x, y, z), 0.1, 0x31) for h, x, y, z in tools]
    r = parse_tx(check_reply(with_crc(format_tx(recs, frame))))
    for h, x, y, z in tools:
        t = r.tools[h].translation_mm
        assert np.all(np.abs(t) <= 10000.0) and r.tools[h].frame == frame


def _run(faults, seconds, seed=0):
    with NDISimulator(faults=faults, seed=seed) as sim:
        with NDIClient(sim.port) as client:
            handles = client.initialize([b"tool-a" * 10, b"tool-b" * 10])
            client.start()
            poses = []
            stats = client.track(seconds, on_frame=lambda r, t: poses.append(r))
            client.stop()
        return handles, stats, poses, sim.counters


def test_clean_tracking_at_60_hz_with_every_frame_accounted_for():
    handles, stats, poses, sim = _run(Faults(), 2.0)
    assert handles == [1, 2]
    assert stats.frames >= 100                    # ~60 Hz for 2 s on a loaded machine
    assert stats.lost_unreported() == 0
    assert stats.crc_errors == stats.timeouts == stats.recovered == 0
    frames = [max(p.frame for p in r.tools.values()) for r in poses]
    assert frames == sorted(set(frames))          # each device frame delivered once
    ok = [r.tools[1] for r in poses if r.tools[1].state == "OK"]
    assert ok and all(np.isfinite(p.matrix()).all() for p in ok)


def test_injected_faults_are_detected_counted_and_recovered():
    faults = Faults(crc_error_rate=0.03, slow_reply_rate=0.02, dropout_rate_per_s=2.0,
                    disconnect_at_s=(1.0,), disconnect_s=0.4)
    _, stats, poses, sim = _run(faults, 3.0, seed=5)
    assert sim["crc_corrupted"] > 0 and stats.crc_errors == sim["crc_corrupted"]
    assert sim["disconnects"] == 1 and stats.recovered == 1
    assert stats.tool_missing > 0                 # occlusion bursts reported per frame
    assert stats.lost_unreported() == 0
    assert len(stats.segments) == 2               # before and after the device reset
    assert stats.frames > 60
