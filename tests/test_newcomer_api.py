"""What a newcomer types first works or says why (issue 27, item 6): `tick` takes a count or a duration and
refuses a negative count; `with world.lock:` and `world.lock()` both hold the world; `load_world` takes a
shipped example's name; `get` reads a body's fields as expressions do; the public face lists public names
only."""

from __future__ import annotations

import numpy as np
import pytest

import dynabrain.orchestrator as face
from dynabrain.orchestrator import DynabrainError, World, load_world


@pytest.fixture()
def cubes():
    world = load_world("two_cubes")  # a shipped example, by name
    yield world
    world.close()


def test_tick_takes_a_count_or_a_duration(cubes):
    cubes.tick("0.1s")
    cubes.tick(0.1)
    cubes.tick(np.int64(2))
    cubes.tick(0)
    assert cubes.tick_count == 102
    for bad, why in ((-5, "a count is 0 or more"), (0.0013, "not a whole number of the world's 2ms steps"),
                     ("1 parsec", "not a duration"), (True, "expected a tick count or a duration"),
                     (None, "expected a tick count")):
        with pytest.raises(DynabrainError, match=why):
            cubes.tick(bad)
    assert cubes.tick_count == 102


def test_the_lock_is_a_context_manager_and_callable(cubes):
    with cubes.lock:
        cubes.tick(1)
    with cubes.lock():
        cubes.tick(1)
    assert cubes.lock().acquire(blocking=False)
    cubes.lock().release()


def test_get_reads_a_bodys_fields_as_expressions_do(cubes):
    cubes.tick(10)
    pos = cubes.get("aa.pos")
    assert cubes.get("aa.z") == pos[2] and cubes.get("core.aa.x") == pos[0]
    assert cubes.get("aa.speed") == pytest.approx(np.linalg.norm(cubes.get("aa.vel")))
    with pytest.raises(DynabrainError, match=r"'aa\.zz'"):
        cubes.get("aa.zz")


def test_a_missing_name_says_so_and_the_face_is_public():
    with pytest.raises(DynabrainError, match="no_such_scenario"):
        load_world("no_such_scenario")
    assert {"Any", "TYPE_CHECKING", "importlib", "annotations"}.isdisjoint(dir(face))
    assert "World" in dir(face) and "load_world" in dir(face)


def test_the_papers_fig8_in_a_few_lines_with_an_engines_name():
    w = World(core="mujoco")
    w.add_body(name="aa", shape="box", size=["100mm"] * 3, mass="50g", pos=["50mm", "50mm", "600mm"], color="blue")
    w.add_body(name="bb", shape="box", size=["200mm", "200mm", "150mm"], mass="60g", pos=[0, 0, "800mm"],
               color="yellow")
    w.make(["aa", "bb"])
    w.tick("3s")
    assert w.core.name == "core" and "floor" in w.core.objects()
    assert abs(w.get("aa.z") - 0.05) < 0.003 and w.get("bb.z") < 0.3  # on the floor, not through it
    w.close()
    with pytest.raises(DynabrainError, match=r"unknown core 'mujco'.*mujoco"):
        World(core="mujco")
