"""Gymnasium environments over any World: learning in the embedded simulator.

    from dynabrain.orchestrator.brain.gym import WorldEnv, WorldVectorEnv

    world = load_world("scenarios/swing.yaml")
    world.remove_module("pump")                       # the agent drives the legs instead
    env = WorldEnv(world,
                   observe=["core.swing_pivot.q", "core.swing_pivot.qd"],       # or {name: (low, high)}
                   act={"servo.l_hip_pitch.q_ref": (-1.5, 1.5), "servo.l_knee.q_ref": (-1.5, 0)},
                   reward=lambda obs, action: abs(float(obs["core.swing_pivot.q"])),
                   ticks_per_step=10, max_steps=800)
    obs, info = env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())

**Spaces.** An observation is a dict of named signals (any port of the world, ``core.<body>.pos``...),
an action a dict of named input ports (ports no connection drives), each a float64 `Box` with the
port's shape: `spaces.Dict` both. Action bounds are given per port, ``(low, high)`` (numbers or arrays
of the port's shape); observation bounds default to -inf, inf. Names, shapes and bounds are checked
when the env is made (`SpaceError`, naming the port and the closest names).

**A step** holds the action on its ports for ``ticks_per_step`` ticks (`World.run`), then observes.
``reward(obs, action) -> float`` and ``terminated(obs, action) -> bool`` are the user's functions of
the new observation and the action; the episode is truncated after ``max_steps`` steps. A step whose
physics fails (`ModuleError` from `World.run`: a diverging physics, a module that raises) ends the
episode: terminated, the observation of the state the world rolled back to, the reward
``failure_reward`` (or ``reward(obs, action)`` when that is None), and ``info["error"]`` (the reason)
and ``info["failed_tick"]``. An ended episode needs `reset` before the next step.

**Actions out of the space are refused, never clipped silently** (Gymnasium leaves it to the
environment; clipping without saying so hides a bug in the agent): `step` raises `SpaceError` (a
ValueError) naming the port, the value and the bounds. To clip, say so: `clip_actions(env)` wraps
the env in Gymnasium's `TransformAction` with an unbounded action space and clips each port to its
bounds, as `gymnasium.wrappers.ClipAction` does for a `Box` space (it takes no `Dict`).

**Reset** restores a snapshot with `World.import_state`: the world's state when the env was made, or
the ``start`` bytes given (`World.export_state`); ``seed`` seeds ``self.np_random``, and an optional
``on_reset(world, rng)`` hook may then change the world (randomise a parameter: ``world.set(...)``).

`WorldVectorEnv` runs ``num_envs`` copies of the same task through a `Batch` (serial, processes, Ray):
each step runs every live copy ``ticks_per_step`` ticks from its own state as one batch. It follows
Gymnasium 1.x's next-step autoreset (``metadata["autoreset_mode"] = AutoresetMode.NEXT_STEP``): the
step after a copy's episode ended resets that copy instead of stepping it (its action is ignored,
reward 0, not terminated or truncated, the reset observation), exactly as `gymnasium.vector.SyncVectorEnv`
of `WorldEnv` copies does; a copy's trajectory is bit-identical to the single env's for the same actions.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import gymnasium
import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from ..kernel.errors import DynabrainError, ModuleError
from ..kernel.suggest import did_you_mean
from ..kernel.world import World
from .batch import Batch

Obs = dict[str, np.ndarray]
Action = dict[str, np.ndarray]
Bounds = tuple[Any, Any]
Reward = Callable[[Obs, Action], float]
Terminated = Callable[[Obs, Action], bool]
OnReset = Callable[[World, np.random.Generator], None]


class SpaceError(DynabrainError, ValueError):
    """An observation or action the env cannot make (unknown name, bad bounds), or an action outside its space."""


@dataclass(frozen=True)
class Task:
    """What an env observes and drives, and how it scores a step: shared by `WorldEnv` and `WorldVectorEnv`.
    ``ports`` maps an action's key (the name given) to the input port's full name."""

    signals: tuple[str, ...]
    ports: dict[str, str]
    observation_space: spaces.Dict
    action_space: spaces.Dict
    ticks_per_step: int
    max_steps: int | None
    reward: Reward
    terminated: Terminated | None
    failure_reward: float | None
    on_reset: OnReset | None

    def observe(self, world: World) -> Obs:
        """The observed signals of ``world`` now (new arrays)."""
        return {name: np.array(world.get(name), dtype=np.float64) for name in self.signals}

    def check_action(self, action: Any, copy: int | None = None) -> Action:
        """``action`` as arrays of the ports' shapes; `SpaceError` when it is not in the action space."""
        where = "" if copy is None else f" (copy {copy})"
        if not isinstance(action, Mapping):
            raise SpaceError(f"an action is a dict of input ports {list(self.ports)}, "
                             f"got {type(action).__name__}{where}")
        unknown = [k for k in action if k not in self.ports]
        if unknown:
            raise SpaceError(f"the action has no port {unknown[0]!r}{where}" + did_you_mean(str(unknown[0]), self.ports)
                             + f"; its ports: {', '.join(self.ports)}")
        out = {}
        for key, box in self.action_space.items():
            if key not in action:
                raise SpaceError(f"the action lacks a value for port {key!r}{where}")
            try:
                value = np.asarray(action[key], dtype=np.float64)
            except (TypeError, ValueError):
                raise SpaceError(f"action {key}{where}: expected numbers, got {action[key]!r}") from None
            if value.shape != box.shape:
                raise SpaceError(f"action {key}{where} has shape {value.shape}; the port's shape is {box.shape}")
            if not np.all((value >= box.low) & (value <= box.high)):
                raise SpaceError(
                    f"action {key}{where} = {_short(value)} is outside the action space [{_short(box.low)}, "
                    f"{_short(box.high)}]: the env refuses it rather than clip it silently; clip in the agent or "
                    "wrap the env with dynabrain.orchestrator.brain.gym.clip_actions (Gymnasium's ClipAction "
                    "takes Box spaces only)")
            out[key] = value
        return out

    def inputs(self, action: Action) -> dict[str, np.ndarray]:
        """`World.run` inputs that hold ``action`` for one step."""
        return {self.ports[k]: np.broadcast_to(v, (self.ticks_per_step, *v.shape)) for k, v in action.items()}

    def score(self, obs: Obs, action: Action, steps: int, error: str | None,
              failed_tick: int | None) -> tuple[float, bool, bool, dict[str, Any]]:
        """Reward, terminated, truncated and info of a step that was the episode's ``steps``-th."""
        if error is not None:
            reward = self.failure_reward if self.failure_reward is not None else self.reward(obs, action)
            return float(reward), True, self._truncated(steps), {"error": error, "failed_tick": failed_tick}
        done = bool(self.terminated(obs, action)) if self.terminated is not None else False
        return float(self.reward(obs, action)), done, self._truncated(steps), {}

    def _truncated(self, steps: int) -> bool:
        return self.max_steps is not None and steps >= self.max_steps


