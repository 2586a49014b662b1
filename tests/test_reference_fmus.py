"""The Modelica Association's Reference FMUs (tests/reference_fmus, third-party) built here with the
system C compiler and run as dynabrain modules (issue 28, item 2). Clocks (FMI 3.0 scheduled
execution) follows the pattern of the Reference repository's examples/scs_synchronous.c: inClock1
every second, inClock2 triggered at 0, 1, 8 and 9 s, inClock3 a countdown inClock1 starts at 4 s."""

from __future__ import annotations

import platform
import shutil
import subprocess
import zipfile
from pathlib import Path

import pytest

from dynabrain.orchestrator.fmu import make_fmu_module
from dynabrain.orchestrator.kernel.world import World

SOURCE = Path(__file__).resolve().parent / "reference_fmus"
pytestmark = pytest.mark.usefixtures("fmu_cache")
TICKS = ("inClock1Ticks", "inClock2Ticks", "inClock3Ticks", "totalInClockTicks")


def build(model: str, version: int, out: Path) -> Path:
    """``MODEL-fmiN.fmu`` in ``out``: the model's C files compiled as its CMake build does."""
    cc = shutil.which("cc")
    if cc is None:
        pytest.skip("no C compiler (cc) to build the Reference FMUs")
    so = out / f"{model}-{version}.so"
    subprocess.run([cc, "-shared", "-fPIC", "-O2", "-fvisibility=hidden", f"-DFMI_VERSION={version}",
                    "-DDISABLE_PREFIX", f"-I{SOURCE / 'include'}", f"-I{SOURCE / model}",
                    str(SOURCE / model / "model.c"),
                    str(SOURCE / "src" / f"fmi{version}Functions.c"), str(SOURCE / "src" / "cosimulation.c"),
                    "-o", str(so), "-lm"], check=True)
    platform_dir = "linux64" if version == 2 else f"{platform.machine()}-linux"
    fmu = out / f"{model}-fmi{version}.fmu"
    with zipfile.ZipFile(fmu, "w") as z:
        z.write(SOURCE / model / f"FMI{version}.xml", "modelDescription.xml")
        z.write(so, f"binaries/{platform_dir}/{model}.so")
    return fmu


@pytest.fixture(scope="session")
def clocks_fmu(tmp_path_factory) -> Path:
    return build("Clocks", 3, tmp_path_factory.mktemp("reference_fmus"))


def run_clocks(fmu: Path, seconds: int) -> list[tuple[float, ...]]:
    """The tick counters at each second from 1 s; inClock2 triggered at 1, 8 and 9 s."""
    rows = []
    with World(step="1s") as w:
        w.add_module(make_fmu_module("c", str(fmu), base_dir=".", params={}, targets=[]))
        for k in range(seconds):
            w.set("c.inClock2", 1.0 if k + 1 in (1, 8, 9) else 0.0)
            w.tick()
            rows.append(tuple(float(w.get(f"c.{n}")) for n in TICKS))
    return rows


def test_clocks_partitions_tick_as_the_reference_example_until_the_countdown(clocks_fmu):
    # at 0 s (initialization) inClock1 ticks alone: dynabrain does not read triggered clocks there
    assert run_clocks(clocks_fmu, 3) == [(2, 1, 0, 3), (3, 1, 0, 4), (4, 1, 0, 5)]


def test_clocks_countdown_of_zero_ticks_at_once(clocks_fmu):
    # at 4 s inClock1's partition gives the countdown inClock3 the interval 0: its partition runs at once
    assert run_clocks(clocks_fmu, 4)[-1][2] == 1


def test_clocks_tick_pattern_over_the_reference_examples_ten_seconds(clocks_fmu):
    """The pattern of the Reference repo's examples/scs_synchronous.c, worked out from its schedule: at each
    second t inClock1 ticks; inClock2 is triggered at 0, 1, 8 and 9 s (here not at 0: the triggered clock's port
    is not read at initialization, so one tick fewer); at 4 s inClock1's partition gives the countdown inClock3
    the interval 0, and its partition runs at once."""
    expected = []
    for t in range(1, 10):
        one = t + 1
        two = sum(1 for k in (0, 1, 8, 9) if k <= t) - 1
        three = 1 if t >= 4 else 0
        expected.append((one, two, three, one + two + three))
    assert run_clocks(clocks_fmu, 9) == expected


def test_an_enumeration_connector_is_exported_as_an_enumeration(tmp_path):
    """The Reference FMU Feedthrough (FMI 3.0) has an input and an output of enumeration type ``Option``:
    the SSP names the type on both connectors and lists its items once (checked against the SSP 1.0
    schema), and imports back."""
    from lxml import etree

    from dynabrain.orchestrator.scenario.ssp import SSD, export_ssp, import_ssp

    fmu = build("Feedthrough", 3, tmp_path)
    (tmp_path / "ft.yaml").write_text(f"name: ft\nworld: {{step: 1ms, duration: 10ms, core: null}}\n"
                                      f"modules:\n  - {{name: f, fmu: {fmu}}}\n")
    result = export_ssp(tmp_path / "ft.yaml", tmp_path / "ft.ssp")
    assert result.validated
    with zipfile.ZipFile(result.path) as z:
        root = etree.fromstring(z.read(SSD))
    ns = {"ssd": "http://ssp-standard.org/SSP1/SystemStructureDescription",
          "ssc": "http://ssp-standard.org/SSP1/SystemStructureCommon"}
    typed = {c.get("name"): c.find("ssc:Enumeration", ns).get("name")
             for c in root.iterfind(".//ssd:Connector", ns) if c.find("ssc:Enumeration", ns) is not None}
    assert typed == {"Enumeration_input": "Option", "Enumeration_output": "Option"}
    items = [(i.get("name"), i.get("value")) for i in root.iterfind("ssd:Enumerations/ssc:Enumeration/ssc:Item", ns)]
    assert items == [("Option 1", "1"), ("Option 2", "2")]
    import_ssp(result.path, tmp_path / "back.yaml")
