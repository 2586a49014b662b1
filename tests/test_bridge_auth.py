"""Configurations beyond the loopback default, for real: a server configured with Zenoh user/password
authentication refuses brains with wrong or no credentials; the shipped secure configuration (TLS,
user/password, access control) lets a pilot drive the world and a monitor only watch it; a world,
a robot and a brain can meet through a router."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time

import pytest

from dynabrain.bridge import BrainClient, CallTimeoutError, ConnectError, NoWorldError
from dynabrain.bridge.testing import EmulatorProcess, ServerProcess
from dynabrain.bridge.zenoh_io import Settings, open_session

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ARM = os.path.join(ROOT, "bridge", "arm.yaml")
SECURE = os.path.join(ROOT, "bridge", "zenoh-secure.json5")


def credentials(folder) -> str:
    path = os.path.join(folder, "credentials.txt")
    with open(path, "w") as fh:
        fh.write("alice:wonderland\ngrafana:dashboards\n")
    return path


def brain(endpoint: str, user: str | None, password: str | None, **extra) -> BrainClient:
    return BrainClient("arm", settings=Settings(connect=[endpoint], user=user, password=password,
                                                connect_timeout_ms=1000, extra=extra))


def test_user_password_authentication_refuses_wrong_credentials(tmp_path):
    config = tmp_path / "auth.json5"
    config.write_text(json.dumps({"transport": {"auth": {"usrpwd": {"dictionary_file": credentials(tmp_path)}}}}))
    with ServerProcess(ARM, "--zenoh-config", str(config)) as server:
        with brain(server.endpoint, "alice", "wonderland") as alice:
            assert alice.tick(3) == 3
        for user, password in (("alice", "wrong"), (None, None), ("mallory", "wonderland")):
            with pytest.raises(ConnectError, match="accepts connections but refused the Zenoh session"):
                brain(server.endpoint, user, password)
        with brain(server.endpoint, "alice", "wonderland") as alice:  # the server went on
            assert alice.status()["tick"] == 3


def make_certificates(folder) -> None:
    """A CA and a server certificate for 127.0.0.1 / localhost, made with openssl."""
    certs = os.path.join(folder, "certs")
    os.makedirs(certs)

    def ssl(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=certs, check=True, capture_output=True)

    ssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes", "-days", "2",
        "-subj", "/CN=dynabrain test CA", "-keyout", "ca.key", "-out", "ca.pem")
    ssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes", "-subj", "/CN=localhost",
        "-keyout", "server.key", "-out", "server.csr")
    with open(os.path.join(certs, "san.ext"), "w") as fh:
        fh.write("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
    ssl("x509", "-req", "-in", "server.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial", "-days", "2",
        "-extfile", "san.ext", "-out", "server.pem")


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl not found: cannot make the TLS certificates")
def test_the_shipped_secure_config_lets_pilots_drive_and_monitors_only_watch(tmp_path):
    make_certificates(tmp_path)
    credentials(tmp_path)
    ca = str(tmp_path / "certs" / "ca.pem")
    with ServerProcess(ARM, "--zenoh-config", SECURE, "--lease", "1s", listen="tls/127.0.0.1:0",
                       cwd=str(tmp_path)) as server:
        assert server.endpoint.startswith("tls/")
        tls = {"transport/link/tls/root_ca_certificate": ca}
        with brain(server.endpoint, "alice", "wonderland", **tls) as pilot:
            assert pilot.tick(5) == 5
            with brain(server.endpoint, "grafana", "dashboards", **tls) as monitor:
                frames: list = []
                monitor.subscribe_state(frames.append)
                assert monitor.status()["tick"] == 5
                with pytest.raises((NoWorldError, CallTimeoutError)):  # its query never reaches the world
                    monitor.call("tick", 0.5)
                pilot.tick(3)
                assert pilot.status()["tick"] == 8
                end = time.monotonic() + 5
                while not any(f.tick == 8 for f in frames) and time.monotonic() < end:
                    time.sleep(0.02)
                assert any(f.tick == 8 for f in frames)  # the monitor watches the state stream
        with pytest.raises(ConnectError, match="refused the Zenoh session"):
            brain(server.endpoint, "alice", "wrong", **tls)
        with pytest.raises(ConnectError):  # right credentials, but no trust in the server's certificate
            brain(server.endpoint, "alice", "wonderland")


def test_a_world_served_through_a_router():
    """Server, robot emulator and brain as Zenoh clients of a router (here a router-mode session of the
    test process: real Zenoh routing, no peer-to-peer links)."""
    router, endpoints = open_session(Settings(listen=["tcp/127.0.0.1:0"], mode="router"))
    try:
        via = endpoints[0]
        with ServerProcess(ARM, "--mode", "client", "--connect", via, "--robot", "arm=servo", listen="") as server:
            assert f"through {via}" in server.ready_line
            with EmulatorProcess(ARM, "arm", via, "--mode", "client"), \
                    BrainClient("arm", settings=Settings(connect=[via], mode="client")) as pilot:
                assert pilot.tick(4) == 4
                end = time.monotonic() + 10
                while pilot.robot_status("arm")["mode"] != "disabled" and time.monotonic() < end:
                    time.sleep(0.05)
                status = pilot.robot_status("arm")  # its token and its state frames came through the router
                assert status["alive"] and status["mode"] == "disabled" and status["counts"]["states"] > 0
    finally:
        router.close()
