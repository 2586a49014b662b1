"""The public face: `from dynabrain.orchestrator import ...` gives what the README and a module author
use, the README's Python example runs as written, and importing a room loads no room above it."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import dynabrain.orchestrator as face

ROOT = Path(__file__).resolve().parents[1]


def test_every_public_name_resolves():
    for name in face.__all__:
        assert getattr(face, name) is not None, name
    assert sorted(face._WHERE) == sorted(face.__all__)


def test_unknown_name_is_an_attribute_error():
    try:
        face.NoSuchThing  # noqa: B018
    except AttributeError as exc:
        assert "NoSuchThing" in str(exc)
    else:
        raise AssertionError("an unknown name resolved")


def test_readme_python_example_runs(tmp_path, monkeypatch):
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert blocks, "the README shows no Python example"
    monkeypatch.chdir(ROOT)
    for block in blocks:
        exec(compile(block, "README.md", "exec"), {"__name__": "readme_example"})  # our own README


def test_importing_the_kernel_loads_no_room_above_it():
    code = ("import sys; import dynabrain.orchestrator.kernel; import dynabrain.modules.servo; "
            "above = [m for m in sys.modules if m.startswith(('dynabrain.orchestrator.scenario', "
            "'dynabrain.orchestrator.logs', 'dynabrain.orchestrator.cli', 'dynabrain.orchestrator.fmu', "
            "'dynabrain.bridge'))]; print(above)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
