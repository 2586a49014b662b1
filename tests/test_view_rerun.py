"""A log seen in Rerun, in a real browser: a logged run (a robot arm beside a post, a crate; then a batch of
pushes on a slider, two of them kept as imagined futures) becomes a Rerun recording with the scene's bodies,
their poses, the signals, the events and each imagined future under entity paths of its own (read back with
the ``rerun`` program); the recording served on loopback by `serve_rrd`, opened in headless Chromium (Debian's
``chromium``) and screenshot through the DevTools protocol shows the scene: the bodies' colours in the 3D
view's region, not an empty view. The same browser then opens a running world streamed by `RerunLive`
(``serve --view``): the blocks on their table. One browser, started once (the suite's heavy check)."""

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
from typing import Any

import numpy as np
import pytest

rr = pytest.importorskip("rerun", reason="rerun-sdk is not installed (the [view] extra)")

from dynabrain.orchestrator import Batch  # noqa: E402
from dynabrain.orchestrator.logs.logger import McapLogger  # noqa: E402
from dynabrain.orchestrator.logs.rerun_live import RerunLive  # noqa: E402
from dynabrain.orchestrator.logs.rerun_view import record_log, rerun_program, serve_rrd, viewer_url  # noqa: E402
from dynabrain.orchestrator.scenario.model import load_scenario  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TESTS = Path(__file__).resolve().parent
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
BROWSER_WAIT_S = 25.0
BODY_PIXELS = 400
"""Saturated pixels in the 3D view's region that say bodies are drawn (an empty view, or one still loading,
has none: its greys, whites and the loading screen's dark)."""


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
        self.port = int(active.read_text().split()[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{self.port}/json/list", timeout=10) as resp:
            page = next(p for p in json.load(resp) if p.get("type") == "page")
        self.ws: Any = None
        self._connect(page["webSocketDebuggerUrl"])

    def _connect(self, url: str) -> None:
        from websockets.sync.client import connect

        if self.ws is not None:
            self.ws.__exit__(None, None, None)
        self.ws = connect(url, max_size=None).__enter__()
        self.calls = 0

    def open(self, url: str) -> None:
        """A new page at ``url`` (another origin: a page of its own), screenshot from now on."""
        request = urllib.request.Request(f"http://127.0.0.1:{self.port}/json/new?{url}", method="PUT")
        with urllib.request.urlopen(request, timeout=10) as resp:
            self._connect(json.load(resp)["webSocketDebuggerUrl"])

    def call(self, method: str, params: dict) -> dict:
        self.calls += 1
        self.ws.send(json.dumps({"id": self.calls, "method": method, "params": params}))
        while True:
            reply = json.loads(self.ws.recv(timeout=30))
            if reply.get("id") == self.calls:
                assert "error" not in reply, f"{method}: {reply['error']}"
                return reply["result"]

    def shows_bodies(self, until: float) -> tuple[bool, np.ndarray]:
        """Screenshots until the 3D view shows bodies (`body_pixels`) or ``until`` (monotonic time) passes."""
        image = self.screenshot()
        while body_pixels(image) < BODY_PIXELS and time.monotonic() < until:
            time.sleep(0.5)
            image = self.screenshot()
        return body_pixels(image) >= BODY_PIXELS, image

    def screenshot(self) -> np.ndarray:
        """The page as an (h, w, 3) uint8 image."""
        from PIL import Image

        png = base64.b64decode(self.call("Page.captureScreenshot", {"format": "png"})["data"])
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
def test_web_viewer_shows_the_scene_of_a_log_and_of_a_running_world(logs, tmp_path):
    from PIL import Image

    arm, _slider = logs
    record_log(arm, tmp_path / "arm.rrd")
    web, grpc = _free_port(), _free_port()
    server = serve_rrd(tmp_path / "arm.rrd", web_port=web, grpc_port=grpc)
    browser = live = world = None
    try:
        end = time.monotonic() + BROWSER_WAIT_S
        while socket.socket().connect_ex(("127.0.0.1", web)) != 0:
            assert time.monotonic() < end and server.poll() is None, "the rerun web viewer did not start"
            time.sleep(0.1)
        browser = DevTools(viewer_url(web, grpc), tmp_path / "profile")
        loading = body_pixels(browser.screenshot())  # the viewer is still loading: no scene yet
        shown, image = browser.shows_bodies(end)
        Image.fromarray(image).save(tmp_path / "log.png")
        assert shown, f"the 3D view shows no bodies after {BROWSER_WAIT_S} s (see {tmp_path / 'log.png'})"
        assert loading < BODY_PIXELS

        blocks = load_scenario(ROOT / "scenarios" / "blocks.yaml")  # coloured blocks on a table
        world = blocks.build()
        live = RerunLive(web_port=_free_port(), grpc_port=_free_port()).attach(world)
        world.tick(100)
        assert live.sent >= 4
        browser.open(live.url)
        shown, image = browser.shows_bodies(time.monotonic() + BROWSER_WAIT_S)
        Image.fromarray(image).save(tmp_path / "live.png")
        assert shown, f"the live 3D view shows no bodies (see {tmp_path / 'live.png'})"
    finally:
        if browser is not None:
            browser.close()
        if world is not None:
            world.close()  # closes the live stream (an observer) too
        if live is not None:
            live.close()
        server.kill()
        server.wait()
