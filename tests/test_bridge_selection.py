"""The bridge's ``make`` call takes ``others`` (issue 18, target 3): a brain selects objects with the others
absent over a real Zenoh session on loopback, and a bad mode or an unknown object gets a clear error reply,
the world left as it was."""

from __future__ import annotations

import pytest

from dynabrain.bridge.errors import BadRequestError, WorldRefusedError
from dynabrain.bridge.testing import serving
from dynabrain.orchestrator.scenario import load_world

SCENE = """\
name: pick
world: {step: 2ms, core: mujoco}
scene:
  - plane: {name: floor}
  - box: {name: low, size: [0.2, 0.2, 0.2], pos: [0, 0, 0.1], mass: 1}
  - box: {name: drop, size: [0.1, 0.1, 0.1], pos: [0, 0, 0.45], mass: 0.2}
"""


def test_a_brain_makes_the_others_absent_and_bad_input_changes_nothing(tmp_path):
    path = tmp_path / "pick.yaml"
    path.write_text(SCENE)
    world = load_world(path)
    with serving(world, "pick") as (_server, brain):
        brain.tick(3)
        snap = world.snapshot()
        for call, error, words in [
                (lambda: brain.make(["drop"], others="gone"), BadRequestError, "others"),
                (lambda: brain.call("make", objects=["drop"], others=3), BadRequestError, "others"),
                (lambda: brain.make(["ghost"], others="absent"), WorldRefusedError, "ghost")]:
            with pytest.raises(error) as err:
                call()
            assert words in str(err.value), str(err.value)
        now = world.snapshot()
        assert now.tick == snap.tick and now.bus.tobytes() == snap.bus.tobytes()
        assert world.core.absent == ()
        assert brain.make(["floor", "drop"], others="absent") == ["floor", "drop"]
        assert world.core.absent == ("low",)
        brain.tick(150)
        assert world.get("drop.pos")[2] < 0.2  # through where the low box stood
        assert brain.make(["floor", "drop", "low"]) == ["floor", "low", "drop"] and world.core.absent == ()
