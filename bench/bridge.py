"""Bridge benchmark: a lock-step brain loop over Zenoh against a raw Zenoh query/reply loop, in one run.

The brain loop sends ``tick`` with a view and receives the state after the tick as a binary frame of
about 2 KB (the arm's bodies and joints plus a 166-channel noise module, 256 float64 values). The
baseline is a bare Zenoh queryable in another process answering the same command payload with a
reply of the same size, prepared in advance: the floor any bridge over Python Zenoh stands on. Both
servers run as separate processes on loopback; rounds of the two alternate so that both see the same
machine load, and the figures of each are the median over rounds.

Target: the brain loop at least 80 % of the raw rate.

Also printed, to say where the time goes: a brain loop that only reads the same frame (``read``, no
tick: the bridge's own cost), and the server-side cost of ``tick`` + frame measured in-process, hot
(called back to back) and cold (the caches flushed between calls, as they are in a lock-step loop where
two processes and the network stack share the cores).

Run: ``.venv/bin/python bench/bridge.py`` (``--rounds``, ``--seconds``).
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


def raw_server(port: int, size: int) -> None:
    """A bare queryable that answers every query with ``size`` prepared bytes."""
    from dynabrain.bridge.zenoh_io import FRAME, Settings, open_session

    session, _ = open_session(Settings(listen=[f"tcp/127.0.0.1:{port}"]))
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
    ap.add_argument("--seconds", type=float, default=1.5, help="length of one round")
    ap.add_argument("--pin", action="store_true",
                    help="pin the brain to the first CPU and the servers to the second (both loops alike)")
    ap.add_argument("--raw-server", nargs=2, type=int, metavar=("PORT", "SIZE"), help=argparse.SUPPRESS)
    ap.add_argument("--floor-server", type=int, metavar="PORT", help=argparse.SUPPRESS)
    opts = ap.parse_args()
    if opts.raw_server:
        raw_server(*opts.raw_server)
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


def benchmark(opts: argparse.Namespace) -> None:

    from dynabrain.bridge import BrainClient
    from dynabrain.bridge import protocol as p
    from dynabrain.bridge.zenoh_io import JSON, Settings, free_port, open_session

    cpus = sorted(os.sched_getaffinity(0))
    pin = opts.pin and len(cpus) >= 2
    if pin:
        os.sched_setaffinity(0, {cpus[0]})
    server_cpus = {cpus[1]} if pin else None
    _, line = spawn(["-m", "dynabrain.orchestrator.cli", "serve", "bridge/arm.yaml", "--listen",
                          "tcp/127.0.0.1:0", "--decimate", "0"], server_cpus)
    endpoint = re.search(r" on (\S+)", line).group(1)
    brain = BrainClient("arm", connect=endpoint)
    brain.add_module(name="noise", python="dynabrain.modules.basic:Noise", params={"n": NOISE_CHANNELS, "sigma": 0.1})
    brain.set("servo.target", [0.4, 0.6, -0.9])
    view = brain.view(VIEW)
    frame_bytes = 40 + 8 * view.size
    command = p.encode({"v": 1, "brain": brain.brain, "instance": brain.instance, "args": {"n": 1, "view": view.id}})

    port = free_port()
    spawn([os.path.join(HERE, "bridge.py"), "--raw-server", str(port), str(frame_bytes)], server_cpus)
    floor_port = free_port()
    spawn([os.path.join(HERE, "bridge.py"), "--floor-server", str(floor_port)], server_cpus)
    session, _ = open_session(Settings(connect=[f"tcp/127.0.0.1:{port}", f"tcp/127.0.0.1:{floor_port}"]))
    querier = session.declare_querier("dynabrain/raw/call/tick", timeout=10.0)
    floor_querier = session.declare_querier("dynabrain/floor/call/tick", timeout=10.0)

    def raw_step() -> None:
        reply = next(iter(querier.get(payload=command, encoding=JSON)))
        reply.ok.payload.to_bytes()

    def floor_step() -> None:
        reply = next(iter(floor_querier.get(payload=command, encoding=JSON)))
        reply.ok.payload.to_bytes()

    def brain_step() -> None:
        brain.tick(1, view=view)

    def read_step() -> None:
        brain.read(view)

    print(f"bridge benchmark (lock-step, loopback, {os.cpu_count()} cores{', pinned' if pin else ''}): "
          f"command {len(command)} B, reply {frame_bytes} B ({view.size} float64)")
    loops = {"raw": raw_step, "floor": floor_step, "brain": brain_step, "read": read_step}
    results: dict[str, list[dict[str, float]]] = {k: [] for k in loops}
    for r in range(opts.rounds):
        for name, step in loops.items():
            results[name].append(loop(step, opts.seconds))
        print(f"   round {r + 1}: " + "   ".join(f"{k} {v[-1]['rate']:6.0f}/s" for k, v in results.items()))
    med = {k: {m: statistics.median(x[m] for x in v) for m in ("rate", "p50", "p99")} for k, v in results.items()}
    labels = {"raw": "raw Zenoh query/reply", "floor": "floor: bare tick + frame server",
              "brain": "brain: tick + 2 KB state", "read": "brain: read 2 KB (no tick)"}
    print(f"   {'loop':<30} {'rate /s':>8} {'p50 us':>7} {'p99 us':>7} {'/ raw':>6}")
    for k, label in labels.items():
        m = med[k]
        rel = m["rate"] / med["raw"]["rate"]
        print(f"   {label:<30} {m['rate']:>8.0f} {m['p50']:>7.0f} {m['p99']:>7.0f} {rel:>6.2f}")
    ratio = med["brain"]["rate"] / med["raw"]["rate"]
    print(f"   brain tick loop / raw rate: {ratio:.2f}   target >= 0.80: {'met' if ratio >= 0.8 else 'MISSED'}")
    hot, cold = server_side_cost(view_signals=VIEW)
    extra = 1e6 / med["brain"]["rate"] - 1e6 / med["raw"]["rate"]
    print(f"   per round trip over raw: {extra:.0f} us; server-side tick + frame in-process: {hot:.0f} us hot, "
          f"{cold:.0f} us cold (caches flushed between calls)")
    print(f"   brain tick loop / floor (the same world behind a bare server): "
          f"{med['brain']['rate'] / med['floor']['rate']:.2f}")
    print(json.dumps({**med, "ratio": ratio, "server_tick_hot_us": hot, "server_tick_cold_us": cold}))

    querier.undeclare()
    floor_querier.undeclare()
    session.close()
    brain.close()


if __name__ == "__main__":
    main()
