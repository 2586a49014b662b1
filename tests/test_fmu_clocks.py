"""FMI 3.0 clocks in co-simulation (fmus/conformance/sampled_pi and plant, built here): a PI controller
sampled at 100 Hz by a time-based clock drives a plant stepped at 1 kHz, exactly as the sampled
system computed by hand; event mode at every tick; triggered input clocks and output clocks on the
bus; rollback, fork and isolation bit for bit; clocks that cannot run are refused with their name."""

from __future__ import annotations

import math
import zipfile
from pathlib import Path

import numpy as np
import pytest

from dynabrain.orchestrator.fmu import FMUError, make_fmu_module
from dynabrain.orchestrator.fmu.build import build_fmu, package_fmu
from dynabrain.orchestrator.fmu.check import check_fmu
from dynabrain.orchestrator.kernel.errors import DynabrainError, WiringError
from dynabrain.orchestrator.kernel.module import Module, Port
from dynabrain.orchestrator.kernel.world import World

ROOT = Path(__file__).resolve().parents[1]
CONFORMANCE = ROOT / "fmus" / "conformance"
KP, KI, R, TAU, GAIN, PERIOD, H = 0.8, 6.0, 1.0, 0.05, 2.0, 0.01, 0.001

pytestmark = pytest.mark.usefixtures("fmu_cache")  # FMUs built here go to a cache of this module's own


def loop(isolate: bool = False, **pi_params) -> World:
    """The plant at 1 kHz under the PI controller (its clock: 100 Hz), both stepping every 1 ms."""
    world = World(step="1ms")
    world.add_module(make_fmu_module("plant", "fmus/conformance/plant@fmi3", base_dir=str(ROOT), params={},
                                     targets=[], isolate=isolate))
    world.add_module(make_fmu_module("pi", "fmus/conformance/sampled_pi", base_dir=str(ROOT), params=pi_params,
                                     targets=[], isolate=isolate), connect=[("plant.y", "pi.y"), ("pi.u", "plant.u")])
    return world


def by_hand(ticks: int) -> list[tuple[float, float, int]]:
    """(plant.y, pi.u, samples) after each tick: the controller samples the plant's output as the bus
    holds it when the controller steps (the plant's, from the tick's start) at each 10 ms, the first at
    t=0 (initialization); the plant then steps with the command."""
    y, integral, samples = 0.0, 0.0, 0

    def sample(y: float) -> float:
        nonlocal integral, samples
        e = R - y
        integral += e * PERIOD
        samples += 1
        return KP * e + KI * integral

    u = sample(y)
    rows = []
    for n in range(ticks):
        if (n + 1) % 10 == 0:
            u = sample(y)
        y += (1.0 - math.exp(-H / TAU)) * (GAIN * u - y)
        rows.append((y, u, samples))
    return rows


def test_a_pi_controller_sampled_at_100_hz_drives_a_plant_at_1_khz_exactly():
    with loop() as w:
        assert (w.get("pi.samples"), w.get("pi.u")) == (1, KP * R + KI * R * PERIOD)  # the tick at t=0
        rows = []
        for _ in range(250):
            w.tick()
            rows.append((w.get("plant.y"), w.get("pi.u"), w.get("pi.samples")))
    assert rows == by_hand(250)
    assert rows[-1][2] == 26 and abs(rows[-1][0] - R) < 0.1  # 26 samples in 0.25 s; the plant near the set point


def test_the_loop_rolls_back_forks_and_runs_isolated_bit_for_bit():
    results = []
    for isolate in (False, True):
        with loop(isolate) as w:
            w.tick(15)
            at15 = w.snapshot().bus.copy()
            w.tick(22)
            at37 = w.snapshot().bus.copy()
            w.backtick(22)  # back over two ticks of the clock (20 ms, 30 ms)
            assert np.array_equal(w.snapshot().bus, at15)
            w.tick(22)
            assert np.array_equal(w.snapshot().bus, at37)
            fork = w.fork()
            fork.tick(13)
            w.tick(13)
            assert np.array_equal(fork.snapshot().bus, w.snapshot().bus)
            fork.close()
            results.append(w.snapshot().bus.copy())
    assert np.array_equal(*results)


