"""The FMU adapter with real FMUs (compiled from C here, FMI 2.0 and 3.0): ports and parameters
from the model description, each shipped FMU's behaviour, rollback and fork through FMU state,
state slots that do not leak, and the C step helper against the Python path."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from dynabrain.orchestrator.fmu import make_fmu_module
from dynabrain.orchestrator.fmu.check import check_fmu
from dynabrain.orchestrator.fmu.module import FMUModule
from dynabrain.orchestrator.fmu.states import FMUState, SerializedFMUState
from dynabrain.orchestrator.kernel.errors import ForkError, RollbackError
from dynabrain.orchestrator.kernel.module import PortBinding, SetupContext
from dynabrain.orchestrator.kernel.world import World

FMUS = Path(__file__).resolve().parents[1] / "fmus"
VERSIONS = (2, 3)


pytestmark = pytest.mark.usefixtures("fmu_cache")  # FMUs built here go to a cache of this module's own


def fmu(name: str, version: int = 2, module: str | None = None, **params) -> FMUModule:
    return make_fmu_module(module or name, f"{FMUS / name}@fmi{version}", base_dir=".", params=params, targets=[])


def write_fmu(folder: Path, name: str, variables: str, body: str, extra: str = "") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "fmu.yaml").write_text(f"name: {name}\nfmi: [2, 3]\n{extra}variables:\n{variables}")
    (folder / f"{name}.c").write_text('#include <math.h>\n#include "fmu_model.h"\n' + body)
    return folder


@pytest.mark.parametrize("version", VERSIONS)
def test_passthrough_ports_params_and_values(version):
    m = fmu("passthrough", version, gain=2.0)
    assert [(p.name, p.shape, p.view_of) for p in m.inputs()][:2] == [("u", (4,), None), ("u[1]", (), ("u", 0))]
    assert [p.name for p in m.outputs()] == ["y", "y[1]", "y[2]", "y[3]", "y[4]"]
    assert m.param_specs()["gain"].runtime and m.params["gain"] == 2.0
    assert m.CAPABILITIES.can_rollback and m.CAPABILITIES.can_fork and m.CAPABILITIES.feedthrough
    with World(step="1ms") as w:
        w.add_module(m)
        w.add_module(fmu("passthrough", version, module="src"))
        w.connect("src.y[1]", "passthrough.u[3]")  # one element of a vector, by its view ports
        w.set("src.u", [0.5, 0.0, 0.0, 0.0])
        w.set("passthrough.u[1]", 1.0)
        w.tick()
        assert np.array_equal(w.get("passthrough.y"), [2.0, 0.0, 1.0, 0.0])
        w.set("passthrough.gain", -1.0)  # tunable: applied from the next step on
        w.tick()
        assert np.array_equal(w.get("passthrough.y"), [-1.0, 0.0, -0.5, 0.0])


@pytest.mark.parametrize("version", VERSIONS)
def test_servo_pd_torque_limit_and_motor_lag(version):
    with World(step="2ms") as w:
        w.add_module(fmu("servo", version, kp=10.0, kd=2.0, tau_max=3.0, lag=0.01))
        w.set("servo.q_ref", [0.1, 1.0])
        w.set("servo.q", [0.0, 0.0])
        w.set("servo.qd", [0.5, 0.0])
        cmd = np.array([10 * 0.1 - 2 * 0.5, 3.0])  # the second joint saturates at tau_max
        tau = np.zeros(2)
        a = 1 - math.exp(-0.002 / 0.01)
        for _ in range(5):
            w.tick()
            tau = tau + a * (cmd - tau)
            assert np.allclose(w.get("servo.tau"), tau, rtol=0, atol=1e-15)
        w.set("servo.lag", 0.0)  # no lag: the torque is the command at once
        w.tick()
        assert np.array_equal(w.get("servo.tau"), cmd)


@pytest.mark.parametrize("version", VERSIONS)
def test_moving_floor_follows_a_sine_and_ramps_off(version):
    amp, freq = 0.04, 2.0
    with World(step="2ms") as w:
        w.add_module(fmu("moving_floor", version, module="floor", amplitude=amp, frequency=freq, ramp=0.1))
        deps = {s.name: s.depends for s in w.modules["floor"].info.outputs}
        assert deps["position"] == deps["velocity"] == () and deps["force"] is None  # from ModelStructure
        assert w.modules["floor"].CAPABILITIES.feedthrough  # the force depends on q, qd directly
        positions = []
        for k in range(1, 101):
            w.tick()
            positions.append(w.get("floor.position"))
            envelope = min(1.0, k * 0.002 / 0.1)  # eases in over the 0.1 s ramp
            assert w.get("floor.position") == pytest.approx(envelope * amp * math.sin(2 * math.pi * freq * k * 0.002),
                                                            abs=1e-12)
        v_fd = np.gradient(positions, 0.002)
        assert w.get("floor.velocity") == pytest.approx(v_fd[-1], rel=0.02, abs=1e-3)
        w.set("floor.enabled", False)
        w.tick(60)  # 0.12 s: past the 0.1 s ramp
        assert w.get("floor.position") == 0.0 and w.get("floor.velocity") == 0.0
        w.set("floor.q", 0.01)  # the tracking force pulls a displaced slide back
        w.tick()
        assert w.get("floor.force") == pytest.approx(-4000.0 * 0.01)


@pytest.mark.parametrize("version", VERSIONS)
def test_sensor_filter_low_pass_and_seeded_noise_that_rolls_back(version):
    with World(step="2ms") as w:
        w.add_module(fmu("sensor_filter", version, module="clean", cutoff=10.0))
        w.set("clean.u", [1.0, 2.0, 3.0])
        w.tick(10)
        a = 1 - math.exp(-2 * math.pi * 10.0 * 0.002)
        assert np.allclose(w.get("clean.y"), np.array([1.0, 2.0, 3.0]) * (1 - (1 - a) ** 10), atol=1e-12)

    def noisy(seed: int) -> list[np.ndarray]:
        with World(step="2ms") as w:
            w.add_module(fmu("sensor_filter", version, module="s", sigma=0.1, seed=seed))
            out = []
            for _ in range(20):
                w.tick()
                out.append(w.get("s.y"))
            w.backtick(10)
            for i in range(10):
                w.tick()
                assert np.array_equal(w.get("s.y"), out[10 + i])  # the same noise again, bit for bit
            return out

    first, again, other = noisy(1), noisy(1), noisy(2)
    assert all(np.array_equal(a, b) for a, b in zip(first, again, strict=True))
    assert not np.array_equal(first[5], other[5])
    assert 0.05 < np.std(np.concatenate(first)) < 0.2


@pytest.mark.parametrize("version", VERSIONS)
def test_rollback_and_replay_are_bit_exact_through_fmu_states(version):
    with World(step="1ms", history=100) as w:
        w.add_module(fmu("sensor_filter", version, module="s", sigma=0.3, seed=7, cutoff=30.0))
        w.add_module(fmu("moving_floor", version, module="floor"))
        w.add_module(fmu("servo", version))
        w.connect("s.y[1]", "floor.q")
        w.set("s.u", [0.3, -0.2, 0.1])
        w.set("servo.q_ref", [0.5, -0.5])
        w.tick(20)
        first = []
        for _ in range(30):
            w.tick()
            first.append(w.snapshot().bus)
        w.backtick(30)
        for bus in first:
            w.tick()
            assert np.array_equal(w.snapshot().bus, bus)


@pytest.mark.parametrize("version", VERSIONS)
def test_fork_copies_the_fmu_through_its_serialized_state(version):
    with World(step="1ms") as w:
        w.add_module(fmu("sensor_filter", version, module="s", sigma=0.2))
        w.set("s.u", [1.0, 0.0, -1.0])
        w.tick(15)
        plan = w.fork()
        try:
            assert plan.modules["s"]._session is not w.modules["s"]._session
            for _ in range(10):
                w.tick()
                plan.tick()
                assert np.array_equal(w.get("s.y"), plan.get("s.y"))
            plan.set("s.u", [5.0, 5.0, 5.0])  # the copy is independent
            plan.tick(5)
            w.tick(5)
            assert not np.array_equal(w.get("s.y"), plan.get("s.y"))
        finally:
            plan.close()


@pytest.mark.parametrize("version", VERSIONS)
@pytest.mark.parametrize("name", ["passthrough", "servo", "moving_floor", "sensor_filter"])
def test_every_shipped_fmu_passes_check_fmu(name, version):
    report = check_fmu(f"{FMUS / name}@fmi{version}")
    report.assert_ok()
    assert "fork" in report.checked and "step -> restore -> step" in report.checked


def test_state_pickles_as_serialized_bytes_and_restores_into_another_instance():
    import pickle

    with World(step="1ms") as w, World(step="1ms") as v:
        w.add_module(fmu("servo", module="a"))
        v.add_module(fmu("servo", module="a"))
        w.set("a.q_ref", [0.3, 0.1])
        w.tick(7)
        state = w.modules["a"].get_state()
        assert isinstance(state, FMUState)
        blob = pickle.loads(pickle.dumps(state))
        assert isinstance(blob, SerializedFMUState) and len(blob.data) > 16
        v.modules["a"].set_state(blob)
        v.set("a.q_ref", [0.3, 0.1])
        w.tick()
        v.tick()
        assert np.array_equal(w.get("a.tau"), v.get("a.tau"))


def test_history_reuses_state_slots_instead_of_leaking():
    with World(step="1ms", history=10) as w:
        w.add_module(fmu("passthrough"))
        pool = w.modules["passthrough"]._pool
        w.tick(500)
        assert pool.in_use() <= 12  # the ring's 11 states and the current one
        assert len(pool.slots) <= 32
        snap = w.snapshot()  # a snapshot keeps its state alive past the ring
        w.tick(50)
        assert snap.states[0].slot not in pool.free


def test_fmu_without_state_support_refuses_rollback_and_fork(tmp_path):
    folder = write_fmu(tmp_path / "plain", "plain",
                       "  - {name: u, causality: input}\n  - {name: y, causality: output}\n",
                       "int model_init(ModelData *m) { m->y = m->u; return MODEL_OK; }\n"
                       "int model_step(ModelData *m, double h) { m->y += h * m->u; return MODEL_OK; }\n",
                       "capabilities: {get_set_state: false, serialize: false}\n")
    getset = write_fmu(tmp_path / "getset", "getset",
                       "  - {name: u, causality: input}\n  - {name: y, causality: output}\n",
                       "int model_init(ModelData *m) { m->y = m->u; return MODEL_OK; }\n"
                       "int model_step(ModelData *m, double h) { m->y += h * m->u; return MODEL_OK; }\n",
                       "capabilities: {get_set_state: true, serialize: false}\n")
    with World(step="1ms") as w:
        w.add_module(make_fmu_module("p", str(folder), base_dir=".", params={}, targets=[]))
        w.add_module(make_fmu_module("g", str(getset), base_dir=".", params={}, targets=[]))
        w.set("p.u", 1.0)
        w.tick(3)
        assert w.get("p.y") == pytest.approx(0.003)
        with pytest.raises(RollbackError, match=r"module\(s\) p cannot roll back"):
            w.backtick(1)
        with pytest.raises(ForkError, match="p, g cannot fork"):
            w.fork()
        w.remove_module("p")
        w.set("g.u", 2.0)
        w.tick(2)
        w.backtick(2)  # get/set state without serialization: rollback works, fork does not
        assert w.get("g.y") == 0.0


def test_python_step_path_gives_the_same_bits_as_the_c_helper():
    worlds = []
    for python in (False, True):
        w = World(step="1ms")
        w.add_module(fmu("sensor_filter", module="s", sigma=0.5))
        w.add_module(fmu("moving_floor", module="floor"))
        w.add_module(fmu("servo"))
        w.connect("s.y[1]", "floor.q")
        if python:
            for name in ("s", "floor", "servo"):
                m = w.modules[name]
                m._session.stepper.use_python()
                m.bind()
        assert [w.modules[n]._session.stepper.fast for n in ("s", "floor", "servo")] == [not python] * 3
        w.set("s.u", [0.2, 0.4, 0.6])
        w.set("servo.q_ref", [1.0, 2.0])
        worlds.append(w)
    try:
        for _ in range(50):
            for w in worlds:
                w.tick()
            assert np.array_equal(worlds[0].snapshot().bus, worlds[1].snapshot().bus)
        worlds[1].backtick(20)
        worlds[0].backtick(20)
        worlds[0].tick(5)
        worlds[1].tick(5)
        assert np.array_equal(worlds[0].snapshot().bus, worlds[1].snapshot().bus)
    finally:
        for w in worlds:
            w.close()


TYPED_VARS = """\
  - {name: x, causality: input}
  - {name: inc, type: integer, causality: input}
  - {name: hold, type: boolean, causality: input}
  - {name: w, causality: parameter, size: 2, start: [1.0, 2.0]}
  - {name: step_by, type: integer, causality: parameter, start: 1}
  - {name: y, causality: output}
  - {name: count, type: integer, causality: output}
  - {name: odd, type: boolean, causality: output}
