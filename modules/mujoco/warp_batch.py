"""The MJWarp physics for the lockstep backend: the MuJoCo cores of N branches stepped one tick together on
`mujoco_warp` (MuJoCo's physics written in NVIDIA Warp), one warp world per branch.

Warp runs the same kernels on its CPU device (compiled to native code by LLVM on first use: about 20 s
on two cores for a small model, then read from warp's kernel cache) and on a CUDA GPU when one is there.
Nothing here needs a GPU: the device is ``"cpu"`` unless ``DYNABRAIN_WARP_DEVICE`` (or `WarpWorlds`'s
``device``) names another. The kernel cache is ``DYNABRAIN_WARP_CACHE`` or a folder under the system's
temporary folder, so that test runs and benches compile once.

A tick of the cores (`step_cores`, the warp counterpart of `batched.step_cores`):

1. each core's inputs are copied into its own MjData, as its `MujocoCore.step` copies them;
2. the state of the N datas (qpos, qvel, act, ctrl, applied forces, mocap, time, the solver's warm
   start) is stacked and put on the device, and `mujoco_warp.step` is called the core's substeps times
   for all N worlds at once;
3. the new state comes back into each MjData (with the sensor values warp computed in its last step:
   those of the acceleration stage), and MuJoCo's C `mj_step1` makes the positions, velocities and
   sensors the core's outputs read, as the core's own step ends.

Not bit for bit MuJoCo's C: warp computes in float32 and solves in its own order. `tests/test_mjwarp.py`
measures the gap against C (`TOLERANCE`); run to run on the CPU device it is deterministic (bit equal).
A world whose state is not finite after the step fails alone with `PhysicsDivergedError`; the others go on.

Branches with parameters of their own: warp's model holds one value per world of many fields (masses,
frictions, gains, damping: those `mujoco_warp` marks batched); the model most cores share is put on the
device, and the fields in which another core's model differs from it hold each world's own value. A
core whose model differs in anything else (an option such as gravity, a field warp shares among its
worlds) steps with its own C `step`, alone, before the rest; so do an animated robot's core and one
whose velocity input holds a value (Python between the halves of its step, as in `batched.step_cores`).
Warp's own switches derived from values (e.g. whether any tendon is stiff) are the shared model's.
"""

from __future__ import annotations

import copy
import functools
import os
import tempfile
import threading
import warnings
from collections import Counter
from collections.abc import Sequence
from typing import Any

import mujoco
import numpy as np

from dynabrain.orchestrator.kernel.errors import DynabrainError, PhysicsDivergedError

from . import batched

TOLERANCE = {"qpos_m": 1e-3, "qvel_m_s": 1e-2}
"""The largest gap accepted between warp (CPU device) and MuJoCo's C over runs of up to a second of 2 ms
ticks, contacts included (`tests/test_mjwarp.py` checks it over 200 ticks). Measured: at most 3e-7 m and
4e-6 m/s on the test's small model (a box dropped onto the floor, a double pendulum driven by a motor),
3e-6 m on the two cubes, 2.1e-4 m on the humanoid's pelvis with its servos over 500 ticks
(bench/mjwarp.py): warp's float32 and its solver's own order of sums. Over longer runs a chaotic contact
(a box sliding off another's corner) grows the gap like any change of rounding: decimetres after 5 s of
the two cubes. See bench/README.md."""

_IN = ("qpos", "qvel", "act", "ctrl", "qfrc_applied", "xfrc_applied", "mocap_pos", "mocap_quat", "qacc_warmstart")
"""The fields of an MjData that make a world's next step (besides time)."""
_OUT = ("qpos", "qvel", "act", "qacc_warmstart", "qacc", "sensordata")
"""The fields that come back from warp after a step (besides time); `mj_step1` makes the rest."""
STEPPED = Counter()
"""World-ticks stepped: ``STEPPED["warp"]`` on MJWarp, ``STEPPED["c"]`` on C instead (a core that cannot
share the warp model, or a model warp refuses): tests and benches read it to know what ran."""
_LOCK = threading.Lock()
_REFUSED: dict[int, tuple[mujoco.MjModel, str]] = {}  # id of an MjModel warp refused -> (it, why)
_WORLDS: dict[tuple, WarpWorlds] = {}  # (ids of a model and its core's params, worlds, device, fields) -> them
_DIFFERING: dict[tuple[int, ...], tuple[tuple, frozenset[str] | None]] = {}  # `_differing`


