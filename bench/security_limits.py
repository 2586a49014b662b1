"""What the input limits of issue 24 cost and save, each figure measured in this run:

1. a model file of 150 x 150 replicated free boxes (22,500 bodies): refused by `scenario.modelfile`
   (its bodies counted in the XML, before MuJoCo reads it) against MuJoCo only parsing it
   (``MjSpec.from_file``, before any compile), and their ratio;
2. the count of a shipped model file (``--model``, default the see-saw: two attached humanoids) against
   MuJoCo compiling it: what the check adds to loading a scene, as a share;
3. an FMU's archive checked (`fmu.archive.check_archive`: its directory only) against extracting it.

The best of ``--repeats`` each, interleaved. The machine's load (1-minute average) is printed before
and after.

Run: ``.venv/bin/python bench/security_limits.py [--repeats 7] [--model scenarios/models/kid.xml]``
"""

from __future__ import annotations

import argparse
import os
import tempfile
import zipfile
from pathlib import Path

import mujoco
from timing import best_of_each

from dynabrain.orchestrator.fmu import archive
from dynabrain.orchestrator.fmu.build import build_fmu
from dynabrain.orchestrator.scenario.modelfile import ModelFileError, count_bodies

ROOT = Path(__file__).resolve().parents[1]
REPLICATED = ROOT / "tests" / "hostile" / "models" / "replicate_22500.xml"


def load() -> str:
    return f"load {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores"


def refuse(path: Path) -> None:
    try:
        count_bodies(str(path))
    except ModelFileError:
        return
    raise AssertionError(f"{path} was not refused")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--model", default=str(ROOT / "scenarios" / "models" / "seesaw.xml"))
    args = parser.parse_args()
    print(load())

    refused, parsed = best_of_each([lambda: refuse(REPLICATED), lambda: mujoco.MjSpec.from_file(str(REPLICATED))],
                                   repeats=max(1, args.repeats // 3))
    print(f"22,500 replicated bodies: refused in {refused * 1e3:.2f} ms; MuJoCo's parse alone {parsed:.2f} s "
          f"(x{parsed / refused:,.0f})")

    counted, compiled = best_of_each([lambda: count_bodies(args.model),
                                      lambda: mujoco.MjModel.from_xml_path(args.model)], repeats=args.repeats)
    print(f"{Path(args.model).name}: counted in {counted * 1e3:.2f} ms, compiled by MuJoCo in {compiled * 1e3:.1f} ms "
          f"(the count adds {counted / compiled:.1%})")

    fmu = build_fmu(ROOT / "fmus" / "passthrough", 2)
    with tempfile.TemporaryDirectory() as tmp:
        def check() -> None:
            with zipfile.ZipFile(fmu) as zf:
                archive.check_archive(zf, "FMU passthrough")

        def extract() -> None:
            archive.extract(fmu, os.path.join(tmp, "x"), "FMU passthrough")

        checked, extracted = best_of_each([check, extract], repeats=args.repeats)
    print(f"FMU archive: checked in {checked * 1e6:.0f} us, extracted in {extracted * 1e3:.2f} ms "
          f"(the check adds {checked / extracted:.1%})")
    print(load())


if __name__ == "__main__":
    main()
