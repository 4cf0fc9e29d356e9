"""Live devices: OpenIGTLink message loss vs send rate (pyigtl keeps only the
latest message per device), simulated NDI tracking (rate and frame
accounting, clean and with faults), and the live loop's latency.

All traffic is on 127.0.0.1 (an ephemeral port) or a pseudo-terminal.

    python -m benchmarks devices [-- --seconds 2 --repeats 3 --poll-hz 100]
"""

from __future__ import annotations

import argparse
import socket
import threading
import time

import numpy as np


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def igtl_loss(rate_hz, seconds, poll_hz):
    """Send transforms with a ``seq`` at ``rate_hz``; the receiver polls at
    ``poll_hz``.  Returns sent, received, counted lost, unaccounted."""
    import pyigtl

    from fluoguide import mrml_io
    from FluoNavLib.devices.igtl_client import IGTLReceiver

    port = _free_port()
    server = pyigtl.OpenIGTLinkServer(port=port, local_server=True)
    rx = None
    try:
        rx = IGTLReceiver(mrml_io.new_scene(), "127.0.0.1", port).connect(timeout_s=10)
        t_end = time.monotonic() + 10
        while not server.is_connected() and time.monotonic() < t_end:
            time.sleep(0.01)
        stop = threading.Event()

        def poller():
            while not stop.is_set():
                rx.poll()
                time.sleep(1.0 / poll_hz)

        th = threading.Thread(target=poller, daemon=True)
        th.start()
        n = int(rate_hz * seconds)
        t0 = time.monotonic()
        for k in range(n):
            m = np.eye(4)
            m[:3, 3] = (k, 0.0, 0.0)
            msg = pyigtl.TransformMessage(m, device_name="CameraToTracker",
                                          timestamp=t0 + k / rate_hz)
            msg.header_version = 2           # metadata (the seq) needs header v2
            msg.metadata = {"seq": str(k)}
            # queued like a tracking server: the server thread sends in bursts
            server.send_message(msg, wait=False)
            dt = t0 + (k + 1) / rate_hz - time.monotonic()
            if dt > 0:
                time.sleep(dt)
        send_rate = n / (time.monotonic() - t0)
        time.sleep(0.3)           # the last message arrives and is polled
        stop.set()
        th.join(2.0)
        rx.poll()
        got = rx.received.get("CameraToTracker", 0)
        lost = rx.lost.get("CameraToTracker", 0)
        # messages replaced before the first poll: seen from the first seq (sender counts from 0)
        first = rx.first_seq.get("CameraToTracker", 0)
        return {"sent": n, "send_rate_hz": send_rate, "received": got, "lost": lost,
                "lost_before_first": max(first, 0), "unaccounted": n - got - lost - max(first, 0)}
    finally:
        if rx is not None:
            rx.close()
        server.stop()


def ndi_track(seconds, faults):
    from FluoNavLib.devices.ndi_client import NDIClient
    from FluoNavLib.devices.ndi_simulator import Faults, NDISimulator

    with NDISimulator(faults=Faults.typical() if faults else Faults(), seed=1) as sim:
        with NDIClient(sim.port) as client:
            client.initialize([b"rom" * 30] * 2)
            client.start()
            t0 = time.monotonic()
            s = client.track(seconds)
            dt = time.monotonic() - t0
            client.stop()
    return {"frames": s.frames, "rate_hz": s.frames / dt, "missing": s.missing,
            "crc_errors": s.crc_errors, "recovered": s.recovered,
            "lost_unreported": s.lost_unreported()}


def live_latency(seconds, fps):
    from FluoNavLib.devices.frame_sources import SyntheticSource
    from FluoNavLib.devices.live_loop import LiveLoop
    from FluoNavLib.devices.ndi_client import NDIClient
    from FluoNavLib.devices.ndi_simulator import NDISimulator

    with NDISimulator(seed=2) as sim:
        with NDIClient(sim.port) as client:
            client.initialize([b"rom" * 30])
            client.start()
            rep = LiveLoop(SyntheticSource(fps=fps, width=348, height=260), lambda *a: None,
                           tracker=client).run(seconds=seconds)
            client.stop()
    return rep


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m benchmarks devices")
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--poll-hz", type=float, default=100.0)
    args = ap.parse_args(argv)
    print(f"OpenIGTLink (pyigtl 127.0.0.1) transform loss vs send rate, receiver polling at "
          f"{args.poll_hz:g} Hz, {args.seconds:g} s per rate, median of {args.repeats}:")
    print("  rate [Hz] | achieved [Hz] | received % | lost (counted) % | unaccounted")
    for rate in (30, 60, 120, 250, 500, 1000):
        runs = [igtl_loss(rate, args.seconds, args.poll_hz) for _ in range(args.repeats)]
        med = {k: float(np.median([r[k] for r in runs])) for k in runs[0]}
        got, lost = 100 * med["received"] / med["sent"], 100 * med["lost"] / med["sent"]
        print(f"  {rate:9d} | {med['send_rate_hz']:13.1f} | {got:10.1f} | {lost:16.1f} | "
              f"{max(r['unaccounted'] for r in runs):d}")
    for faults in (False, True):
        r = ndi_track(5.0, faults)
        print(f"NDI simulator 5 s{' with faults' if faults else ''}: {r['frames']} frames, "
              f"{r['rate_hz']:.1f} Hz, missing {r['missing']}, CRC errors {r['crc_errors']}, "
              f"recovered {r['recovered']}, lost_unreported {r['lost_unreported']}")
    rep = live_latency(5.0, 30.0)
    lat = rep["latency_ms"]
    print(f"live loop (sim tracker + 30 fps synthetic camera, 5 s): {rep['delivered']} frames, "
          f"dropped {rep['dropped_slow']}+{rep['dropped_upstream']}, pose invalid "
          f"{rep['pose_invalid']}, latency median {lat['median']:.1f} ms, p95 {lat['p95']:.1f} ms, "
          f"lost_unreported {rep['lost_unreported']}")
    return 0