@functools.cache
def _warp() -> tuple[Any, Any]:
    """Warp and mujoco_warp, imported and initialised once (the kernel cache set first), or a
    `DynabrainError` that says why they cannot be used here."""
    try:
        import warp as wp
    except ImportError as exc:
        raise DynabrainError(f"modules.mujoco.warp_batch: warp-lang is not installed ({exc}); "
                             "pip install 'dynabrain[warp]'") from exc
    wp.config.kernel_cache_dir = cache_dir()
    wp.config.log_level = wp.LOG_WARNING  # not a line per kernel module loaded
    wp.init()
    try:
        import mujoco_warp as mjw
    except ImportError as exc:
        raise DynabrainError(f"modules.mujoco.warp_batch: mujoco-warp is not installed ({exc}); "
                             "pip install 'dynabrain[warp]'") from exc
    return wp, mjw


def cache_dir() -> str:
    """Where warp keeps its compiled kernels: ``DYNABRAIN_WARP_CACHE``, or a folder of the system's
    temporary folder (shared by every run of this user)."""
    given = os.environ.get("DYNABRAIN_WARP_CACHE", "").strip()
    user = os.getuid() if hasattr(os, "getuid") else "user"
    return given or os.path.join(tempfile.gettempdir(), f"dynabrain-warp-kernels-{user}")


def default_device() -> str:
    """The warp device the cores step on: ``DYNABRAIN_WARP_DEVICE`` or ``"cpu"`` (never a GPU unasked)."""
    return os.environ.get("DYNABRAIN_WARP_DEVICE", "").strip() or "cpu"


@functools.cache
def unavailable() -> str | None:
    """Why MJWarp cannot step here (not installed, warp fails to start), or None when it can (asked once)."""
    try:
        _warp()
    except Exception as exc:  # any failure to import or initialise is the answer
        return str(exc)
    return None


class WarpWorlds:
    """``worlds`` copies of one MjModel on a warp device: their state put from MjDatas, stepped together,
    and taken back into them."""

    def __init__(self, model: mujoco.MjModel, worlds: int, device: str | None = None,
                 per_world: frozenset[str] = frozenset(), params: Any = None):
        """``per_world``: the model's fields that hold a value per world (`set_models` fills them), the
        others are ``model``'s for every world; ``params``: the values its core wrote ``model`` from
        (`worlds_for`)."""
        wp, mjw = _warp()
        self.model, self.worlds, self.per_world, self.params = model, worlds, per_world, params
        self.device = device or default_device()
        self.models_key: tuple = ()
        taken = copy.copy(model)  # warp refuses MuJoCo's auto-reset flag (the core sets it): divergence is ours
        taken.opt.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_AUTORESET)
        try:
            with wp.ScopedDevice(self.device):
                self.wmodel = mjw.put_model(taken, batch_sizes={name: worlds for name in per_world})
                self.wdata = mjw.make_data(model, nworld=worlds)
        except Exception as exc:  # warp refuses the model (a feature it lacks) or the device
            raise DynabrainError(f"modules.mujoco.warp_batch: MJWarp cannot take this model on device "
                                 f"{self.device!r}: {exc}") from exc
        self._wp, self._mjw = wp, mjw

    def set_models(self, models: Sequence[mujoco.MjModel], key: tuple = ()) -> None:
        """Each world's values of the `per_world` fields from its own model (``models``: one per world, all
        of ``model``'s structure); ``key`` says which models they are: the same key again copies nothing."""
        if key and key == self.models_key:
            return
        for name in self.per_world:
            target = getattr(self.wmodel, name)
            values = np.stack([np.asarray(getattr(m, name)) for m in models])
            target.assign(values.reshape(target.shape + getattr(target.dtype, "_shape_", ())))
        self.models_key = key

    def put(self, datas: Sequence[mujoco.MjData]) -> None:
        """The state of ``datas`` (one per world, in order) onto the device."""
        for name in _IN:
            target = getattr(self.wdata, name)
            if target.size:
                target.assign(np.stack([getattr(d, name) for d in datas]).astype(np.float32))
        self.wdata.time.assign(np.array([d.time for d in datas], dtype=np.float32))
        if self.wdata.eq_active.size:  # equality constraints switched on or off at run time (a made joint)
            self.wdata.eq_active.assign(np.stack([d.eq_active for d in datas]).astype(bool))

    def step(self, substeps: int = 1) -> None:
        """Every world ``substeps`` MuJoCo steps (`mujoco_warp.step`), waiting for the device to finish."""
        with self._wp.ScopedDevice(self.device):
            for _ in range(substeps):
                self._mjw.step(self.wmodel, self.wdata)
        self._wp.synchronize_device(self.device)

    def take(self, datas: Sequence[mujoco.MjData], substeps: int = 1) -> np.ndarray:
        """The device's state back into ``datas`` (stepped ``substeps`` since `put`: their time is counted
        here in float64, as MuJoCo's C counts it, not read back in warp's float32); returns, per world,
        whether its state is finite."""
        finite = np.ones(len(datas), dtype=bool)
        for name in _OUT:
            source = getattr(self.wdata, name)
            if not source.size:
                continue
            values = source.numpy().astype(np.float64)
            if name in ("qpos", "qvel"):
                finite &= np.isfinite(values.reshape(len(datas), -1)).all(axis=1)
            for d, row in zip(datas, values, strict=True):
                getattr(d, name)[:] = row.reshape(getattr(d, name).shape)
        timestep = self.model.opt.timestep
        for d in datas:
            for _ in range(substeps):
                d.time += timestep
        return finite


