"""A Ray cluster started outside dynabrain, as a user starts one: ``ray start --head`` and a worker node
(``ray start --address``), with Ray's default token authentication, on loopback. A brain in another
process joins it with the head's token (``RAY_AUTH_TOKEN``) and runs a batch whose branches equal the
serial ones bit for bit; without the token it is refused, and the error says a token is missing.
Only the cluster's own processes are stopped after (found by its temp folder): other Rays go on."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import uuid
from pathlib import Path

import pytest

pytest.importorskip("ray", reason="Ray (the ray extra) is not installed")
import psutil  # (Ray's own dependency)

RAY = str(Path(sys.executable).with_name("ray"))
DRIVER = """
import json, sys, time
import numpy as np
from dynabrain.orchestrator import Batch, load_world
from dynabrain.orchestrator.kernel.errors import DynabrainError
world = load_world("two_cubes")
kw = dict(branches=4, params={"core.friction": [0.3, 0.5, 0.7, 0.9]}, record=["core.aa.pos"])
try:
    with Batch(world, backend="ray", address=sys.argv[1]) as remote:
        remote.run(5, branches=2)  # the actors up
        t0 = time.perf_counter(); got = remote.run(100, **kw); t_ray = time.perf_counter() - t0
    with Batch(world, backend="serial") as serial:
        t0 = time.perf_counter(); want = serial.run(100, **kw); t_serial = time.perf_counter() - t0
    same = all(np.array_equal(got.branch("core.aa.pos", b), want.branch("core.aa.pos", b)) for b in range(4))
    print(json.dumps({"ok": got.ok, "same": same, "backend": got.backend,
                      "overhead_ms_per_branch": (t_ray - t_serial / 4) / 4 * 1e3}))
except DynabrainError as exc:
    print(json.dumps({"error": str(exc)}))
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _stop(temp: str) -> None:
    """Kill this cluster's processes (their command lines name its temp folder), with their children."""
    for proc in psutil.process_iter(["cmdline"]):
        if any(temp in arg for arg in proc.info["cmdline"] or ()):
            for p in [*proc.children(recursive=True), proc]:
                with contextlib.suppress(psutil.Error):
                    p.kill()


@pytest.fixture(scope="module")
def cluster():
    token = uuid.uuid4().hex
    temp = tempfile.mkdtemp(prefix="dbray-", dir="/tmp")  # (Ray's socket paths must stay short)
    home = tempfile.mkdtemp(prefix="dbray-home-")  # no ~/.ray/auth_token of the user's in the way
    env = {**os.environ, "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": token, "HOME": home,
           "RAY_USAGE_STATS_ENABLED": "0"}
    port = _free_port()
    common = ["--node-ip-address", "127.0.0.1", "--num-cpus", "1", "--disable-usage-stats"]
    try:
        subprocess.run([RAY, "start", "--head", "--port", str(port), "--include-dashboard", "false",
                        "--temp-dir", temp, *common], env=env, check=True, capture_output=True, timeout=120)
        subprocess.run([RAY, "start", "--address", f"127.0.0.1:{port}", *common], env=env, check=True,
                       capture_output=True, timeout=120)
        yield f"127.0.0.1:{port}", token, home
    finally:
        _stop(temp)
        for folder in (temp, home):
            shutil.rmtree(folder, ignore_errors=True)


def _driver(address: str, env: dict) -> dict:
    run = subprocess.run([sys.executable, "-c", DRIVER, address], capture_output=True, text=True, timeout=180,
                         env=env)
    assert run.returncode == 0, run.stderr[-3000:]
    return json.loads(run.stdout.strip().splitlines()[-1])


def test_a_brain_with_the_heads_token_runs_a_batch_on_the_external_cluster(cluster):
    address, token, home = cluster
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_AUTH")}
    seen = _driver(address, {**env, "RAY_AUTH_TOKEN": token, "HOME": home})  # no RAY_AUTH_MODE: dynabrain sets it
    assert seen.get("error") is None, seen
    assert seen["ok"] and seen["same"] and seen["backend"] == "ray", seen
    print(f"per-branch overhead on the external cluster: {seen['overhead_ms_per_branch']:.1f} ms")


def test_without_the_token_the_error_says_a_token_is_missing(cluster):
    address, _, home = cluster
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_AUTH")}
    seen = _driver(address, {**env, "HOME": home, "RAY_gcs_rpc_server_connect_timeout_s": "3"})
    assert "cannot join the Ray cluster" in seen.get("error", "") and "no token" in seen["error"], seen
    assert "RAY_AUTH_TOKEN" in seen["error"]
