"""End-to-end test of the browser viewer in headless Chromium (Debian's ``chromium`` package).

Drives the page over the DevTools protocol (WebSocket, ``websockets``): the page loads the
bundle, starts an episode and shows a frame; a mouse drag orbits (new frame); a key press moves
(new frame); a teleport into a collision box is refused and the red banner shows the reason.
Skips with a reason when no Chromium is installed (CI installs ``chromium``).
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import httpx
import pytest

CHROMIUM = next((p for p in (os.environ.get("BRAVE6D_CHROMIUM"), shutil.which("chromium"),
                             shutil.which("chromium-browser"), shutil.which("google-chrome")) if p), None)

pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="headless Chromium not installed "
                                "(apt-get install chromium, or set BRAVE6D_CHROMIUM)")


class DevTools:
    """A minimal Chrome DevTools Protocol client over one page's WebSocket."""

    def __init__(self, ws_url: str) -> None:
        from websockets.sync.client import connect

        self._connection = connect(ws_url, max_size=None, open_timeout=30)
        self.ws = self._connection.__enter__()
        self.next_id = 0

    def call(self, method: str, timeout: float = 30.0, **params: object) -> dict:
        self.next_id += 1
        mid = self.next_id
        self.ws.send(json.dumps({"id": mid, "method": method, "params": params}))
        deadline = time.monotonic() + timeout
        while True:
            msg = json.loads(self.ws.recv(timeout=max(0.1, deadline - time.monotonic())))
            if msg.get("id") == mid:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})

    def eval(self, expression: str) -> object:
        out = self.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in out:
            raise RuntimeError(f"JS error in {expression!r}: {out['exceptionDetails']}")
        return out["result"].get("value")

    def wait_for(self, expression: str, timeout: float = 60.0) -> object:
        deadline = time.monotonic() + timeout
        guarded = f"(() => {{ try {{ return ({expression}); }} catch (e) {{ return false; }} }})()"
        while time.monotonic() < deadline:  # (the page may still be loading: errors mean "not yet")
            value = self.eval(guarded)
            if value:
                return value
            time.sleep(0.1)
        raise AssertionError(f"timed out waiting for {expression!r}")

    def close(self) -> None:
        self._connection.__exit__(None, None, None)