class Pulse(Module):
    """Outputs a clock tick (1) at the ticks listed in ``at``, else 0; records a clock input."""

    def __init__(self, name: str, at: tuple[int, ...] = ()):
        super().__init__(name)
        self.at, self.n, self.heard = at, 0, []

    def inputs(self):
        return (Port("heard", unit="clock"),)

    def outputs(self):
        return (Port("tick", unit="clock"),)

    def step(self, t_ns, dt_ns):
        self.heard.append(float(self.inp["heard"]))
        self.out["tick"][...] = 1.0 if self.n in self.at else 0.0
        self.n += 1

    def get_state(self):
        return self.n

    def set_state(self, state):
        self.n = state


def test_a_triggered_input_clock_ticks_when_its_port_reads_other_than_0():
    with loop() as w:
        assert [(p.name, p.unit) for p in w.modules["pi"].inputs()] == [("y", "1"), ("reset", "clock")]
        pulse = Pulse("pulse", at=(24,))
        w.add_module(pulse, connect=[("pulse.tick", "pi.reset")])
        w.tick(20)
        sampled = w.get("pi.integral")  # after the sample at 20 ms
        w.tick(5)  # the reset at the end of tick 24 (25 ms) zeroes the FMU's integral ...
        assert w.get("pi.integral") == sampled  # ... a clocked output of `sample`: the bus holds it till 30 ms
        w.tick(5)
        assert w.get("pi.integral") == (R - w.get("pi.y")) * PERIOD  # one sample since the reset


def test_an_output_clock_ticks_another_fmus_triggered_clock():
    with World(step="1ms") as w:
        w.add_module(make_fmu_module("a", "fmus/conformance/sampled_pi", base_dir=str(ROOT), params={"band": 0.5},
                                     targets=[]))
        w.add_module(make_fmu_module("b", "fmus/conformance/sampled_pi", base_dir=str(ROOT), params={}, targets=[]),
                     connect=[("a.alarm", "b.reset")])
        assert w.get("a.alarm") == 1.0  # the error (1) is outside the band at the tick at t=0
        listener = Pulse("listener")
        w.add_module(listener, connect=[("a.alarm", "listener.heard")])
        w.tick(9)
        w.set("a.y", 0.9)  # inside the band at the sample at 10 ms
        w.tick(10)
        assert w.get("b.integral") == 2 * R * PERIOD and listener.heard == [0.0] * 19
        w.set("a.y", -1.0)  # outside again at 20 ms: a's alarm ticks, and b's integral is reset before b samples
        w.tick()
        assert (w.get("a.alarm"), w.get("b.integral"), listener.heard[-1]) == (1.0, R * PERIOD, 1.0)
        w.tick()
        assert w.get("a.alarm") == 0.0  # 1 only for the step at whose end it ticked


def test_clocks_that_cannot_run_are_refused_naming_them(tmp_path):
    with World(step="1ms") as w:
        w.add_module(make_fmu_module("pi", "fmus/conformance/sampled_pi", base_dir=str(ROOT), params={}, targets=[]))
        with pytest.raises(WiringError, match=r"unit mismatch, pi.u is in '1', pi.reset in 'clock'"):
            w.connect("pi.u", "pi.reset")
    with World(step="1ms") as w, pytest.raises(DynabrainError, match=r"module 'pi': the interval of clock 'sample' "
                                                                      r"is 0.01 s, not a whole number of the "
                                                                      r"module's periods \(0.003 s\)"):
        w.add_module(make_fmu_module("pi", "fmus/conformance/sampled_pi", base_dir=str(ROOT), params={}, targets=[]),
                     period="3ms")
    built = build_fmu(CONFORMANCE / "sampled_pi", 3)
    for edit, why in ((lambda x: x.replace(' intervalDecimal="0.01"', ""), r"clock 'sample' \(constant\) has no "
                                                                           r"period: it declares no intervalDecimal"),
                      (lambda x: x.replace(' hasEventMode="true"', ""), r"clocks \(reset, sample, alarm\) but no "
                                                                        r"event mode")):
        with zipfile.ZipFile(built) as zf:
            xml = zf.read("modelDescription.xml").decode()
            lib = next(n for n in zf.namelist() if n.startswith("binaries/"))
            (tmp_path / "sampled_pi.so").write_bytes(zf.read(lib))
        bad = package_fmu(tmp_path / "bad.fmu", edit(xml), {str(Path(lib).parent): tmp_path / "sampled_pi.so"})
        with pytest.raises(FMUError, match=why):
            make_fmu_module("pi", str(bad), base_dir=".", params={}, targets=[])


def test_a_clocked_fmu_passes_its_check():
    report = check_fmu(str(CONFORMANCE / "sampled_pi"), ticks=30)
    assert report.ok, str(report)
