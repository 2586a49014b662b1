"""A log seen in Rerun, in a real browser: a logged run (a robot arm beside a post, a crate; then a batch of
pushes on a slider, two of them kept as imagined futures) becomes a Rerun recording with the scene's bodies,
their poses, the signals, the events and each imagined future under entity paths of its own (read back with
the ``rerun`` program); the recording served on loopback by `serve_rrd`, opened in headless Chromium (Debian's
``chromium``) and screenshot through the DevTools protocol shows the scene: the bodies' colours in the 3D
view's region, not an empty view. One browser, started once (the suite's heavy check)."""

from __future__ import annotations

import base64
import io
import json
import shutil
import socket
import subprocess
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

rr = pytest.importorskip("rerun", reason="rerun-sdk is not installed (the [view] extra)")

from dynabrain.orchestrator import Batch  # noqa: E402
from dynabrain.orchestrator.logs.logger import McapLogger  # noqa: E402
from dynabrain.orchestrator.logs.rerun_view import record_log, rerun_program, serve_rrd, viewer_url  # noqa: E402
from dynabrain.orchestrator.scenario.model import load_scenario  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TESTS = Path(__file__).resolve().parent
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
BROWSER_WAIT_S = 25.0


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    """The arm's run (scenarios/robot_arm.yaml, 0.6 s) and the slider with two imagined pushes, logged."""
    tmp = tmp_path_factory.mktemp("view")
    arm = load_scenario(ROOT / "scenarios" / "robot_arm.yaml")
    world = arm.build()
    McapLogger(tmp / "arm.mcap").attach(world, arm)
    world.tick(300)
    world.close()
    slider = load_scenario(TESTS / "scenarios" / "slider.yaml")
    world = slider.build()
    McapLogger(tmp / "slider.mcap").attach(world, slider)
    world.tick(10)
    with Batch(world, backend="serial") as batch:
        forces = np.array([np.full(30, f) for f in (-2.0, 0.0, 2.0)])
        pushes = batch.run(30, branches=3, inputs={"core.s.force": forces},
                           record=["core.cart.pos", "core.cart.quat", "core.s.q"])
        pushes.imagine(world, "push", branches=[0, 2])
    world.tick(30)
    world.close()
    return tmp / "arm.mcap", tmp / "slider.mcap"


def entity_paths(rrd: Path) -> set[str]:
    """The entity paths of a recording, as the ``rerun`` program prints them."""
    out = subprocess.run([rerun_program(), "rrd", "print", str(rrd)], capture_output=True, text=True, timeout=60,
                         check=True)
    return {w for w in out.stdout.split() if w.startswith("/")}


def test_recording_holds_bodies_signals_events_and_futures(logs, tmp_path):
    arm, slider = logs
    report = record_log(arm, tmp_path / "arm.rrd")
    paths = entity_paths(tmp_path / "arm.rrd")
    assert report.bodies >= 4 and report.poses >= 300 and report.signals > 0
    drawn = {"/world/crate/boxes", "/world/turret/cylinders", "/world/hand/spheres", "/world/upper/boxes"}
    assert drawn <= paths, sorted(paths)[:40]
    assert any(p.startswith("/signals/") for p in paths)
    report = record_log(slider, tmp_path / "slider.rrd")
    paths = entity_paths(tmp_path / "slider.rrd")
    assert sorted(report.imagined) == ["imagined/push/0", "imagined/push/2"]
    for branch in (0, 2):  # each future drawn beside the cart, with its own signals
        assert {f"/imagined/push/{branch}/cart", f"/imagined/push/{branch}/cart/boxes",
                f"/imagined/push/{branch}/signals/core/s/q"} <= paths, sorted(paths)
    assert "/world/cart" in paths


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class DevTools:
    """Headless Chromium driven through its DevTools protocol (loopback): screenshots of its one page."""

    def __init__(self, url: str, profile: Path):
        self.proc = subprocess.Popen([CHROMIUM, "--headless", "--no-sandbox", "--use-angle=swiftshader",
                                      "--enable-unsafe-swiftshader", "--window-size=1280,800", "--no-first-run",
                                      "--remote-debugging-address=127.0.0.1", "--remote-debugging-port=0",
                                      f"--user-data-dir={profile}", url],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        active = profile / "DevToolsActivePort"
        end = time.monotonic() + BROWSER_WAIT_S
        while not active.exists() or not active.read_text().strip():
            assert time.monotonic() < end and self.proc.poll() is None, "chromium did not start its DevTools server"
            time.sleep(0.1)
        port = int(active.read_text().split()[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as resp:
            page = next(p for p in json.load(resp) if p.get("type") == "page")
        from websockets.sync.client import connect

        self.ws = connect(page["webSocketDebuggerUrl"], max_size=None).__enter__()
        self.calls = 0

    def screenshot(self) -> np.ndarray:
        """The page as an (h, w, 3) uint8 image."""
        from PIL import Image

        self.calls += 1
        self.ws.send(json.dumps({"id": self.calls, "method": "Page.captureScreenshot", "params": {"format": "png"}}))
        while True:
            reply = json.loads(self.ws.recv(timeout=30))
            if reply.get("id") == self.calls:
                png = base64.b64decode(reply["result"]["data"])
                return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))

    def close(self) -> None:
        self.ws.__exit__(None, None, None)
        self.proc.kill()
        self.proc.wait()


def body_pixels(image: np.ndarray) -> int:
    """Coloured pixels (the bodies: saturated, not the viewer's greys and whites) in the 3D view's region:
    the left 60% of the page below its top bar, above the time panel."""
    h, w, _ = image.shape
    region = image[int(0.08 * h):int(0.92 * h), :int(0.58 * w)].astype(int)
    saturation = region.max(axis=2) - region.min(axis=2)
    return int((saturation > 80).sum())


@pytest.mark.skipif(CHROMIUM is None, reason="no chromium on PATH (make system-deps installs Debian's package)")
def test_web_viewer_shows_the_scene(logs, tmp_path):
    arm, _slider = logs
    record_log(arm, tmp_path / "arm.rrd")
    web, grpc = _free_port(), _free_port()
    server = serve_rrd(tmp_path / "arm.rrd", web_port=web, grpc_port=grpc)
    browser = None
    try:
        end = time.monotonic() + BROWSER_WAIT_S
        while socket.socket().connect_ex(("127.0.0.1", web)) != 0:
            assert time.monotonic() < end and server.poll() is None, "the rerun web viewer did not start"
            time.sleep(0.1)
        browser = DevTools(viewer_url(web, grpc), tmp_path / "profile")
        first = browser.screenshot()  # the viewer is still loading: no scene yet
        image, seen = first, body_pixels(first)
        while seen < 400 and time.monotonic() < end:
            time.sleep(0.5)
            image = browser.screenshot()
            seen = body_pixels(image)
        from PIL import Image

        Image.fromarray(image).save(tmp_path / "viewer.png")
        assert seen >= 400, f"the 3D view shows no bodies after {BROWSER_WAIT_S} s (see {tmp_path / 'viewer.png'})"
        assert body_pixels(first) < seen
    finally:
        if browser is not None:
            browser.close()
        server.kill()
        server.wait()
