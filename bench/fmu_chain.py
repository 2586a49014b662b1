"""FMU chain benchmark: 10 ``passthrough`` FMUs (FMI 2.0, 4 channels), each output wired to the next
input, 1 ms step, 10,000 steps; only the stepping is timed, every figure measured in this run on the
same FMUs: the median of `RUNS` runs (``--runs``), the best beside it. Every master's output at the end
of the chain is checked against the input (a passthrough chain: y of the last FMU is u of the first).
Targets: our master at most 0.6 us per FMU-step with history on, and at most 0.7 of ecos's figure in
the same run; an isolated FMU's step at most 40 us.

1. our master: a World with the 10 FMU modules (the kernel's schedule and bus; history on, so every
   FMU state is saved every tick, as in any run; the chain steps as one call into the C helper,
   `orchestrator.fmu.fused`), then the same without state saving, then with the C step helper off
   (the pure-Python path, a call per FMU);
2. the FMPy hand loop: ``FMU2Slave`` getReal / setReal / doStep;
3. libcosimpy, ecospy and OMSimulator (from PyPI): ``make bench-peers`` installs them (and the
   system's libtbb12 that ecos needs, where it can; OMSimulator's install downloads OpenModelica's
   binaries, so it is there only where that host is reached);
4. the C floor: a C program that dlopens the FMU and calls it directly;
5. FMU state costs per FMU: save + restore (GetFMUstate into a reused slot, SetFMUstate) and
   serialize + deserialize.

Run: ``.venv/bin/python bench/fmu_chain.py``  (builds the FMU into the dynabrain cache if needed)
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import os
import statistics
import subprocess
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from timing import best_of_each

from dynabrain.orchestrator.fmu import load_fmu_info
from dynabrain.orchestrator.fmu.build import compiler
from dynabrain.orchestrator.fmu.module import FMUModule
from dynabrain.orchestrator.kernel.world import World

ROOT = Path(__file__).resolve().parents[1]
N_FMUS, STEPS, DT_NS, CHANNELS = 10, 10_000, 1_000_000, 4
RUNS = 15
"""Timed runs of each contender (``--runs``): the median is the figure, the best is shown beside it."""
EXPECTED = np.arange(1.0, CHANNELS + 1)
"""The chain's output: the first FMU's input, passed through ten FMUs of gain 1."""


@dataclasses.dataclass(frozen=True)
class Timing:
    """Seconds of one timed call, over the runs: the median (the figure) and the best."""

    median: float
    best: float


def timed(fn: Callable[[], object], runs: int | None = None) -> Timing:
    """``fn()`` called ``runs`` times (default `RUNS`), each timed."""
    times = []
    for _ in range(RUNS if runs is None else runs):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return Timing(statistics.median(times), min(times))


def checked(out: object) -> str:
    """The chain's output, and whether it is what the chain must give."""
    values = np.asarray(out, dtype=float)
    return f"output {values.tolist()} {'(right)' if np.array_equal(values, EXPECTED) else '(WRONG)'}"


def per_fmu_step_us(seconds: float) -> float:
    return seconds / (STEPS * N_FMUS) * 1e6


# -- 1. our master ------------------------------------------------------------------------------------------
def master(info, *, save_states: bool = True, python_path: bool = False) -> tuple[Timing, np.ndarray]:
    world = World("chain", step=DT_NS, history=1000)
    for i in range(N_FMUS):
        m = FMUModule(f"p{i}", info)
        if not save_states:
            m.CAPABILITIES = dataclasses.replace(m.CAPABILITIES, can_rollback=False, can_fork=False)
        world.add_module(m)
        if python_path:
            m._session.stepper.use_python()
            m.bind()
    for i in range(N_FMUS - 1):
        world.connect(f"p{i}.y", f"p{i + 1}.u")
    world.set("p0.u", np.arange(1.0, CHANNELS + 1))
    world.tick(10)
    seconds = timed(lambda: world.tick(STEPS))
    out = world.get(f"p{N_FMUS - 1}.y")
    world.close()
    return seconds, out