def make_task(world: World, *, observe: Sequence[str] | Mapping[str, Bounds | None], act: Mapping[str, Bounds],
              reward: Reward, terminated: Terminated | None = None, ticks_per_step: int = 1,
              max_steps: int | None = None, failure_reward: float | None = None,
              on_reset: OnReset | None = None) -> Task:
    """Check the names, shapes and bounds against ``world`` and make the spaces (see the module docstring)."""
    if isinstance(observe, str) or not isinstance(observe, (Sequence, Mapping)) or not observe:
        raise SpaceError("observe: give a list of signal names, or a dict of signal name -> (low, high) or None")
    if not isinstance(act, Mapping) or not act:
        raise SpaceError("act: give a dict of input port -> (low, high)")
    if isinstance(ticks_per_step, bool) or not isinstance(ticks_per_step, (int, np.integer)) or ticks_per_step < 1:
        raise SpaceError(f"ticks_per_step must be a positive integer, got {ticks_per_step!r}")
    if max_steps is not None and (isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer))
                                  or max_steps < 1):
        raise SpaceError(f"max_steps must be a positive integer or None, got {max_steps!r}")
    for what, fn in (("reward", reward), ("terminated", terminated), ("on_reset", on_reset)):
        if fn is not None and not callable(fn):
            raise SpaceError(f"{what} must be a function, got {type(fn).__name__}")
    if reward is None:
        raise SpaceError("reward: give a function reward(obs, action) -> float")
    bounds = dict(observe) if isinstance(observe, Mapping) else dict.fromkeys(observe)
    signals = set(world.signals)
    core = world.core.name if world.core is not None else None
    obs_boxes = {}
    for name, given in bounds.items():
        if name not in signals and f"{core}.{name}" not in signals:
            raise SpaceError(f"observe: no signal {name!r}" + did_you_mean(name, signals))
        obs_boxes[name] = _box(f"observe[{name!r}]", np.shape(world.get(name)), given, unbounded=True)
    act_boxes, ports = {}, {}
    for name, given in act.items():
        try:
            full = world.settable(name)
        except DynabrainError as exc:
            raise SpaceError(f"act: {exc}") from None
        if not isinstance(full, str):
            raise SpaceError(f"act: {name!r} is a parameter; actions are input ports (set a parameter in on_reset, "
                             "or give one value per branch to a Batch)")
        if full in ports.values():
            raise SpaceError(f"act: port {full} is named twice")
        ports[name] = full
        act_boxes[name] = _box(f"act[{name!r}]", np.shape(world.get(full)), given, unbounded=False)
    return Task(tuple(bounds), ports, spaces.Dict(obs_boxes), spaces.Dict(act_boxes), int(ticks_per_step),
                None if max_steps is None else int(max_steps), reward, terminated,
                None if failure_reward is None else float(failure_reward), on_reset)