def worlds_for(model: mujoco.MjModel, worlds: int, device: str | None = None, params: Any = None,
               per_world: frozenset[str] = frozenset()) -> WarpWorlds:
    """The warp worlds of ``model`` for ``worlds`` branches, ``per_world`` fields their own (made once, kept
    while ``params``, the values its core wrote the model from, are the same object: a core writes its
    model only from its parameters, and a change of them is a new object)."""
    device = device or default_device()
    key = (id(model), id(params), worlds, device, per_world)
    with _LOCK:
        held = _WORLDS.get(key)
        if held is not None and held.model is model and held.params is params:
            return held
        if len(_WORLDS) >= 16:
            _WORLDS.clear()
        made = _WORLDS[key] = WarpWorlds(model, worlds, device, per_world, params)
        return made


@functools.cache
def _array_fields() -> tuple[tuple[str, ...], frozenset[str]]:
    """(the names of MjModel's arrays, those of them warp can hold one value per world of)."""
    import dataclasses

    from mujoco_warp._src import types, warp_util

    probe = mujoco.MjModel.from_xml_string("<mujoco/>")
    names = tuple(n for n in dir(probe) if not n.startswith("_") and isinstance(getattr(probe, n), np.ndarray))
    per_world = frozenset(f.name for f in dataclasses.fields(types.Model)
                          if warp_util.is_array_spec(f.type) and getattr(f.type, "shape", ())[:1] == ("*",))
    return names, per_world & set(names)


def _differing(base: mujoco.MjModel, base_params: Any, other: mujoco.MjModel, params: Any) -> frozenset[str] | None:
    """The fields in which ``other`` differs from ``base``, when warp can hold each per world; None when
    they differ in anything else (their options, their structure, a field warp shares). Kept while the
    params they were written from are the same objects (`worlds_for`)."""
    if other is base:
        return frozenset()
    key = (id(base), id(base_params), id(other), id(params))
    held = _DIFFERING.get(key)
    if held is not None and all(a is b for a, b in zip(held[0], (base, base_params, other, params), strict=True)):
        return held[1]
    names, per_world = _array_fields()
    found: frozenset[str] | None = None
    if str(base.opt) == str(other.opt):
        differ = {n for n in names if getattr(base, n).shape != getattr(other, n).shape
                  or not np.array_equal(getattr(base, n), getattr(other, n), equal_nan=True)}
        found = frozenset(differ) if differ <= per_world else None
    if len(_DIFFERING) >= 4096:
        _DIFFERING.clear()
    _DIFFERING[key] = ((base, base_params, other, params), found)
    return found


