"""Bridge benchmark: a lock-step brain loop over Zenoh against a bare server that ticks the same world, in one run.

The brain loop sends ``tick`` with a view and receives the state after the tick as a binary frame of
about 2 KB (the arm's bodies and joints plus a 166-channel noise module, 256 float64 values). The
reference (``floor``) is a bare Zenoh queryable in another process that ticks the same world and replies
with the same values as a frame: no protocol checks, holds or errors, the least a Python server can do
per lock-step call. Also measured: a raw queryable that answers with prepared bytes (the Zenoh round trip
alone, no tick), and a brain loop that only reads (``read``: the bridge's cost without the tick). All
servers are separate processes on loopback; rounds of the loops alternate so that all see the same
machine load, and the figures of each are the median over rounds.

Target (issue 18): the brain loop at least 0.95 of the floor's rate.

Shared memory: Zenoh 1.x moves a message of 3 KB or more through shared memory when both ends are on
one host (on by default). The bench compares a raw reply of the frame's size and one of 64 KB with
shared memory off and on, and the brain loop with its 2 KB frames moved to shared memory (a threshold of
512 bytes on both sides) against the default.

Run: ``.venv/bin/python bench/bridge.py`` (``--rounds``, ``--seconds``, ``--no-shm``).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
VIEW = ["core.body_pos", "core.body_quat", "core.body_linvel", "core.body_angvel", "core.joint_q", "core.joint_qd",
        "core.joint_force", "servo.force", "noise.y"]
NOISE_CHANNELS = 166


SHM_MODES = {"off": {"shared_memory": False}, "on": {"shared_memory": True, "shm_threshold": 512}}
"""Shared memory off, and on for every message of 512 bytes or more (Zenoh's default threshold is 3072)."""


def raw_server(port: int, size: int, shm: str = "default") -> None:
    """A bare queryable that answers every query with ``size`` prepared bytes."""
    from dynabrain.bridge.zenoh_io import FRAME, Settings, open_session

    session, _ = open_session(Settings(listen=[f"tcp/127.0.0.1:{port}"], **SHM_MODES.get(shm, {})))
    reply = bytes(size)

    def on_query(query) -> None:
        query.reply(query.key_expr, reply, encoding=FRAME)
        query.drop()

    queryable = session.declare_queryable("dynabrain/raw/call/tick", on_query, complete=True)
    print("ready", flush=True)
    sys.stdin.read()  # until the parent closes our stdin
    queryable.undeclare()
    session.close()


def floor_server(port: int) -> None:
    """The least a Python server can do per lock-step call on the same world: tick once, gather the same
    values into a frame, reply. No protocol, validation, holds or errors: the floor the bridge stands on."""
    from dynabrain.bridge import frames
    from dynabrain.bridge.zenoh_io import FRAME, Settings, open_session
    from dynabrain.modules.basic import Noise
    from dynabrain.orchestrator import load_world
    from dynabrain.orchestrator.kernel.observers import WorldView

    world = load_world(os.path.join(ROOT, "bridge", "arm.yaml"))
    world.add_module(Noise("noise", n=NOISE_CHANNELS, sigma=0.1))
    world.set("servo.target", [0.4, 0.6, -0.9])
    slots = WorldView(world).signal_slots()
    index = np.concatenate([np.arange(slots[n][0], slots[n][0] + int(np.prod(slots[n][1]))) for n in VIEW])
    view = WorldView(world)
    session, _ = open_session(Settings(listen=[f"tcp/127.0.0.1:{port}"]))

    def on_query(query) -> None:
        world.tick()
        query.reply(query.key_expr, frames.pack(frames.STATE, view.bus().take(index), seq=world.tick_count),
                    encoding=FRAME)
        query.drop()

    queryable = session.declare_queryable("dynabrain/floor/call/tick", on_query, complete=True)
    print("ready", flush=True)
    sys.stdin.read()
    queryable.undeclare()
    session.close()
    world.close()


CHILDREN: list[subprocess.Popen] = []


def spawn(args: list[str], cpus: set[int] | None = None) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen([sys.executable, *args], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                            cwd=ROOT)
    CHILDREN.append(proc)
    if cpus:
        os.sched_setaffinity(proc.pid, cpus)  # before it starts its threads: they inherit it
    return proc, proc.stdout.readline()


def loop(step, seconds: float) -> dict[str, float]:
    for _ in range(200):  # warm up
        step()
    lat = []
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        t0 = time.perf_counter()
        step()
        lat.append(time.perf_counter() - t0)
    arr = np.array(lat)
    return {"rate": len(arr) / arr.sum(), "p50": float(np.percentile(arr, 50)) * 1e6,
            "p99": float(np.percentile(arr, 99)) * 1e6, "n": len(arr)}


def server_side_cost(view_signals: list[str], calls: int = 2000) -> tuple[float, float]:
    """In-process cost (us) of the server's tick-with-view on the benchmark's world, hot and cold."""
    from dynabrain.bridge import protocol as p
    from dynabrain.bridge.calls import WorldService
    from dynabrain.modules.basic import Noise
    from dynabrain.orchestrator import load_world

    world = load_world(os.path.join(ROOT, "bridge", "arm.yaml"))
    world.add_module(Noise("noise", n=NOISE_CHANNELS, sigma=0.1))
    service = WorldService(world, instance=1)
    args = p.TickArgs(n=1, view=service.do_view(p.ViewArgs(signals=view_signals))["view"])
    junk = np.ones(4_000_000)  # 32 MB: more than the caches
    out = []
    for flush in (False, True):
        total = 0.0
        for _ in range(calls):
            if flush:
                junk += 1.0
            t0 = time.perf_counter()
            service.call("tick", args)
            total += time.perf_counter() - t0
        out.append(total / calls * 1e6)
    world.close()
    return out[0], out[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--seconds", type=float, default=1.0, help="length of one loop in a round")
    ap.add_argument("--no-shm", action="store_true", help="leave out the shared-memory comparison")
    ap.add_argument("--pin", action="store_true",
                    help="pin the brain to the first CPU and the servers to the second (all loops alike)")
    ap.add_argument("--raw-server", nargs=3, metavar=("PORT", "SIZE", "SHM"), help=argparse.SUPPRESS)
    ap.add_argument("--floor-server", type=int, metavar="PORT", help=argparse.SUPPRESS)
    opts = ap.parse_args()
    if opts.raw_server:
        raw_server(int(opts.raw_server[0]), int(opts.raw_server[1]), opts.raw_server[2])
        return
    if opts.floor_server:
        floor_server(opts.floor_server)
        return
    try:
        benchmark(opts)
    finally:
        for proc in CHILDREN:
            if proc.poll() is None:
                proc.terminate()
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()


TARGET = 0.95


def serve(config: str | None, cpus: set[int] | None) -> str:
    """A `dynabrain serve` of the arm; its endpoint."""
    extra = ["--zenoh-config", config] if config else []
    _, line = spawn(["-m", "dynabrain.orchestrator.cli", "serve", "bridge/arm.yaml", "--listen", "tcp/127.0.0.1:0",
                     "--decimate", "0", *extra], cpus)
    match = re.search(r" on (\S+)", line)
    if match is None:
        raise SystemExit(f"the server did not start: {line!r}")
    return match.group(1)


def brain_on(endpoint: str, settings_extra: dict) -> tuple:
    from dynabrain.bridge import BrainClient
    from dynabrain.bridge.zenoh_io import Settings

    brain = BrainClient("arm", settings=Settings(connect=[endpoint], **settings_extra))
    brain.add_module(name="noise", python="dynabrain.modules.basic:Noise", params={"n": NOISE_CHANNELS, "sigma": 0.1})
    brain.set("servo.target", [0.4, 0.6, -0.9])
    return brain, brain.view(VIEW)


def benchmark(opts: argparse.Namespace) -> None:
    from dynabrain.bridge import protocol as p
    from dynabrain.bridge.zenoh_io import JSON, Settings, free_port, open_session

    cpus = sorted(os.sched_getaffinity(0))
    pin = opts.pin and len(cpus) >= 2
    if pin:
        os.sched_setaffinity(0, {cpus[0]})
    server_cpus = {cpus[1]} if pin else None
    brain, view = brain_on(serve(None, server_cpus), {})
    frame_bytes = 40 + 8 * view.size
    command = p.encode({"v": 1, "brain": brain.brain, "instance": brain.instance, "args": {"n": 1, "view": view.id}})

    raws = {"raw": (frame_bytes, "default")}
    if not opts.no_shm:
        raws.update({"raw 2k shm off": (frame_bytes, "off"), "raw 2k shm on": (frame_bytes, "on"),
                     "raw 64k shm off": (64 * 1024, "off"), "raw 64k shm on": (64 * 1024, "on")})
    ports = {}
    for name, (size, shm) in raws.items():
        ports[name] = free_port()
        spawn([os.path.join(HERE, "bridge.py"), "--raw-server", str(ports[name]), str(size), shm], server_cpus)
    floor_port = free_port()
    spawn([os.path.join(HERE, "bridge.py"), "--floor-server", str(floor_port)], server_cpus)
    sessions = []

    def querier(port: int, key: str):
        session, _ = open_session(Settings(connect=[f"tcp/127.0.0.1:{port}"]))
        sessions.append(session)
        q = session.declare_querier(key, timeout=10.0)

        def step() -> None:
            reply = next(iter(q.get(payload=command, encoding=JSON)))
            reply.ok.payload.to_bytes()
        return step

    loops = {"raw": querier(ports["raw"], "dynabrain/raw/call/tick"),
             "floor": querier(floor_port, "dynabrain/floor/call/tick"),
             "brain": lambda: brain.tick(1, view=view),
             "read": lambda: brain.read(view)}
    shm_brain = None
    if not opts.no_shm:
        import tempfile

        with tempfile.NamedTemporaryFile("w", suffix=".json5", delete=False) as conf:
            conf.write('{transport: {shared_memory: {enabled: true, '
                       'transport_optimization: {message_size_threshold: 512}}}}')
        shm_brain, shm_view = brain_on(serve(conf.name, server_cpus), SHM_MODES["on"])
        loops["brain shm"] = lambda: shm_brain.tick(1, view=shm_view)
        for name in raws:
            if name != "raw":
                loops[name] = querier(ports[name], "dynabrain/raw/call/tick")

    print(f"bridge benchmark (lock-step, loopback, {os.cpu_count()} cores{', pinned' if pin else ''}, "
          f"load {os.getloadavg()[0]:.2f}): command {len(command)} B, reply {frame_bytes} B ({view.size} float64)")
    results: dict[str, list[dict[str, float]]] = {k: [] for k in loops}
    for r in range(opts.rounds):
        for name, step in loops.items():
            results[name].append(loop(step, opts.seconds))
        print(f"   round {r + 1}: " + "  ".join(f"{k} {v[-1]['rate']:.0f}" for k, v in results.items()
                                              if "shm" not in k) + " /s")
    med = {k: {m: statistics.median(x[m] for x in v) for m in ("rate", "p50", "p99")} for k, v in results.items()}
    labels = {"raw": "raw Zenoh query/reply (no tick)", "floor": "floor: bare tick + frame server",
              "brain": "brain: tick + 2 KB state", "read": "brain: read 2 KB (no tick)"}
    print(f"   {'loop':<32} {'rate /s':>8} {'p50 us':>7} {'p99 us':>7} {'/ floor':>8}")
    for k, label in labels.items():
        m = med[k]
        rel = m["rate"] / med["floor"]["rate"]
        print(f"   {label:<32} {m['rate']:>8.0f} {m['p50']:>7.0f} {m['p99']:>7.0f} {rel:>8.2f}")
    ratio = med["brain"]["rate"] / med["floor"]["rate"]
    pairs = zip(results["brain"], results["floor"], strict=True)
    per_round = statistics.median(b["rate"] / f["rate"] for b, f in pairs)
    print(f"   brain tick loop / floor: {ratio:.3f} (median of per-round ratios {per_round:.3f})   "
          f"target >= {TARGET}: {'met' if ratio >= TARGET else 'MISSED'}")
    us = {k: 1e6 / med[k]["rate"] for k in ("raw", "floor", "brain")}
    hot, cold = server_side_cost(view_signals=VIEW)
    print(f"   per lock-step tick: Zenoh round trip {us['raw']:.0f} us, + the floor's tick and frame "
          f"{us['floor'] - us['raw']:.0f} us, + the bridge {us['brain'] - us['floor']:.0f} us "
          f"(server-side tick + frame in-process: {hot:.0f} us hot, {cold:.0f} us cold)")
    out = {**med, "ratio": ratio, "target": TARGET, "server_tick_hot_us": hot, "server_tick_cold_us": cold}
    if shm_brain is not None:
        print("   shared memory (Zenoh's transport between the two processes; off / on for messages >= 512 B):")
        for size in ("2k", "64k"):
            off, on = med[f"raw {size} shm off"]["rate"], med[f"raw {size} shm on"]["rate"]
            print(f"     raw reply {size:>3}: off {off:7.0f}/s  on {on:7.0f}/s  on / off {on / off:.2f}")
        shm = med["brain shm"]["rate"] / med["brain"]["rate"]
        print(f"     brain tick loop, 2 KB frames through shared memory / default (under Zenoh's 3 KB threshold): "
              f"{shm:.2f}")
        out["shm_brain_ratio"] = shm
    print(json.dumps(out))

    for session in sessions:
        session.close()
    brain.close()
    if shm_brain is not None:
        shm_brain.close()


if __name__ == "__main__":
    main()
