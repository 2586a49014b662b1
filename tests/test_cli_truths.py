"""The command says what is so: ``-q`` prints only what went wrong and the verdict, ``-vv`` adds debug
lines, help shows no type placeholders (``<bool>``, ``<list[str]>``), a reserved FMU name is called
reserved. Run as a user runs it: the installed entry point's code, in a process of its own."""

from __future__ import annotations

import subprocess
import sys

import pytest


def dynabrain(*args: str, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dynabrain.orchestrator.cli", *args], capture_output=True,
                          text=True, cwd=cwd, timeout=120)


def test_quiet_prints_the_verdict_and_very_verbose_adds_debug_lines():
    quiet = dynabrain("-q", "run", "two_cubes")
    assert quiet.returncode == 0 and quiet.stdout.strip() == "all checks passed", quiet.stdout
    loud = dynabrain("-vv", "run", "two_cubes", "-q")
    assert "DEBUG dynabrain.cli: world two_cubes: step 2ms, schedule core" in loud.stderr, loud.stderr
    assert "rests flat on the floor" in loud.stdout  # the table, without -q


@pytest.mark.parametrize("command", [["run"], ["replay"], ["plot"], ["serve"], ["fmu", "new"], ["ssp", "import"]])
def test_help_shows_no_type_placeholders(command):
    text = dynabrain(*command, "--help").stdout
    assert "Usage: " in text and "<bool>" not in text and "<list[" not in text, text
    assert "{log}" not in text and "{scenario}" not in text


def test_a_reserved_fmu_name_is_called_reserved(tmp_path):
    made = dynabrain("fmu", "new", "m", cwd=tmp_path)
    assert made.returncode != 0 and "'m' is reserved: the generated C code uses" in made.stderr, made.stderr
    assert not (tmp_path / "m").exists()