# -- 2. FMPy ------------------------------------------------------------------------------------------------
def fmpy_loop(info, unzip: str) -> tuple[Timing, np.ndarray]:
    from fmpy.fmi2 import FMU2Slave

    vr_u = next(s.vrs for s in info.inputs if s.name == "u")
    vr_y = next(s.vrs for s in info.outputs if s.name == "y")
    fmus = []
    for i in range(N_FMUS):
        f = FMU2Slave(guid=info.token, modelIdentifier=info.model_identifier, unzipDirectory=unzip,
                      instanceName=f"p{i}")
        f.instantiate()
        f.setupExperiment(startTime=0.0)
        f.enterInitializationMode()
        f.exitInitializationMode()
        fmus.append(f)
    source = list(np.arange(1.0, CHANNELS + 1))
    state = {"t": 0.0, "k": 0}

    def run() -> None:
        h = DT_NS / 1e9
        for _ in range(STEPS):
            t = state["k"] * h
            values = source
            for f in fmus:
                f.setReal(vr_u, values)
                f.doStep(t, h)
                values = f.getReal(vr_y)
            state["k"] += 1
        state["out"] = values

    seconds = timed(run)
    for f in fmus:
        f.terminate()
        f.freeInstance()
    return seconds, np.array(state["out"])


# -- 3. libcosim and ecos -----------------------------------------------------------------------------------
def libcosim(info, fmu_path: str) -> tuple[Timing | None, str]:
    try:
        from libcosimpy.CosimExecution import CosimExecution
        from libcosimpy.CosimLogging import CosimLogLevel, log_output_level
        from libcosimpy.CosimObserver import CosimObserver
        from libcosimpy.CosimSlave import CosimLocalSlave
    except ImportError as exc:
        return None, f"libcosimpy does not import here: {exc}"
    log_output_level(CosimLogLevel.ERROR)
    vr_u = next(s.vrs for s in info.inputs if s.name == "u")
    vr_y = next(s.vrs for s in info.outputs if s.name == "y")
    ex = CosimExecution.from_step_size(DT_NS)
    slaves = [ex.add_local_slave(CosimLocalSlave(fmu_path, f"p{i}")) for i in range(N_FMUS)]
    for a, b in itertools.pairwise(slaves):
        for vy, vu in zip(vr_y, vr_u, strict=True):
            ex.connect_real_variables(a, vy, b, vu)
    for vu, value in zip(vr_u, range(1, CHANNELS + 1), strict=True):
        ex.real_initial_value(slaves[0], vu, float(value))
    observer = CosimObserver.create_last_value()  # (observes after each step: part of the timed cost)
    ex.add_observer(observer)
    ex.step(10)
    seconds = timed(lambda: ex.step(STEPS))
    out = observer.last_real_values(slaves[-1], list(vr_y))
    return seconds, f"libcosimpy {_version('libcosimpy')}, {checked(out)}"


def ecos(info, fmu_path: str) -> tuple[Timing | None, str]:
    try:
        from ecospy.EcosSimulation import EcosSimulation
        from ecospy.EcosSimulationStructure import EcosSimulationStructure
    except ImportError as exc:
        return None, f"ecospy does not import here: {exc}"
    structure = EcosSimulationStructure()
    for i in range(N_FMUS):
        structure.add_model(f"p{i}", fmu_path)
    for i in range(N_FMUS - 1):
        for c in range(1, CHANNELS + 1):
            structure.make_real_connection(f"p{i}::y[{c}]", f"p{i + 1}::u[{c}]")
    sim = EcosSimulation(structure=structure, step_size=DT_NS / 1e9)
    for c in range(1, CHANNELS + 1):
        sim.set_real(f"p0::u[{c}]", float(c))
    sim.init()
    sim.step(10)
    seconds = timed(lambda: sim.step(STEPS))
    out = [sim.get_real(f"p{N_FMUS - 1}::y[{c}]") for c in range(1, CHANNELS + 1)]
    sim.terminate()
    return seconds, f"ecospy {_version('ecospy')}, {checked(out)}"


