"""The lock-step hot path (issue 18): `WorldService.step_frame` gives what `do_tick` / `do_read` give,
bit for bit, and hands back anything that is not a one-step call with a current view before ticking;
`frames.state_header` accepts exactly the frames `frames.unpack` and the client's checks accept; the
shared-memory settings reach Zenoh's configuration."""

from __future__ import annotations

import os

import numpy as np
import pytest

from dynabrain.bridge import frames
from dynabrain.bridge import protocol as p
from dynabrain.bridge.calls import WorldService
from dynabrain.bridge.protocol import ProtocolError
from dynabrain.bridge.zenoh_io import Settings, build_config
from dynabrain.orchestrator.scenario import load_world

ARM = os.path.join(os.path.dirname(__file__), "..", "bridge", "arm.yaml")
SIGNALS = ["core.joint_q", "core.joint_qd", "servo.force"]


def service() -> WorldService:
    world = load_world(ARM)
    world.set("servo.target", [0.4, 0.6, -0.9])
    return WorldService(world, instance=7)


def test_step_frame_gives_the_frames_of_the_general_handlers_bit_for_bit():
    fast, slow = service(), service()
    try:
        vf = fast.do_view(p.ViewArgs(signals=SIGNALS))["view"]
        vs = slow.do_view(p.ViewArgs(signals=SIGNALS))["view"]
        assert vf == vs
        for i in range(20):
            if i == 5:  # an input held for the next step: applied by both before their tick
                fast.submit({"servo.target": [0.1, 0.2, 0.3]})
                slow.submit({"servo.target": [0.1, 0.2, 0.3]})
            a = fast.step_frame(p.TickArgs(n=1, view=vf))
            b = slow.do_tick(p.TickArgs(n=1, view=vs))
            assert a == b
            assert fast.step_frame(p.ViewRef(view=vf)) == slow.do_read(p.ViewRef(view=vs))
        assert fast.world.tick_count == slow.world.tick_count == 20
    finally:
        fast.world.close()
        slow.world.close()


def test_step_frame_hands_back_what_is_not_one_step_with_a_current_view_before_ticking():
    svc = service()
    try:
        vid = svc.do_view(p.ViewArgs(signals=SIGNALS))["view"]
        for args in (p.TickArgs(n=2, view=vid), p.TickArgs(n=1), p.TickArgs(n=1, view=vid + 99),
                     p.ViewRef(view=vid + 99)):
            assert svc.step_frame(args) is None
        assert svc.world.tick_count == 0
        svc.world.add_module(_noise())  # a new structure: the view must be resolved again
        assert svc.step_frame(p.TickArgs(n=1, view=vid)) is None
        assert svc.world.tick_count == 0
        svc.do_tick(p.TickArgs(n=1, view=vid))  # the general handler resolves it; then the hot path serves it
        assert svc.step_frame(p.TickArgs(n=1, view=vid)) is not None
        assert svc.world.tick_count == 2
    finally:
        svc.world.close()


def _noise():
    from dynabrain.modules.basic import Noise

    return Noise("noise", n=3, sigma=0.1)


def _good(count: int = 4, view: int = 3, source: int = 7) -> bytes:
    return frames.pack(frames.STATE, np.arange(count, dtype=float), source=source, seq=11, stamp=22, aux=view)


def test_state_header_accepts_exactly_the_expected_state_frame():
    assert frames.state_header(_good(), 3, 4, 7) == (11, 22)
    assert frames.state_header(_good(), 3, 4, None) == (11, 22)
    np.testing.assert_array_equal(frames.values_of(_good(), 4), np.arange(4.0))
    good = _good()
    wrong = {
        "magic": b"XXXX" + good[4:],
        "kind": frames.pack(frames.SHADOW, np.arange(4.0), source=7, aux=3),
        "view": _good(view=4),
        "source": _good(source=8),
        "count": _good(count=5),
        "short": good[:-8],
        "long": good + bytes(8),
        "header only": good[:frames.HEADER_SIZE],
        "empty": b"",
        "declared count": good[:36] + (5).to_bytes(4, "little") + good[40:],
    }
    for what, data in wrong.items():
        assert frames.state_header(data, 3, 4, 7) is None, what
    # what the general path says of those (the client falls back to it): each is refused somewhere
    for what in ("magic", "short", "long", "header only", "empty", "declared count"):
        with pytest.raises(ProtocolError):
            frames.unpack(wrong[what])
    assert frames.state_header(_good(count=0), 3, 0, 7) == (11, 22)
    assert frames.state_header(bytes(frames.HEADER_SIZE + 8 * (frames.MAX_VALUES + 1)), 3,
                               frames.MAX_VALUES + 1, 7) is None


def test_shared_memory_settings_reach_zenoh():
    conf = build_config(Settings(shared_memory=False, shm_threshold=512))
    assert conf.get_json("transport/shared_memory/enabled") == "false"
    assert conf.get_json("transport/shared_memory/transport_optimization/message_size_threshold") == "512"
    default = build_config(Settings())
    assert default.get_json("transport/shared_memory/enabled") in ("true", "false")  # Zenoh's own default
