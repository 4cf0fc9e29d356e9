"""The web app against hostile clients and hostile paths (issue #21).

A scripted websocket client on 127.0.0.1 speaks wslink to a real ``fluo app``:
a foreign Origin is refused before any message, a wrong secret gets no call
through, a second session is refused while one is open, and an authenticated
client that types a path outside the workspace writes nothing there. The
workspace rules themselves are checked without a server.
"""

import asyncio
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from fluoguide.errors import FluoInputError
from fluoapp.webapp.security import BUNDLED_PREFIX, Workspace

ROOT = Path(__file__).resolve().parents[2]


# ----------------------------------------------------------------- workspace rules
def test_workspace_resolves_inside_and_refuses_the_rest(tmp_path):
    ws = Workspace(tmp_path / "ws")
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "secret.png").write_bytes(b"x")
    (ws.root / "cal").mkdir()
    (ws.root / "cal" / "a.png").write_bytes(b"x")
    (ws.root / "cal" / "link.png").symlink_to(outside / "secret.png")
    (ws.root / "escape").symlink_to(outside)

    assert ws.path("cal/a.png", "images") == ws.root / "cal" / "a.png"
    assert ws.path(str(ws.root / "cal" / "a.png"), "images") == ws.root / "cal" / "a.png"
    for bad in ("../outside/secret.png", str(outside / "secret.png"), "escape/secret.png",
                "cal/link.png", "/etc/passwd", "", "a\x00b"):
        with pytest.raises(FluoInputError) as err:
            ws.path(bad, "scene file")
        assert str(outside) not in str(err.value) or bad.startswith(str(outside))
    with pytest.raises(FluoInputError, match="read-only"):
        ws.path(BUNDLED_PREFIX + "opencv_left/x.mrml", "scene file", writable=True)
    with pytest.raises(FluoInputError, match="inside the bundled data"):
        ws.path(BUNDLED_PREFIX + "../../../etc/passwd", "images")
    # globs: relative only, and links that lead outside are dropped
    assert [Path(f).name for f in ws.glob("cal/*.png", "images")] == ["a.png"]
    for bad in ("/etc/*", "../*", "../outside/*.png"):
        with pytest.raises(FluoInputError):
            ws.glob(bad, "images")
    assert ws.glob("escape/*", "images") == []
    assert len(ws.glob(BUNDLED_PREFIX + "opencv_left/left*.jpg", "images")) >= 3
    # what the user sees
    assert ws.shown(ws.root / "cal" / "a.png") == "cal/a.png"
    text = ws.scrub(f"{ws.root / 'cal' / 'stack.json'}: not valid JSON; see /etc/fluo/x.conf")
    assert text == "cal/stack.json: not valid JSON; see …/x.conf"
    assert ws.scrub("mua 0.01 1/mm, ratio 3/4, yield [1e-3 / mm]") == \
        "mua 0.01 1/mm, ratio 3/4, yield [1e-3 / mm]"
    # a name holding markup is shown as it is ("</b>" was cut to "<…/b>", issue #34)
    assert ws.scrub("Segment '<b>x</b>': 3 voxels") == "Segment '<b>x</b>': 3 voxels"
    with pytest.raises(FluoInputError, match="root"):
        Workspace("/")


# ----------------------------------------------------------------- a real server
def _start_app(workspace, tmp_path):
    log = open(tmp_path / "app.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "fluoapp", "app", "--port", "0",
                             "--workspace", str(workspace)], cwd=tmp_path, stdout=log,
                            stderr=subprocess.STDOUT, text=True)
    t0 = time.time()
    while time.time() - t0 < 180:
        text = (tmp_path / "app.log").read_text()
        m = re.search(r"FluoGuide app: (http://127\.0\.0\.1:(\d+)/)\?secret=(\S+)", text)
        if m:
            return proc, log, m.group(1), int(m.group(2)), m.group(3)
        if proc.poll() is not None:
            break
        time.sleep(0.3)
    proc.kill()
    log.close()
    pytest.fail(f"app did not start: {(tmp_path / 'app.log').read_text()[-2000:]}")


class _Client:
    """A minimal wslink client (msgpack in chunks over a binary websocket)."""

    def __init__(self, ws):
        from wslink.chunking import UnChunker

        self.ws = ws
        self.unchunker = UnChunker()
        self.unchunker.set_max_message_size(2**30)
        self.n = 0
        self.state = {}          # what the server published (trame.state.topic)

    async def call(self, method, *args, system=False):
        import aiohttp
        import msgpack
        from wslink.chunking import generate_chunks

        self.n += 1
        rid = f"{'system' if system else 'rpc'}:c0:{self.n}"
        msg = msgpack.packb({"wslink": "1.0", "id": rid, "method": method, "args": list(args),
                             "kwargs": {}})
        for chunk in generate_chunks(msg, 4096):
            await self.ws.send_bytes(chunk)
        while True:
            m = await self.ws.receive(timeout=60)
            if m.type != aiohttp.WSMsgType.BINARY:
                return {"closed": m.type}
            full = self.unchunker.process_chunk(m.data)
            if full is None:
                continue
            if str(full.get("id", "")).startswith("publish:trame.state.topic"):
                self.state.update(full.get("result") or {})
            if full.get("id") == rid:
                return full