"""
TYPED_C = """
int model_init(ModelData *m) { m->count = 0; m->odd = 0; m->y = m->w[0] * m->x; return MODEL_OK; }
int model_step(ModelData *m, double h) {
    (void)h;
    if (!m->hold) m->count += m->inc * m->step_by;
    m->odd = m->count % 2 != 0;
    m->y = m->w[0] * m->x + m->w[1];
    return MODEL_OK;
}
"""


@pytest.mark.parametrize("version", VERSIONS)
def test_integer_and_boolean_ports_and_vector_parameters(tmp_path, version):
    folder = write_fmu(tmp_path / "typed", "typed", TYPED_VARS, TYPED_C)
    m = make_fmu_module("t", f"{folder}@fmi{version}", base_dir=".", params={"w": [3.0, 0.5], "step_by": 3},
                        targets=[])
    assert [p.name for p in m.inputs()] == ["x", "inc", "hold"]  # reals first, then integers, then booleans
    with pytest.raises(Exception, match="expected an integer"):
        make_fmu_module("t", f"{folder}@fmi{version}", base_dir=".", params={"step_by": 1.5}, targets=[])
    with World(step="1ms") as w:
        w.add_module(m)
        w.set("t.x", 2.0)
        w.set("t.inc", 1.0)
        w.tick()
        assert (w.get("t.y"), w.get("t.count"), w.get("t.odd")) == (6.5, 3.0, 1.0)
        w.set("t.hold", 1.0)
        w.tick()
        assert (w.get("t.count"), w.get("t.odd")) == (3.0, 1.0)
        w.set("t.hold", 0.0)
        w.tick()
        assert (w.get("t.count"), w.get("t.odd")) == (6.0, 0.0)
        w.backtick(2)
        assert w.get("t.count") == 3.0


def test_a_fixed_parameter_set_before_the_world_runs_reinitializes_the_fmu():
    with World(step="1ms") as w:
        w.add_module(fmu("sensor_filter", module="s", sigma=1.0, seed=1))
        first = w.get("s.y")
        w.set("s.seed", 2)  # fixed: allowed at tick 0, the FMU is initialized again
        assert not np.array_equal(w.get("s.y"), first)
        w.tick()
        with pytest.raises(Exception, match="cannot be changed at run time"):
            w.set("s.seed", 3)


def test_ports_not_side_by_side_in_memory_go_through_staging_buffers():
    m = fmu("moving_floor", module="floor", amplitude=0.0)
    m.setup(SetupContext("w", 1_000_000, 1_000_000, 0, np.random.default_rng(0)))
    try:
        bus = np.zeros(8)  # side by side, as the world lays ports out: bound in place
        outputs = ("position", "velocity", "force")
        m.bind_ports(PortBinding({"q": bus[0:1].reshape(()), "qd": bus[1:2].reshape(())},
                                 {n: bus[2 + i:3 + i].reshape(()) for i, n in enumerate(outputs)}))
        bus[0] = 0.01
        m.bind()
        assert not m._gather and not m._scatter
        m.start(0)
        assert bus[4] == pytest.approx(-40.0)
        inp = {"q": np.array(0.02), "qd": np.array(0.0)}  # separate arrays: copied in and out each step
        out = {n: np.array(0.0) for n in ("position", "velocity", "force")}
        m.bind_ports(PortBinding(inp, out))
        m.bind()
        assert m._gather and m._scatter
        m.step(0, 1_000_000)
        assert out["force"] == pytest.approx(-80.0) and out["position"] == 0.0
    finally:
        m.close()


def test_unconnected_inputs_read_the_fmus_start_values(tmp_path):
    src = tmp_path / "biased"
    src.mkdir()
    (src / "fmu.yaml").write_text("name: biased\nfmi: [2]\nstep: 0.001\nvariables:\n"
                                  "  - {name: u, causality: input, start: 1.5}\n"
                                  "  - {name: y, causality: output}\n")
    (src / "biased.c").write_text('#include "fmu_model.h"\n'
                                  "int model_init(ModelData *m) { m->y = m->u; return MODEL_OK; }\n"
                                  "int model_step(ModelData *m, double h) { (void)h; m->y = 2 * m->u; "
                                  "return MODEL_OK; }\n")
    with World(step="1ms") as w:
        w.add_module(make_fmu_module("b", str(src), base_dir=str(tmp_path), params={}, targets=[]))
        assert w.get("b.u") == 1.5  # the bus slot starts at the FMU's start value
        w.tick()
        assert w.get("b.y") == 3.0