def _box(what: str, shape: tuple[int, ...], given: Bounds | None, unbounded: bool) -> spaces.Box:
    if given is None:
        if not unbounded:
            raise SpaceError(f"{what}: an action port needs its bounds (low, high)")
        return spaces.Box(-np.inf, np.inf, shape, np.float64)
    if isinstance(given, (str, bytes)) or not isinstance(given, Sequence) or len(given) != 2:
        raise SpaceError(f"{what}: bounds are a pair (low, high), got {given!r}")
    try:
        low, high = (np.broadcast_to(np.asarray(b, dtype=np.float64), shape).copy() for b in given)
    except (TypeError, ValueError):
        raise SpaceError(f"{what}: bounds {given!r} are not numbers of the port's shape {shape}") from None
    if np.any(np.isnan(low)) or np.any(np.isnan(high)) or np.any(low > high):
        raise SpaceError(f"{what}: bounds {given!r} need low <= high (and no NaN)")
    return spaces.Box(low, high, shape, np.float64)


def _short(value: np.ndarray) -> str:
    return np.array2string(np.asarray(value), precision=6, threshold=8)


def clip_actions(env: gymnasium.Env) -> gymnasium.Env:
    """``env`` taking any action and clipping each port to its bounds (Gymnasium's `TransformAction`
    with an unbounded `Dict` action space: what `gymnasium.wrappers.ClipAction` does for a `Box`)."""
    space = env.action_space
    if not isinstance(space, spaces.Dict) or not all(isinstance(b, spaces.Box) for b in space.values()):
        raise SpaceError("clip_actions takes an env whose action space is a Dict of Box spaces")
    wide = spaces.Dict({k: spaces.Box(-np.inf, np.inf, b.shape, b.dtype) for k, b in space.items()})

    def clip(action: Mapping[str, Any]) -> Action:
        return {k: np.clip(np.asarray(action[k], dtype=np.float64), b.low, b.high) for k, b in space.items()}

    return gymnasium.wrappers.TransformAction(env, clip, wide)