async def _attack(url, port, secret, workspace, outside):
    import aiohttp

    origin = f"http://127.0.0.1:{port}"
    ws_url = f"ws://127.0.0.1:{port}/ws"
    report = {}
    async with aiohttp.ClientSession() as http:
        # a page of another site (or a DNS-rebinding one) cannot even open the socket
        with pytest.raises(aiohttp.WSServerHandshakeError) as err:
            await http.ws_connect(ws_url, headers={"Origin": "http://evil.example"})
        report["foreign_origin_status"] = err.value.status
        with pytest.raises(aiohttp.WSServerHandshakeError):
            await http.ws_connect(ws_url, headers={"Origin": f"http://evil.example:{port}"})
        # the right origin without the secret: every call refused
        async with http.ws_connect(ws_url, headers={"Origin": origin}) as ws:
            c = _Client(ws)
            report["public_secret"] = await c.call("wslink.hello", {"secret": "wslink-secret"},
                                                   system=True)
            report["no_secret"] = await c.call("wslink.hello", {}, system=True)
            report["unauthenticated_call"] = await c.call("trame.state.update",
                                                          [{"key": "calib_save_path",
                                                            "value": str(outside / "x.mrml")}])
        # the owner: a script with the secret (no Origin, as non-browser clients send none)
        owner = await http.ws_connect(ws_url)
        c = _Client(owner)
        report["owner_hello"] = await c.call("wslink.hello", {"secret": secret}, system=True)
        state = await c.call("trame.state.get")
        report["owner_state_keys"] = len(state.get("result", {}).get("state", {}))
        # while the owner is connected, a second session is refused, page and socket
        async with http.get(url + "index.html") as r:
            report["second_page"] = (r.status, await r.text())
        async with http.ws_connect(ws_url, headers={"Origin": origin}) as ws2:
            report["second_hello"] = await _Client(ws2).call("wslink.hello", {"secret": secret},
                                                             system=True)
        # an authenticated user typing a path outside the workspace writes nothing there
        # the Save button's trigger, as the page's template names it
        templates = [v for v in state["result"]["state"].values()
                     if isinstance(v, str) and 'id="calib-save"' in v]
        m = re.search(r'id="calib-save"[^>]*trigger\(\'(\w+)\'', templates[0]) if templates else None
        report["save_trigger_found"] = m is not None
        if m:
            # the path set in the state, or sent with the click as the page does
            # (app.submit): refused either way
            for target, by_click in ((str(outside / "evil.mrml"), False), ("../evil.mrml", False),
                                     ("../evil.mrml", True)):
                if by_click:
                    kwargs = {"fluo_form": {"calib_save_path": target}}
                else:
                    kwargs = {}
                    await c.call("trame.state.update", [{"key": "calib_save_path",
                                                         "value": target}])
                c.state.pop("fluo_message", None)
                await c.call("trame.trigger", m.group(1), [], kwargs)
                # the server publishes its state after the call returns: on a busy
                # machine the message can come a few pushes later
                for _ in range(40):
                    await c.call("trame.force.push", "fluo_message")
                    if c.state.get("fluo_message"):
                        break
                    await asyncio.sleep(0.25)
                report.setdefault("save_messages", []).append(c.state.get("fluo_message"))
            await c.call("trame.state.update", [{"key": "calib_save_path",
                                                 "value": "session/scene.mrml"}])
            await c.call("trame.trigger", m.group(1), [], {})
        await owner.close()
        await asyncio.sleep(1.0)
        # the owner gone, the next session is admitted
        async with http.ws_connect(ws_url, headers={"Origin": origin}) as ws3:
            report["next_hello"] = await _Client(ws3).call("wslink.hello", {"secret": secret},
                                                           system=True)
    return report


def test_hostile_clients_on_127_0_0_1(tmp_path):
    pytest.importorskip("aiohttp")
    workspace = tmp_path / "ws"
    outside = tmp_path / "outside"
    outside.mkdir()
    proc, log, url, port, secret = _start_app(workspace, tmp_path)
    try:
        report = asyncio.run(asyncio.wait_for(_attack(url, port, secret, workspace, outside), 240))
    finally:
        proc.terminate()
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()
    assert report["foreign_origin_status"] == 403
    for key in ("public_secret", "no_secret", "unauthenticated_call", "second_hello"):
        assert "error" in report[key] and "result" not in report[key], (key, report[key])
    assert report["owner_hello"].get("result", {}).get("clientID"), report["owner_hello"]
    assert report["owner_state_keys"] > 10
    status, page = report["second_page"]
    assert status == 409 and "another browser session" in page
    assert "result" in report["next_hello"], report["next_hello"]
    assert len(secret) >= 30 and secret != "wslink-secret"
    # nothing was written outside the workspace; the in-workspace save worked
    assert list(outside.iterdir()) == []
    assert not (tmp_path / "evil.mrml").exists()
    assert report["save_trigger_found"]
    for msg in report["save_messages"]:
        assert "inside the workspace" in str(msg), msg
    assert (workspace / "session" / "scene.mrml").is_file()
    log_text = (tmp_path / "app.log").read_text()
    assert "Traceback" not in log_text