@pytest.fixture(scope="module")
def synthetic_bundle(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from brave6d.serve.toy_scene import make_synthetic_bundle

    return make_synthetic_bundle(tmp_path_factory.mktemp("viewer_scene"), n_gaussians=20_000)


@pytest.fixture()
def browser(tmp_path: Path):
    profile = tmp_path / "chromium-profile"
    profile.mkdir()
    proc = subprocess.Popen(
        [CHROMIUM, "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
         "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run",
         "--no-default-browser-check", "--disable-extensions", f"--user-data-dir={profile}",
         "--remote-debugging-address=127.0.0.1", "--remote-debugging-port=0", "--window-size=1100,800",
         "about:blank"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        port_file = profile / "DevToolsActivePort"
        deadline = time.monotonic() + 60
        while not (port_file.exists() and port_file.read_text().strip()):
            if proc.poll() is not None:
                pytest.skip(f"chromium exited with status {proc.returncode} at start")
            if time.monotonic() > deadline:
                pytest.skip("chromium did not open its DevTools port within 60 s")
            time.sleep(0.1)
        port = int(port_file.read_text().split()[0])
        pages = [t for t in httpx.get(f"http://127.0.0.1:{port}/json/list", timeout=10).json() if t["type"] == "page"]
        tools = DevTools(pages[0]["webSocketDebuggerUrl"])
        yield tools
        tools.close()
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)


def test_viewer_renders_moves_and_shows_refusal(synthetic_bundle: Path, tmp_path: Path, browser: DevTools) -> None:
    from brave6d.serve.app import create_app
    from brave6d.serve.runner import ServerThread

    app = create_app(synthetic_bundle, device="cpu", log_dir=tmp_path / "episodes", mode="training")  # draws the truth
    with ServerThread(app) as server:
        browser.call("Page.enable")
        browser.call("Page.navigate", url=f"{server.url}/viewer/?seed=5&width=320&height=240&target=0")
        browser.wait_for("document.body.dataset.state === 'ready' && Number(document.body.dataset.frames) >= 1")
        # the canvas shows a real render (not a blank image)
        spread = browser.eval("""(() => { const c = document.getElementById('view');
            const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
            let lo = 255, hi = 0; for (let i = 0; i < d.length; i += 4) { lo = Math.min(lo, d[i]); hi = Math.max(hi, d[i]); }
            return [c.width, c.height, hi - lo]; })()""")
        assert spread[0] == 320 and spread[1] == 240 and spread[2] > 50, spread
        # object axes and ids are drawn over the render
        labels = browser.eval("window.braveViewer.labels")
        assert any(label.startswith("id 1 cube_red") for label in labels), labels
        assert any(label.startswith("id 2 cube_blue") for label in labels), labels
        # the object table lists both objects with the target highlighted
        assert browser.eval("document.querySelectorAll('#objects tbody tr').length") == 2
        assert browser.eval("document.querySelectorAll('#objects tbody tr.target').length") == 1
        episode = browser.eval("window.braveViewer.episodeId")
        pose0 = httpx.get(f"{server.url}/episodes/{episode}").json()["world_T_cam"]

        # drag on the canvas: orbit -> a new frame and a new pose
        box = browser.eval("(() => { const r = document.getElementById('view').getBoundingClientRect();"
                           " return [r.left, r.top]; })()")
        x, y = box[0] + 160, box[1] + 120
        browser.call("Input.dispatchMouseEvent", type="mousePressed", x=x, y=y, button="left", buttons=1, clickCount=1)
        for k in range(1, 6):
            browser.call("Input.dispatchMouseEvent", type="mouseMoved", x=x + 8 * k, y=y, button="left", buttons=1)
        browser.call("Input.dispatchMouseEvent", type="mouseReleased", x=x + 40, y=y, button="left", buttons=0,
                     clickCount=1)
        browser.wait_for("Number(document.body.dataset.frames) >= 2 && window.braveViewer.idle")
        state = httpx.get(f"{server.url}/episodes/{episode}").json()
        assert state["world_T_cam"] != pose0 and state["adjustments"] >= 1

        # key W: one forward move
        frames = browser.eval("Number(document.body.dataset.frames)")
        adjustments = state["adjustments"]
        browser.call("Input.dispatchKeyEvent", type="keyDown", key="w", code="KeyW", text="w",
                     windowsVirtualKeyCode=87)
        browser.call("Input.dispatchKeyEvent", type="keyUp", key="w", code="KeyW", windowsVirtualKeyCode=87)
        browser.wait_for(f"Number(document.body.dataset.frames) > {frames} && window.braveViewer.idle")
        state = httpx.get(f"{server.url}/episodes/{episode}").json()
        assert state["adjustments"] == adjustments + 1

        # a teleport into the post: refused, red banner with the reason, pose unchanged
        before = state["world_T_cam"]
        browser.eval("window.braveViewer.setPose({look_at: {eye: [0.30, 0.25, 0.15], target: [0.45, 0.0, 0.0]}})")
        browser.wait_for("Number(document.body.dataset.refusals) >= 1")
        text = browser.eval("document.getElementById('banner').textContent")
        klass = browser.eval("document.getElementById('banner').className")
        assert "Refused" in text and "post" in text and "refused" in klass and "hidden" not in klass, (text, klass)
        colour = browser.eval("getComputedStyle(document.getElementById('banner')).backgroundColor")
        assert colour.startswith("rgba(200, 30, 30"), colour
        state = httpx.get(f"{server.url}/episodes/{episode}").json()
        assert state["world_T_cam"] == before and state["adjustments"] == adjustments + 1

        shot = browser.call("Page.captureScreenshot", format="png")
        out = Path(os.environ.get("BRAVE6D_VIEWER_SCREENSHOT", tmp_path / "viewer.png"))
        out.write_bytes(base64.b64decode(shot["data"]))
        assert out.stat().st_size > 1000


def test_viewer_of_a_scored_server_shows_images_only(synthetic_bundle: Path, tmp_path: Path,
                                                    browser: DevTools) -> None:
    """A scored server (the default) sends no object poses: the viewer draws the render without axes or
    object rows, says the mode, and still orbits (around the bundle's start target) and moves."""
    from brave6d.serve.app import create_app
    from brave6d.serve.runner import ServerThread

    with ServerThread(create_app(synthetic_bundle, device="cpu", log_dir=tmp_path / "episodes")) as server:
        browser.call("Page.enable")
        browser.call("Page.navigate", url=f"{server.url}/viewer/?seed=5&width=320&height=240&target=0")
        browser.wait_for("document.body.dataset.state === 'ready' && Number(document.body.dataset.frames) >= 1")
        assert browser.eval("document.body.dataset.serverMode") == "scored"
        assert "scored mode" in browser.eval("document.getElementById('scene').textContent")
        assert browser.eval("window.braveViewer.labels.length") == 0
        assert browser.eval("document.querySelectorAll('#objects tbody tr').length") == 0
        episode = browser.eval("window.braveViewer.episodeId")
        pose0 = httpx.get(f"{server.url}/episodes/{episode}").json()["world_T_cam"]
        box = browser.eval("(() => { const r = document.getElementById('view').getBoundingClientRect();"
                           " return [r.left, r.top]; })()")
        x, y = box[0] + 160, box[1] + 120
        browser.call("Input.dispatchMouseEvent", type="mousePressed", x=x, y=y, button="left", buttons=1, clickCount=1)
        for k in range(1, 6):
            browser.call("Input.dispatchMouseEvent", type="mouseMoved", x=x + 8 * k, y=y, button="left", buttons=1)
        browser.call("Input.dispatchMouseEvent", type="mouseReleased", x=x + 40, y=y, button="left", buttons=0,
                     clickCount=1)
        browser.wait_for("Number(document.body.dataset.frames) >= 2 && window.braveViewer.idle")
        assert httpx.get(f"{server.url}/episodes/{episode}").json()["world_T_cam"] != pose0


def test_viewer_free_view_of_a_bundle_without_objects(tmp_path: Path, browser: DevTools) -> None:
    """Issue #47's acceptance in the viewer: a bundle without objects (as an imported capture) opens in
    free view, draws a real image from POST /render, moves with the keys and shows a refused pose."""
    from brave6d.serve.app import create_app
    from brave6d.serve.runner import ServerThread
    from brave6d.serve.toy_scene import make_synthetic_bundle

    bare = make_synthetic_bundle(tmp_path / "bare", n_gaussians=8000, objects=False)
    with ServerThread(create_app(bare, device="cpu", log_dir=tmp_path / "episodes")) as server:
        browser.call("Page.enable")
        browser.call("Page.navigate", url=f"{server.url}/viewer/?width=160&height=120")
        browser.wait_for("document.body.dataset.state === 'ready' && Number(document.body.dataset.frames) >= 1")
        assert browser.eval("document.body.dataset.mode") == "free"
        assert browser.eval("document.getElementById('free').checked && document.getElementById('free').disabled")
        spread = browser.eval("""(() => { const c = document.getElementById('view');
            const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
            let lo = 255, hi = 0; for (let i = 0; i < d.length; i += 4) { lo = Math.min(lo, d[i]); hi = Math.max(hi, d[i]); }
            return [c.width, c.height, hi - lo]; })()""")
        assert spread[0] == 160 and spread[1] == 120 and spread[2] > 50, spread
        assert httpx.get(f"{server.url}/episodes").json()["episodes"] == []  # no episode was made

        pose0 = browser.eval("window.braveViewer.pose")
        frames = browser.eval("Number(document.body.dataset.frames)")
        browser.call("Input.dispatchKeyEvent", type="keyDown", key="w", code="KeyW", text="w", windowsVirtualKeyCode=87)
        browser.call("Input.dispatchKeyEvent", type="keyUp", key="w", code="KeyW", windowsVirtualKeyCode=87)
        browser.wait_for(f"Number(document.body.dataset.frames) > {frames} && window.braveViewer.idle")
        pose1 = browser.eval("window.braveViewer.pose")
        step = [pose1[i][3] - pose0[i][3] for i in range(3)]
        forward = [pose0[i][2] for i in range(3)]  # the camera's z axis in the world
        assert abs(sum(s * f for s, f in zip(step, forward)) - 0.02) < 1e-6, (step, forward)

        browser.eval("window.braveViewer.setPose({look_at: {eye: [0.30, 0.25, 0.15], target: [0.45, 0.0, 0.0]}})")
        browser.wait_for("Number(document.body.dataset.refusals) >= 1")
        assert "post" in browser.eval("document.getElementById('banner').textContent")
        assert browser.eval("window.braveViewer.pose") == pose1
