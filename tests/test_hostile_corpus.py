"""The corpus of nasty scenarios (tests/hostile/, from issue 17 and after): `dynabrain check` refuses each
one with exit code 2 and file:line messages, never a traceback. Each file says what it must be told:
``# expect: LINE TEXT`` lines (line numbers count those lines too). Cases that are bytes rather than
text (encodings, a 10 MB name) are made here."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from dynabrain.orchestrator.cli.main import app

HOSTILE = Path(__file__).resolve().parent / "hostile"
CASES = sorted(HOSTILE.glob("*.yaml"))
runner = CliRunner()

GOOD = b"name: bytes\nworld: {step: 2ms, duration: 10ms, core: null}\n"
BYTE_CASES = {
    "latin1": (b"# caf\xe9\n" + GOOD, 1, "not UTF-8"),
    "latin1_later": (GOOD + b"description: caf\xe9\n", 3, "byte 0xe9"),
    "utf16": ("# x\n".encode("utf-16") + GOOD.decode().encode("utf-16-le"), 1, "UTF-16"),
    "binary": (bytes(range(1, 256)) * 8, 2, "not UTF-8"),  # (byte 10 ends line 1)
    "nul": (GOOD + b"description: a\x00b\n", 3, "NUL byte"),
    "name_10mb": (b"name: " + b"x" * 10_000_000 + b"\n", 1, "MAX_FILE_BYTES"),
    "name_1mb": (b"world: {core: null}\nname: " + b"x" * 1_000_000 + b"\n", 2, "MAX_NAME"),
    "empty": (b"", 1, "a scenario is a mapping"),
    "a_list": (b"- 1\n- 2\n", 1, "a scenario is a mapping"),
}


def check(path: Path):
    result = runner.invoke(app, ["check", str(path)])
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    assert "Traceback" not in result.output
    return result


def expected(path: Path) -> list[tuple[int, str]]:
    found = [re.match(r"# expect: (\d+) (.+)", line) for line in path.read_text().splitlines()]
    return [(int(m[1]), m[2]) for m in found if m]


@pytest.mark.parametrize("path", CASES, ids=[p.stem for p in CASES])
def test_check_refuses_with_file_and_line(path):
    result = check(path)
    assert result.exit_code == 2, result.output
    wanted = expected(path)
    assert wanted, f"{path.name} says nothing it expects"
    lines = result.output.splitlines()
    for line, text in wanted:
        assert any(f"{path.name}:{line} " in out or f"{path.name}:{line}:" in out for out in lines
                   if text in out), f"{path.name}:{line} ... {text}\n{result.output}"
    problems = [out for out in lines if out.startswith("  ")]
    assert problems and all(re.search(re.escape(path.name) + r":\d+[ :]", out) for out in problems), result.output


@pytest.mark.parametrize("name", sorted(BYTE_CASES))
def test_bytes_that_are_no_scenario_are_refused_with_a_line(tmp_path, name):
    raw, line, text = BYTE_CASES[name]
    path = tmp_path / f"{name}.yaml"
    path.write_bytes(raw)
    result = check(path)
    assert result.exit_code == 2
    assert f"{name}.yaml:{line}" in result.output and text in result.output, result.output[:500]


def test_run_of_the_attack_exits_2_and_runs_nothing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = runner.invoke(app, ["run", str(HOSTILE / "expr_globals.yaml"), "-q"])
    assert result.exit_code == 2 and "expr_globals.yaml:" in result.output
    assert not (tmp_path / "x").exists()