class WorldEnv(gymnasium.Env):
    """A Gymnasium environment over ``world`` (see the module docstring). The env drives the world it is
    given (steps it, imports states into it) and leaves it open at `close`: the caller owns it.

    ``start``: the state every episode begins from (`World.export_state` bytes); the world's state now
    when None. The keyword arguments are `make_task`'s.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(self, world: World, *, observe: Sequence[str] | Mapping[str, Bounds | None],
                 act: Mapping[str, Bounds], reward: Reward, terminated: Terminated | None = None,
                 ticks_per_step: int = 1, max_steps: int | None = None, failure_reward: float | None = None,
                 on_reset: OnReset | None = None, start: bytes | None = None):
        self.world = world
        self.task = make_task(world, observe=observe, act=act, reward=reward, terminated=terminated,
                              ticks_per_step=ticks_per_step, max_steps=max_steps, failure_reward=failure_reward,
                              on_reset=on_reset)
        self.start = _start_bytes(world, start)
        self.observation_space = self.task.observation_space
        self.action_space = self.task.action_space
        self._steps = 0
        self._ended: str | None = "step() before reset(): call reset() first"

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Obs, dict[str, Any]]:
        super().reset(seed=seed)
        _no_options(options)
        self.world.import_state(self.start)
        if self.task.on_reset is not None:
            self.task.on_reset(self.world, self.np_random)
        self._steps, self._ended = 0, None
        return self.task.observe(self.world), {}

    def step(self, action: Mapping[str, Any]) -> tuple[Obs, float, bool, bool, dict[str, Any]]:
        if self._ended is not None:
            raise DynabrainError(f"WorldEnv.step: {self._ended}")
        checked = self.task.check_action(action)
        error, failed_tick = None, None
        try:
            self.world.run(self.task.ticks_per_step, inputs=self.task.inputs(checked))
        except ModuleError as err:  # the world rolled back to the start of the failed tick
            error, failed_tick = str(err), err.tick
        self._steps += 1
        obs = self.task.observe(self.world)
        reward, terminated, truncated, info = self.task.score(obs, checked, self._steps, error, failed_tick)
        if terminated or truncated:
            self._ended = "the episode has ended (terminated or truncated): call reset()"
        return obs, reward, terminated, truncated, info


class WorldVectorEnv(VectorEnv):
    """``num_envs`` copies of one task on ``world``, stepped together through a `Batch` on ``backend``
    (``workers``, ``build``: the batch's). Next-step autoreset (see the module docstring). ``world`` is
    only read (its state exported) and stays the caller's; `close` stops the batch's workers.
    """

    metadata: ClassVar[dict[str, Any]] = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": []}

    def __init__(self, world: World, num_envs: int, *, observe: Sequence[str] | Mapping[str, Bounds | None],
                 act: Mapping[str, Bounds], reward: Reward, terminated: Terminated | None = None,
                 ticks_per_step: int = 1, max_steps: int | None = None, failure_reward: float | None = None,
                 on_reset: OnReset | None = None, start: bytes | None = None, backend: str = "serial",
                 workers: int | None = None, build: Callable[[], World] | None = None):
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise SpaceError(f"num_envs must be a positive integer, got {num_envs!r}")
        self.task = make_task(world, observe=observe, act=act, reward=reward, terminated=terminated,
                              ticks_per_step=ticks_per_step, max_steps=max_steps, failure_reward=failure_reward,
                              on_reset=on_reset)
        self.start = _start_bytes(world, start)
        self.num_envs = int(num_envs)
        self.single_observation_space = self.task.observation_space
        self.single_action_space = self.task.action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.batch = Batch(world, backend=backend, workers=workers, build=build)
        self._scratch = world.fork(world.name)  # where a copy is reset and a failed copy observed
        self._rngs: list[np.random.Generator | None] = [None] * self.num_envs
        self._states: list[bytes | None] = [None] * self.num_envs
        self._obs: list[Obs] = []
        self._steps = np.zeros(self.num_envs, dtype=np.int64)
        self._autoreset = np.zeros(self.num_envs, dtype=np.bool_)
        self._fresh: tuple[bytes, Obs] | None = None  # the start's state and observation (no on_reset hook)

    def reset(self, *, seed: int | Sequence[int | None] | None = None,
              options: dict[str, Any] | None = None) -> tuple[Obs, dict[str, Any]]:
        _no_options(options)
        if seed is None or isinstance(seed, (int, np.integer)):
            if seed is not None:
                self._np_random, self._np_random_seed = seeding.np_random(int(seed))
            seeds = [None if seed is None else int(seed) + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"{len(seeds)} seeds for {self.num_envs} copies")
        for i, s in enumerate(seeds):
            if s is not None or self._rngs[i] is None:
                self._rngs[i] = seeding.np_random(s)[0]
        self._obs = [self._reset_copy(i) for i in range(self.num_envs)]
        self._steps[:] = 0
        self._autoreset[:] = False
        return self._stack(self._obs), {}

    def _reset_copy(self, i: int) -> Obs:
        if self.task.on_reset is None:
            if self._fresh is None:
                self._scratch.import_state(self.start)
                self._fresh = (self.start, self.task.observe(self._scratch))
            self._states[i] = self._fresh[0]
            return {k: v.copy() for k, v in self._fresh[1].items()}
        self._scratch.import_state(self.start)
        self.task.on_reset(self._scratch, self._rngs[i])
        self._states[i] = self._scratch.export_state()
        return self.task.observe(self._scratch)

    def step(self, actions: Mapping[str, Any]) -> tuple[Obs, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        if not self._obs:
            raise DynabrainError("WorldVectorEnv.step before reset(): call reset() first")
        live = [i for i in range(self.num_envs) if not self._autoreset[i]]
        checked = self._check_actions(actions, live)
        rewards = np.zeros(self.num_envs, dtype=np.float64)
        terminated = np.zeros(self.num_envs, dtype=np.bool_)
        truncated = np.zeros(self.num_envs, dtype=np.bool_)
        infos: dict[str, Any] = {}
        for i in np.flatnonzero(self._autoreset):
            self._obs[i] = self._reset_copy(int(i))
            self._steps[i] = 0
        if live:
            result = self.batch.run(
                self.task.ticks_per_step, starts=[self._states[i] for i in live],
                inputs={self.task.ports[k]: np.stack([np.broadcast_to(checked[i][k], (self.task.ticks_per_step,
                                                                                         *box.shape)) for i in live])
                        for k, box in self.single_action_space.items()},
                record=self.task.signals)
            for row, i in enumerate(live):
                status, state = result.status[row], result.states[row]
                if status.ok:
                    obs = {name: np.array(result.signals[name][row, -1]) for name in self.task.signals}
                elif state is not None:  # the state its failure rolled back to
                    self._scratch.import_state(state)
                    obs = self.task.observe(self._scratch)
                else:  # its worker died: the copy ends where it was
                    obs = self._obs[i]
                self._states[i] = state
                self._steps[i] += 1
                self._obs[i] = obs
                rewards[i], terminated[i], truncated[i], info = self.task.score(
                    obs, checked[i], int(self._steps[i]), None if status.ok else status.reason, status.failed_tick)
                infos = self._add_info(infos, info, i)
        self._autoreset = terminated | truncated
        return self._stack(self._obs), rewards, terminated, truncated, infos

    def _check_actions(self, actions: Any, live: list[int]) -> dict[int, Action]:
        if not isinstance(actions, Mapping):
            raise SpaceError(f"actions are a dict of input ports {list(self.task.ports)}, each with one row per copy, "
                             f"got {type(actions).__name__}")
        rows = {}
        for k, v in actions.items():
            arr = np.asarray(v, dtype=np.float64) if k in self.task.ports else v
            if k in self.task.ports and (arr.ndim == 0 or arr.shape[0] != self.num_envs):
                raise SpaceError(f"actions[{k!r}] has shape {np.shape(arr)}; {self.num_envs} copies of a port of "
                                 f"shape {self.single_action_space[k].shape} need "
                                 f"{(self.num_envs, *self.single_action_space[k].shape)}")
            rows[k] = arr
        return {i: self.task.check_action({k: (v[i] if k in self.task.ports else v) for k, v in rows.items()}, i)
                for i in live}

    def _stack(self, obs: list[Obs]) -> Obs:
        return {name: np.stack([o[name] for o in obs]) for name in self.task.signals}

    def close_extras(self, **kwargs: Any) -> None:
        self.batch.close()
        self._scratch.close()


def _start_bytes(world: World, start: bytes | None) -> bytes:
    if start is None:
        return world.export_state()
    if not isinstance(start, (bytes, bytearray)):
        raise SpaceError(f"start is World.export_state() bytes, got {type(start).__name__}")
    world.check_state(bytes(start))
    return bytes(start)


def _no_options(options: dict[str, Any] | None) -> None:
    if options:
        raise ValueError(f"reset takes no options here, got {sorted(options)}")