def step_cores(members: Sequence[Any], t_ns: int, dt_ns: int, failed: dict[int, BaseException]) -> None:
    """Step the MuJoCo cores ``members`` (one per branch) one tick on MJWarp: see the module docstring."""
    if unavailable() is not None:  # the lockstep backend refuses "mjwarp" then; a direct call steps on C
        STEPPED["c"] += len(members)
        batched.step_cores(members, t_ns, dt_ns, failed)
        return
    shared = Counter(id(core._compiled.model) for core in members).most_common(1)[0][0]
    base = next(core for core in members if id(core._compiled.model) == shared)
    per_world: set[str] = set()
    stepped: list[tuple[int, Any, Any]] = []  # (index, core, compiled scene) of those stepped on warp
    for k, core in enumerate(members):
        s = core._compiled
        differ = _differing(base._compiled.model, base.params, s.model, core.params)
        if s.anim is not None or core._vel.tobytes() != core._vel_unset or differ is None:
            try:  # its own C step, alone
                core.step(t_ns, dt_ns)
            except Exception as exc:  # this branch's failure
                failed[k] = exc
            continue
        batched.write_inputs(core, s)
        per_world |= differ
        stepped.append((k, core, s))
    if not stepped:
        return
    datas = [s.data for _, _, s in stepped]
    warp_worlds = _worlds_or_none(base._compiled.model, len(datas), base.params, frozenset(per_world))
    if warp_worlds is None:  # warp refused the model: MuJoCo's C on threads, as without MJWarp
        STEPPED["c"] += len(members)
        batched.step_cores([core for _, core, _ in stepped], t_ns, dt_ns, _Shifted(failed, stepped))
        return
    if per_world:
        warp_worlds.set_models([s.model for _, _, s in stepped],
                               tuple((id(s.model), id(core.params)) for _, core, s in stepped))
    STEPPED["warp"] += len(stepped)
    STEPPED["c"] += len(members) - len(stepped)
    warp_worlds.put(datas)
    substeps = stepped[0][1]._nsub
    warp_worlds.step(substeps)
    finite = warp_worlds.take(datas, substeps)
    for (k, core, s), ok in zip(stepped, finite, strict=True):
        if not ok:
            failed[k] = PhysicsDivergedError(core.name, "step", None, "MJWarp: the state is not finite after the step")
            continue
        mujoco.mj_step1(s.model, s.data)
        for dst, di, src, si in core._moves[2]:  # the outputs that can change in a step
            dst[di] = src if si is None else src[si]


class _Shifted(dict):
    """``failed`` seen through the positions of a subset of the members (``stepped``)."""

    def __init__(self, failed: dict[int, BaseException], stepped: list[tuple[int, Any, Any]]):
        super().__init__()
        self.failed, self.stepped = failed, stepped

    def __setitem__(self, k: int, exc: BaseException) -> None:
        self.failed[self.stepped[k][0]] = exc


def _worlds_or_none(model: mujoco.MjModel, worlds: int, params: Any, per_world: frozenset[str]) -> WarpWorlds | None:
    """`worlds_for`, or None (warned once per model, with warp's reason) when warp refuses the model."""
    refused = _REFUSED.get(id(model))
    if refused is not None and refused[0] is model:
        return None
    try:
        return worlds_for(model, worlds, params=params, per_world=per_world)
    except DynabrainError as exc:
        _REFUSED[id(model)] = (model, str(exc))
        warnings.warn(f"{exc}; these cores step on MuJoCo's C instead", RuntimeWarning, stacklevel=2)
        return None


def step_batch(cls: type, members: Sequence[Any], t_ns: int, dt_ns: int, inp: Any, out: Any,
               failed: dict[int, BaseException]) -> None:
    """`Module.step_batch` for the MuJoCo core on MJWarp (the lockstep backend's ``physics="mjwarp"``)."""
    step_cores(members, t_ns, dt_ns, failed)


def handles(cls: type) -> bool:
    """Whether `step_batch` steps modules of class ``cls``: the MuJoCo core and its subclasses."""
    from .core import MujocoCore

    return issubclass(cls, MujocoCore)
