"""FMU chain benchmark: 10 ``passthrough`` FMUs (FMI 2.0, 4 channels), each output wired to the next
input, 1 ms step, 10,000 steps; only the stepping is timed (best of 5), every figure measured in this
run on the same FMUs. Targets: our master at most 0.6 us per FMU-step with history on, and at most
0.7 of ecos's figure in the same run; an isolated FMU's step at most 40 us.

1. our master: a World with the 10 FMU modules (the kernel's schedule and bus; history on, so every
   FMU state is saved every tick, as in any run; the chain steps as one call into the C helper,
   `orchestrator.fmu.fused`), then the same without state saving, then with the C step helper off
   (the pure-Python path, a call per FMU);
2. the FMPy hand loop: ``FMU2Slave`` getReal / setReal / doStep;
3. libcosimpy and ecospy (from PyPI): ``make bench-peers`` installs them (and the system's libtbb12
   that ecos needs, where it can);
4. the C floor: a C program that dlopens the FMU and calls it directly;
5. FMU state costs per FMU: save + restore (GetFMUstate into a reused slot, SetFMUstate) and
   serialize + deserialize.

Run: ``.venv/bin/python bench/fmu_chain.py``  (builds the FMU into the dynabrain cache if needed)
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
from timing import best_of, best_of_each

from dynabrain.orchestrator.fmu import load_fmu_info
from dynabrain.orchestrator.fmu.build import compiler
from dynabrain.orchestrator.fmu.module import FMUModule
from dynabrain.orchestrator.kernel.world import World

ROOT = Path(__file__).resolve().parents[1]
N_FMUS, STEPS, DT_NS, CHANNELS = 10, 10_000, 1_000_000, 4
REPEATS = 5


def per_fmu_step_us(seconds: float) -> float:
    return seconds / (STEPS * N_FMUS) * 1e6


# -- 1. our master ------------------------------------------------------------------------------------------
def master(info, *, save_states: bool = True, python_path: bool = False) -> tuple[float, np.ndarray]:
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
    seconds = best_of(lambda: world.tick(STEPS))
    out = world.get(f"p{N_FMUS - 1}.y")
    world.close()
    return seconds, out


# -- 2. FMPy ------------------------------------------------------------------------------------------------
def fmpy_loop(info, unzip: str) -> tuple[float, np.ndarray]:
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

    seconds = best_of(run)
    for f in fmus:
        f.terminate()
        f.freeInstance()
    return seconds, np.array(state["out"])


# -- 3. libcosim and ecos -----------------------------------------------------------------------------------
def libcosim(info, fmu_path: str) -> tuple[float | None, str]:
    try:
        from libcosimpy.CosimExecution import CosimExecution
        from libcosimpy.CosimLogging import CosimLogLevel, log_output_level
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
    ex.step(10)
    seconds = best_of(lambda: ex.step(STEPS))
    return seconds, "libcosimpy " + _version("libcosimpy")


def ecos(info, fmu_path: str) -> tuple[float | None, str]:
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
    seconds = best_of(lambda: sim.step(STEPS))
    out = [sim.get_real(f"p{N_FMUS - 1}::y[{c}]") for c in range(1, CHANNELS + 1)]
    sim.terminate()
    return seconds, f"ecospy {_version('ecospy')}, output {out}"


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
    double v[4] = {1, 2, 3, 4}, src[4] = {1, 2, 3, 4}, best = 1e30;
    for (int r = 0; r < 3; ++r) {
        struct timespec t0, t1;
        clock_gettime(CLOCK_MONOTONIC, &t0);
        for (long k = 0; k < STEPS; ++k) {
            for (int j = 0; j < 4; ++j) v[j] = src[j];
            for (int i = 0; i < NF; ++i) {
                set(c[i], vu, 4, v); step(c[i], k * 1e-3, 1e-3, fmi2True); get(c[i], vy, 4, v);
            }
        }
        clock_gettime(CLOCK_MONOTONIC, &t1);
        double s = (t1.tv_sec - t0.tv_sec) + 1e-9 * (t1.tv_nsec - t0.tv_nsec);
        if (s < best) best = s;
    }
    printf("%.9f %g %g %g %g\n", best, v[0], v[1], v[2], v[3]);
    return 0;
}
"""


