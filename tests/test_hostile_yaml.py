"""The YAML reader (scenarios and fmu.yaml): limits on size, nesting and alias expansion, and every
encoding problem, each a file:line problem, quickly, never a traceback."""

from __future__ import annotations

import codecs
import time

import pytest

from dynabrain.orchestrator.fmu.errors import FMUBuildError
from dynabrain.orchestrator.fmu.spec import load_spec
from dynabrain.orchestrator.kernel import yamlsrc
from dynabrain.orchestrator.kernel.yamlsrc import YamlSource, read_yaml


def alias_bomb(levels: int = 9, width: int = 9) -> str:
    text = "a0: &a0 [" + ", ".join(["x"] * width) + "]\n"
    for i in range(1, levels):
        text += f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * width) + "]\n"
    return text


def test_an_alias_bomb_is_refused_quickly():
    start = time.perf_counter()
    src = YamlSource(alias_bomb(), "bomb.yaml")
    assert time.perf_counter() - start < 1.0  # generous: it reads 90 values, it never expands 387 million
    (problem,) = src.problems
    assert problem.line == 6 and "MAX_VALUES" in problem.message and "*a4" in problem.message
    assert src.data is None


def test_aliases_within_the_limit_are_expanded():
    src = YamlSource("base: &b {x: 1, y: [1, 2]}\ncopy: *b\n", "f.yaml")
    assert not src.problems and src.data["copy"] == {"x": 1, "y": [1, 2]}


@pytest.mark.parametrize("text", ["a: &a [*a]", "a: &a {b: *a}"])
def test_an_alias_inside_its_own_anchor_is_refused(text):
    (problem,) = YamlSource(text, "f.yaml").problems
    assert problem.line == 1 and "inside its own anchor" in problem.message


@pytest.mark.parametrize("text", ["[" * 500 + "]" * 500, "a:\n" + "".join(" " * i + "- \n" for i in range(1, 200))])
def test_deep_nesting_is_refused_with_a_line(text):
    (problem,) = YamlSource(text, "deep.yaml").problems
    assert problem.line is not None and "MAX_DEPTH" in problem.message


def test_a_file_larger_than_the_limit_is_refused(tmp_path, monkeypatch):
    monkeypatch.setattr(yamlsrc, "MAX_FILE_BYTES", 1000)
    path = tmp_path / "big.yaml"
    path.write_text("name: " + "x" * 2000 + "\n")
    (problem,) = read_yaml(path, "the scenario").problems
    assert problem.file == str(path) and "larger than" in problem.message and "MAX_FILE_BYTES" in problem.message


ENCODINGS = [
    ("latin1", "name: café\nx: 1\n".encode("latin-1"), 1, "not UTF-8"),
    ("latin1_later", b"name: ok\nx: 1\ndescription: caf\xe9\n", 3, "byte 0xe9"),
    ("utf16", "name: x\n".encode("utf-16"), 1, "UTF-16"),
    ("utf16_no_bom", "name: x\n".encode("utf-16-le"), 1, "NUL byte"),
    ("utf32", codecs.BOM_UTF32_LE + "name: x\n".encode("utf-32-le"), 1, "UTF-32"),
    ("binary", bytes(range(256)) * 4, 1, "NUL byte"),
    ("nul_line_2", b"name: x\nwhat: a\x00b\n", 2, "NUL byte"),
    ("control", b"name: x\nwhat: a\x07b\n", 2, "malformed YAML"),
]


@pytest.mark.parametrize(("name", "raw", "line", "words"), ENCODINGS, ids=[e[0] for e in ENCODINGS])
def test_an_encoding_problem_has_a_line(tmp_path, name, raw, line, words):
    path = tmp_path / f"{name}.yaml"
    path.write_bytes(raw)
    (problem,) = read_yaml(path).problems
    assert (problem.file, problem.line) == (str(path), line) and words in problem.message, problem


def test_a_utf8_byte_order_mark_is_fine(tmp_path):
    path = tmp_path / "bom.yaml"
    path.write_bytes(codecs.BOM_UTF8 + "name: café\n".encode())
    src = read_yaml(path)
    assert not src.problems and src.data == {"name": "café"}


@pytest.mark.parametrize(("text", "words"), [
    ("? [1, 2]\n: x\n", "a key is a plain value"),
    ("a: !python/object:os.system x\n", "cannot read this value"),
    ("a: " + "9" * 5000 + "\n", "cannot read this value"),
    ("a: 1\na: 2\n", "written twice"),
])
def test_values_the_reader_cannot_take_are_problems(text, words):
    src = YamlSource(text, "f.yaml")
    assert any(words in p.message and p.line is not None for p in src.problems), src.problems


def test_fmu_yaml_goes_through_the_same_reader(tmp_path):
    folder = tmp_path / "fmu"
    folder.mkdir()
    (folder / "fmu.yaml").write_bytes(b"name: caf\xe9\n")
    with pytest.raises(FMUBuildError) as err:
        load_spec(folder)
    assert "fmu.yaml:1: the file is not UTF-8 text" in str(err.value)
    (folder / "fmu.yaml").write_text(alias_bomb())
    with pytest.raises(FMUBuildError) as err:
        load_spec(folder)
    assert "fmu.yaml:6" in str(err.value) and "MAX_VALUES" in str(err.value)