def omsimulator(info, fmu_path: str) -> tuple[Timing | None, str]:
    """OMSimulator's weakly coupled co-simulation system (its Python scripting API), fixed step."""
    try:
        from OMSimulator import OMSimulator
    except ImportError as exc:
        return None, (f"OMSimulator does not import here ({exc}): pip install omsimulator (its install "
                      "downloads OpenModelica's binaries)")
    oms = OMSimulator()
    with tempfile.TemporaryDirectory() as tmp:
        oms.setTempDirectory(tmp)
        oms.newModel("chain")
        oms.addSystem("chain.root", oms.system_wc)
        for i in range(N_FMUS):
            oms.addSubModel(f"chain.root.p{i}", fmu_path)
        for i in range(N_FMUS - 1):
            for c in range(1, CHANNELS + 1):
                oms.addConnection(f"chain.root.p{i}.y[{c}]", f"chain.root.p{i + 1}.u[{c}]")
        oms.setResultFile("chain", "")
        oms.setFixedStepSize("chain.root", DT_NS / 1e9)
        oms.setStopTime("chain", 1e9)
        oms.instantiate("chain")
        for c in range(1, CHANNELS + 1):
            oms.setReal(f"chain.root.p0.u[{c}]", float(c))
        oms.initialize("chain")
        clock = {"k": 10}
        oms.stepUntil("chain", clock["k"] * DT_NS / 1e9)

        def run() -> None:
            clock["k"] += STEPS
            oms.stepUntil("chain", clock["k"] * DT_NS / 1e9)

        seconds = timed(run)
        out = []
        for c in range(1, CHANNELS + 1):
            got = oms.getReal(f"chain.root.p{N_FMUS - 1}.y[{c}]")
            out.append(got[0] if isinstance(got, tuple) else got)  # (value, status)
        oms.terminate("chain")
        oms.delete("chain")
    return seconds, f"OMSimulator {_version('OMSimulator')}, {checked(out)}"