def c_floor(info, unzip: str) -> tuple[float | None, str]:
    vr_u = next(s.vrs for s in info.inputs if s.name == "u")
    vr_y = next(s.vrs for s in info.outputs if s.name == "y")
    if list(vr_u) != [1, 2, 3, 4] or list(vr_y) != [5, 6, 7, 8]:
        return None, f"value references changed ({vr_u}, {vr_y}); update C_FLOOR"
    with tempfile.TemporaryDirectory() as tmp:
        src, exe = Path(tmp) / "floor.c", Path(tmp) / "floor"
        src.write_text(C_FLOOR)
        from dynabrain.orchestrator.fmu.paths import fmi_headers_dir

        cmd = [*compiler(), "-O2", f"-DNF={N_FMUS}", f"-DSTEPS={STEPS}", f"-I{fmi_headers_dir()}", str(src), "-o",
               str(exe), "-ldl"]
        subprocess.run(cmd, check=True, capture_output=True)
        lib = Path(unzip) / "binaries" / "linux64" / f"{info.model_identifier}.so"
        out = subprocess.run([str(exe), str(lib), info.token], check=True, capture_output=True, text=True).stdout
    seconds, *values = out.split()
    return float(seconds), f"output {values}"


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
        return start, best_of(lambda: world.tick(steps)) / steps


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


def main() -> None:
    import fmpy

    info = load_fmu_info(str(ROOT / "fmus" / "passthrough@fmi2"))
    print(f"FMU chain: {N_FMUS} x passthrough (FMI 2.0, {CHANNELS} channels), 1 ms step, {STEPS} steps, best of "
          f"{REPEATS}; machine: {os.cpu_count()} cores")
    results: list[tuple[str, float | None, str]] = []
    seconds, out = master(info)
    results.append(("our master (history on: states saved every tick)", seconds, f"output {out.tolist()}"))
    seconds, _ = master(info, save_states=False)
    results.append(("our master, no state saving", seconds, ""))
    seconds, _ = master(info, python_path=True)
    results.append(("our master, Python step path (no C helper)", seconds, ""))
    with tempfile.TemporaryDirectory() as unzip:
        fmpy.extract(info.path, unzip)
        seconds, out = fmpy_loop(info, unzip)
        results.append((f"FMPy {fmpy.__version__} hand loop (setReal/doStep/getReal)", seconds,
                        f"output {out.tolist()}"))
        floor_s, note = c_floor(info, unzip)
        results.append(("C floor (dlopen, direct calls)", floor_s, note))
    seconds, note = libcosim(info, info.path)
    results.append(("libcosim", seconds, note))
    try:
        seconds, note = ecos(info, info.path)
    except Exception as exc:  # a library that loads but cannot run this chain: say why
        seconds, note = None, f"ecospy failed: {type(exc).__name__}: {exc} (it needs the system's libtbb12)"
    results.append(("ecos", seconds, note))

    fmpy_us = per_fmu_step_us(results[3][1])
    print(f"   {'':52} {'us/FMU-step':>11} {'vs FMPy loop':>12}")
    for label, seconds, note in results:
        if seconds is None:
            print(f"   {label:52} {'n/a':>11} {'':>12}  {note}")
            continue
        us = per_fmu_step_us(seconds)
        print(f"   {label:52} {us:11.3f} {fmpy_us / us:11.2f}x  {note}")
    ours = per_fmu_step_us(results[0][1])
    lc, ec = results[5][1], results[6][1]
    print(f"   target: our master <= 0.6 us per FMU-step: {'met' if ours <= 0.6 else 'MISSED'} ({ours:.3f} us); "
          f"ahead of the FMPy loop: {'yes' if ours < fmpy_us else 'NO'}; ahead of libcosim: "
          f"{'n/a' if lc is None else ('yes' if ours < per_fmu_step_us(lc) else 'NO')}")
    if ec is None:
        print("   ours / ecos: n/a (ecospy is not installed: make bench-peers)")
    else:
        ratio = ours / per_fmu_step_us(ec)
        print(f"   ours / ecos: {ratio:.2f}  target <= 0.7: {'met' if ratio <= 0.7 else 'MISSED'}")
    costs = state_costs(info)
    print("FMU state per FMU (passthrough): " + ", ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}"
                                                          for k, v in costs.items()))
    per_tick = ours - per_fmu_step_us(results[1][1])
    print(f"   history's share of a step (master with states - without): {per_tick:.3f} us per FMU per tick")
    start, step = isolated_step(info)
    asleep, awake = ping_pong()
    print(f"isolate: true (one FMU in its own process): start {start * 1e3:.0f} ms, {step * 1e6:.1f} us per step "
          f"(inputs, outputs and the serialized state in shared memory, one byte each way on a socket)  "
          f"target <= 40 us: {'met' if step <= 40e-6 else 'MISSED'}")
    print(f"   the floor: a one-byte round trip to another process, {asleep * 1e6:.1f} us waiting asleep, "
          f"{awake * 1e6:.1f} us waiting awake (as the step does); the step's own work {(step - awake) * 1e6:.1f} us")


if __name__ == "__main__":
    main()
