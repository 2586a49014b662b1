"""Offscreen OpenGL for MuJoCo rendering without a display: EGL or OSMesa, chosen at run time.

PyOpenGL binds one platform per process, the first time it is imported (``PYOPENGL_PLATFORM``). So
the backends are tried once per process, in the order asked (``auto``: EGL, then OSMesa):

- a backend whose library the system does not have (``libEGL``, ``libOSMesa``) is skipped;
- when more than one could work and none is bound yet, each is first tried in a short child
  process, so that a failing EGL does not leave this process bound to it;
- the first that works is bound and used for every camera of this process.

When none works, `open_gl` raises `RendererUnavailableError` with the reason of each backend, so a
module can say so at load (and a test can skip with that reason). Linux packages that provide
them: ``libegl1`` and ``libegl-mesa0`` with ``libgl1-mesa-dri`` (EGL, software or GPU), or ``libosmesa6``.
"""

from __future__ import annotations

import ctypes.util
import os
import subprocess
import sys
import threading
from typing import Any

from dynabrain.orchestrator.kernel.errors import DynabrainError

BACKENDS = ("egl", "osmesa")
_LIBRARIES = {"egl": "EGL", "osmesa": "OSMesa"}
_PROBE = """
import mujoco
from mujoco.{name} import GLContext
ctx = GLContext(16, 16)
ctx.make_current()
mujoco.MjrContext(mujoco.MjModel.from_xml_string("<mujoco/>"), mujoco.mjtFontScale.mjFONTSCALE_100)
print("ok")
"""
_LOCK = threading.Lock()
_chosen: dict[str, Any] = {}
_reasons: dict[str, str] = {}


class RendererUnavailableError(DynabrainError):
    """No offscreen OpenGL backend works in this process; ``reasons`` says why, per backend."""

    def __init__(self, reasons: dict[str, str]):
        self.reasons = dict(reasons)
        detail = "; ".join(f"{k}: {v}" for k, v in reasons.items()) or "no backend tried"
        super().__init__(f"no offscreen renderer works here ({detail}); install libegl1 + libegl-mesa0 "
                         "(+ libgl1-mesa-dri) or libosmesa6")


def _bound() -> str | None:
    """The platform PyOpenGL is bound to in this process, if any."""
    platform = os.environ.get("PYOPENGL_PLATFORM", "").lower()
    return platform or None


def _probe(name: str) -> str | None:
    """Try a backend in a child process; None when it works, else the reason."""
    env = dict(os.environ, PYOPENGL_PLATFORM=name, MUJOCO_GL=name)
    try:
        done = subprocess.run([sys.executable, "-c", _PROBE.format(name=name)], env=env, capture_output=True,
                              text=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"probe failed: {exc}"
    if done.returncode == 0 and done.stdout.strip().endswith("ok"):
        return None
    lines = [ln for ln in done.stderr.strip().splitlines() if ln.strip()]
    return lines[-1] if lines else f"probe exited with {done.returncode}"


def _load(name: str) -> Any:
    """Import a backend's GLContext class in this process (binds PyOpenGL to it)."""
    if name == "egl":
        from mujoco.egl import GLContext
    else:
        from mujoco.osmesa import GLContext
    return GLContext


def _choose(order: tuple[str, ...]) -> tuple[str, Any]:
    bound = _bound()
    candidates = [n for n in order if bound in (None, n)]
    for name in order:
        if name not in candidates:
            _reasons.setdefault(name, f"this process already uses PyOpenGL platform {bound!r}")
    available = []
    for name in candidates:
        if ctypes.util.find_library(_LIBRARIES[name]) is None:
            _reasons.setdefault(name, f"lib{_LIBRARIES[name]} is not installed")
        else:
            available.append(name)
    for name in available:
        if name in _reasons:
            continue
        if bound is None and len(available) > 1:
            reason = _probe(name)
            if reason is not None:
                _reasons[name] = reason
                continue
        try:
            cls = _load(name)
            cls(16, 16).free()
        except Exception as exc:  # ImportError, RuntimeError, GLError: the backend does not work here
            _reasons[name] = f"{type(exc).__name__}: {exc}"
            continue
        return name, cls
    raise RendererUnavailableError({n: _reasons[n] for n in order if n in _reasons})


def open_gl(width: int, height: int, prefer: str = "auto") -> tuple[str, Any]:
    """(backend name, a new GL context of at least width x height) from the first backend that works."""
    if prefer != "auto" and prefer not in BACKENDS:
        raise DynabrainError(f"unknown renderer backend {prefer!r}; one of auto, {', '.join(BACKENDS)}")
    order = BACKENDS if prefer == "auto" else (prefer,)
    with _LOCK:
        key = _chosen.get("name")
        if key is None or key not in order:
            name, cls = _choose(order)
            _chosen.update(name=name, cls=cls)
        name, cls = _chosen["name"], _chosen["cls"]
    return name, cls(width, height)