def _version(dist: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(dist)
    except PackageNotFoundError:
        return "?"


# -- 4. the C floor -----------------------------------------------------------------------------------------
C_FLOOR = r"""
#include <dlfcn.h>
#include <stdio.h>
#include <time.h>
#include "fmi2Functions.h"
static void logger(fmi2ComponentEnvironment e, fmi2String n, fmi2Status s, fmi2String c, fmi2String m, ...) {}
int main(int argc, char **argv) {
    void *lib = dlopen(argv[1], RTLD_NOW);
    if (!lib) { fprintf(stderr, "%s\n", dlerror()); return 1; }
    fmi2InstantiateTYPE *inst = (fmi2InstantiateTYPE *)dlsym(lib, "fmi2Instantiate");
    fmi2SetupExperimentTYPE *setup = (fmi2SetupExperimentTYPE *)dlsym(lib, "fmi2SetupExperiment");
    fmi2EnterInitializationModeTYPE *enter = dlsym(lib, "fmi2EnterInitializationMode");
    fmi2ExitInitializationModeTYPE *leave = dlsym(lib, "fmi2ExitInitializationMode");
    fmi2SetRealTYPE *set = (fmi2SetRealTYPE *)dlsym(lib, "fmi2SetReal");
    fmi2GetRealTYPE *get = (fmi2GetRealTYPE *)dlsym(lib, "fmi2GetReal");
    fmi2DoStepTYPE *step = (fmi2DoStepTYPE *)dlsym(lib, "fmi2DoStep");
    fmi2CallbackFunctions cb = {logger, 0, 0, 0, 0};
    fmi2Component c[NF];
    for (int i = 0; i < NF; ++i) {
        c[i] = inst("p", fmi2CoSimulation, argv[2], "", &cb, 0, 0);
        setup(c[i], 0, 0.0, 0.0, 0, 0.0); enter(c[i]); leave(c[i]);
    }
    const fmi2ValueReference vu[4] = {1, 2, 3, 4}, vy[4] = {5, 6, 7, 8};
    double v[4] = {1, 2, 3, 4}, src[4] = {1, 2, 3, 4};
    for (int r = 0; r < RUNS; ++r) {
        struct timespec t0, t1;
        clock_gettime(CLOCK_MONOTONIC, &t0);
        for (long k = 0; k < STEPS; ++k) {
            for (int j = 0; j < 4; ++j) v[j] = src[j];
            for (int i = 0; i < NF; ++i) {
                set(c[i], vu, 4, v); step(c[i], k * 1e-3, 1e-3, fmi2True); get(c[i], vy, 4, v);
            }
        }
        clock_gettime(CLOCK_MONOTONIC, &t1);
        printf("%.9f ", (t1.tv_sec - t0.tv_sec) + 1e-9 * (t1.tv_nsec - t0.tv_nsec));
    }
    printf("\n%g %g %g %g\n", v[0], v[1], v[2], v[3]);
    return 0;
}
"""


def c_floor(info, unzip: str) -> tuple[Timing | None, str]:
    vr_u = next(s.vrs for s in info.inputs if s.name == "u")
    vr_y = next(s.vrs for s in info.outputs if s.name == "y")
    if list(vr_u) != [1, 2, 3, 4] or list(vr_y) != [5, 6, 7, 8]:
        return None, f"value references changed ({vr_u}, {vr_y}); update C_FLOOR"
    with tempfile.TemporaryDirectory() as tmp:
        src, exe = Path(tmp) / "floor.c", Path(tmp) / "floor"
        src.write_text(C_FLOOR)
        from dynabrain.orchestrator.fmu.paths import fmi_headers_dir

        cmd = [*compiler(), "-O2", f"-DNF={N_FMUS}", f"-DSTEPS={STEPS}", f"-DRUNS={RUNS}", f"-I{fmi_headers_dir()}",
               str(src), "-o", str(exe), "-ldl"]
        subprocess.run(cmd, check=True, capture_output=True)
        lib = Path(unzip) / "binaries" / "linux64" / f"{info.model_identifier}.so"
        out = subprocess.run([str(exe), str(lib), info.token], check=True, capture_output=True, text=True).stdout
    times, values = out.splitlines()
    runs = [float(x) for x in times.split()]
    return Timing(statistics.median(runs), min(runs)), checked([float(x) for x in values.split()])


# -- 5. state costs -----------------------------------------------------------------------------------------
def state_costs(info) -> dict[str, float]:
    n = 20_000
    with World("states", step=DT_NS) as world:
        m = FMUModule("p", info)
        world.add_module(m)
        world.tick(5)
        session, pool = m._session, m._pool
        state = pool.capture()
        t0 = time.perf_counter()
        for _ in range(n):
            s = pool.capture()
            pool.restore(s)
        save_restore = (time.perf_counter() - t0) / n * 1e6
        t0 = time.perf_counter()
        for _ in range(n // 10):
            blob = session.serialize(state)
            session.restore(blob)
        serial = (time.perf_counter() - t0) / (n // 10) * 1e6
        size = len(blob.data)
    return {"save+restore us": save_restore, "serialize+deserialize+restore us": serial, "serialized bytes": size}


def isolated_step(info) -> tuple[float, float]:
    """(seconds to start one isolated FMU, seconds per step of it): the price of a process of its own."""
    from dynabrain.orchestrator.fmu.isolate import IsolatedFMUModule

    with World("isolated", step=DT_NS) as world:
        t0 = time.perf_counter()
        world.add_module(IsolatedFMUModule("p", info))
        start = time.perf_counter() - t0
        world.tick(10)
        steps = 2000
        return start, timed(lambda: world.tick(steps)).median / steps


def _echo(conn) -> None:
    """The far end of `ping_pong`: answers each byte with one, until the pipe closes."""
    try:
        while True:
            conn.send_bytes(conn.recv_bytes())
    except EOFError:
        pass


def ping_pong(rounds: int = 5000) -> tuple[float, float]:
    """(seconds, seconds) of a one-byte round trip to another process over a pipe: waiting asleep in
    ``recv`` and waiting awake (polling the pipe without sleeping, as an isolated FMU's step does for up
    to `isolate.SPIN_S`): the floor under an isolated step, on this machine now."""
    import multiprocessing as mp

    here, there = mp.Pipe()
    child = mp.get_context("spawn").Process(target=_echo, args=(there,), daemon=True)
    child.start()

    def asleep() -> None:
        for _ in range(rounds):
            here.send_bytes(b"s")
            here.recv_bytes()

    def awake() -> None:
        for _ in range(rounds):
            here.send_bytes(b"s")
            while not here.poll(0):
                pass
            here.recv_bytes()

    try:
        asleep()  # the child is up and warm
        return tuple(t / rounds for t in best_of_each([asleep, awake], 5))
    finally:
        here.close()
        child.join(5)


def _peer(run: Callable[..., tuple[Timing | None, str]], name: str, info) -> tuple[Timing | None, str]:
    """A peer's figure, or None with why (a library that loads but cannot run this chain)."""
    try:
        return run(info, info.path)
    except Exception as exc:
        return None, f"{name} failed: {type(exc).__name__}: {exc}"


def main() -> None:
    global RUNS
    import fmpy

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=RUNS, help="timed runs of each contender (the median counts)")
    RUNS = parser.parse_args().runs
    info = load_fmu_info(str(ROOT / "fmus" / "passthrough@fmi2"))
    load = os.getloadavg()[0]
    print(f"FMU chain: {N_FMUS} x passthrough (FMI 2.0, {CHANNELS} channels), 1 ms step, {STEPS} steps, median of "
          f"{RUNS} runs (best beside it); machine: {os.cpu_count()} cores, load average {load:.1f}")
    results: list[tuple[str, Timing | None, str]] = []
    seconds, out = master(info)
    results.append(("our master (history on: states saved every tick)", seconds, checked(out)))
    seconds, out = master(info, save_states=False)
    results.append(("our master, no state saving", seconds, checked(out)))
    seconds, out = master(info, python_path=True)
    results.append(("our master, Python step path (no C helper)", seconds, checked(out)))
    with tempfile.TemporaryDirectory() as unzip:
        fmpy.extract(info.path, unzip)
        seconds, out = fmpy_loop(info, unzip)
        results.append((f"FMPy {fmpy.__version__} hand loop (setReal/doStep/getReal)", seconds, checked(out)))
        floor_s, note = c_floor(info, unzip)
        results.append(("C floor (dlopen, direct calls)", floor_s, note))
    results.append(("libcosim", *_peer(libcosim, "libcosimpy", info)))
    ecos_result = _peer(ecos, "ecospy", info)
    if ecos_result[0] is None and "failed" in ecos_result[1]:
        ecos_result = (None, ecos_result[1] + " (it needs the system's libtbb12)")
    results.append(("ecos", *ecos_result))
    results.append(("OMSimulator (weakly coupled system)", *_peer(omsimulator, "OMSimulator", info)))

    fmpy_us = per_fmu_step_us(results[3][1].median)
    print(f"   {'':52} {'us/FMU-step':>11} {'(best)':>7} {'vs FMPy loop':>12}")
    for label, seconds, note in results:
        if seconds is None:
            print(f"   {label:52} {'n/a':>11} {'':>7} {'':>12}  {note}")
            continue
        us = per_fmu_step_us(seconds.median)
        print(f"   {label:52} {us:11.3f} {per_fmu_step_us(seconds.best):7.3f} {fmpy_us / us:11.2f}x  {note}")
    ours = per_fmu_step_us(results[0][1].median)
    peers = {name: t for name, t, _ in results[5:]}
    ahead = ", ".join(f"{name.split()[0]}: " + ("n/a" if t is None else "yes" if ours < per_fmu_step_us(t.median)
                                                 else "NO") for name, t in peers.items())
    print(f"   target: our master <= 0.6 us per FMU-step: {'met' if ours <= 0.6 else 'MISSED'} ({ours:.3f} us); "
          f"ahead of the FMPy loop: {'yes' if ours < fmpy_us else 'NO'}; ahead of {ahead}")
    ec = peers["ecos"]
    if ec is None:
        print("   ours / ecos: n/a (ecospy is not installed: make bench-peers)")
    else:
        ratio = ours / per_fmu_step_us(ec.median)
        print(f"   ours / ecos: {ratio:.2f}  target <= 0.7: {'met' if ratio <= 0.7 else 'MISSED'}")
    costs = state_costs(info)
    print("FMU state per FMU (passthrough): " + ", ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}"
                                                          for k, v in costs.items()))
    per_tick = ours - per_fmu_step_us(results[1][1].median)
    print(f"   history's share of a step (master with states - without): {per_tick:.3f} us per FMU per tick")
    start, step = isolated_step(info)
    asleep, awake = ping_pong()
    print(f"isolate: true (one FMU in its own process): start {start * 1e3:.0f} ms, {step * 1e6:.1f} us per step "
          f"(median; inputs, outputs and the serialized state in shared memory, one byte each way on a socket)  "
          f"target <= 40 us: {'met' if step <= 40e-6 else 'MISSED'}")
    print(f"   the floor: a one-byte round trip to another process, {asleep * 1e6:.1f} us waiting asleep, "
          f"{awake * 1e6:.1f} us waiting awake (as the step does); the step's own work {(step - awake) * 1e6:.1f} us")


if __name__ == "__main__":
    main()
