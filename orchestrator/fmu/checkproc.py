"""`check_fmu` in a child process (``dynabrain fmu check``): an FMU that crashes gets a verdict.

    report, output = check_fmu_apart("vendor.fmu")

The child (``python -m dynabrain.orchestrator.fmu.checkproc FD TRACE_FILE``) runs `check_fmu` and
sends its report back. Before each FMI call it writes the check's phase and the call into TRACE_FILE
(shared memory; `api.trace_calls`), so when the FMU kills it (a segfault, an abort) or hangs, the
parent's report says where: "crashed in fmi2DeSerializeFMUstate during the fork probe (killed by
SIGSEGV)". Within the state checks the probe is told by the call (a state serialized or read back:
the fork probe; a state set: a restore probe). What the child printed (the FMU's log lines, each
once) comes back beside the report.
"""

from __future__ import annotations

import contextlib
import logging
import mmap
import shutil
import signal
import subprocess
import sys
import tempfile
from multiprocessing.connection import Connection
from pathlib import Path

from ..kernel.errors import DynabrainError
from ..kernel.workers import spawn_worker
from .check import FmuCheckReport, check_fmu

TRACE_SIZE = 256
CHECK_TIMEOUT_S = 600.0
"""How long the whole check may take in its child before it is killed (an FMU that never returns)."""
_SEP = "\x1f"


def _probe(phase: str, call: str) -> str:
    """The probe under way, from the check's phase and the FMI call."""
    if phase != "state checks":
        return f"the {phase}"
    lower = call.lower()
    if "serialize" in lower:
        return "the fork probe"
    if "setfmustate" in lower:
        return "a restore probe (save/restore, step -> restore -> step)"
    if "getfmustate" in lower or "freefmustate" in lower:
        return "a save probe"
    return "the state checks"


def check_fmu_apart(fmu: str, *, base_dir: str = ".", ticks: int = 40, step: str | int | None = None,
                    seed: int = 0, timeout: float = CHECK_TIMEOUT_S) -> tuple[FmuCheckReport, list[str]]:
    """`check_fmu` in a child process: (the report, the lines the child printed, each once). A child
    that dies or does not finish within ``timeout`` seconds gives a report whose problem says in which
    FMI call and which probe."""
    work = Path(tempfile.mkdtemp(prefix="dynabrain-check-"))
    try:
        trace_path, log_path = work / "trace", work / "output"
        trace_path.write_bytes(b"\0" * TRACE_SIZE)
        with open(log_path, "wb") as log:
            try:
                proc, conn = spawn_worker("dynabrain.orchestrator.fmu.checkproc", str(trace_path), stdout=log,
                                          stderr=subprocess.STDOUT)
            except OSError as exc:
                raise DynabrainError(f"check of FMU {fmu}: cannot start its process: {exc}") from None
            with conn:
                conn.send(("check", fmu, str(Path(base_dir).resolve()), ticks, step, seed))
                report, hung = _answer(proc, conn, timeout)
        output = _lines(log_path)
        if report is None:
            report = _verdict(fmu, base_dir, proc.returncode, hung, trace_path, output, timeout)
        return report, output
    finally:
        shutil.rmtree(work, ignore_errors=True)


def _answer(proc: subprocess.Popen, conn: Connection, timeout: float) -> tuple[FmuCheckReport | None, bool]:
    """(the child's report, or None when it died or hung; whether it hung and was killed)."""
    hung = False
    with contextlib.suppress(EOFError, OSError):
        hung = not conn.poll(timeout)  # (a dead child's end reads as ready: EOF)
        if not hung:
            report = conn.recv()  # our own child's report (a pipe of our own)
            proc.wait()
            return report, False
    if hung:
        proc.kill()
    proc.wait()
    return None, hung


def _verdict(fmu: str, base_dir: str, rc: int | None, hung: bool, trace_path: Path, output: list[str],
             timeout: float) -> FmuCheckReport:
    """A report for a child that did not answer: where it was, how it ended, its last output."""
    from . import load_fmu_info

    report = FmuCheckReport(fmu)
    with contextlib.suppress(DynabrainError):
        report.info = load_fmu_info(fmu, base_dir=base_dir)  # (reads the description: no binary is loaded)
    raw = trace_path.read_bytes().rstrip(b"\0").decode("utf-8", "replace")
    phase, _, call = raw.partition(_SEP)
    where = f"in {call} during {_probe(phase, call)}" if call else f"during the {phase or 'start'}"
    if hung:
        how = f"did not finish within {timeout:g} s: killed"
    elif rc is not None and rc < 0:
        try:
            how = f"killed by {signal.Signals(-rc).name}"
        except ValueError:
            how = f"killed by signal {-rc}"
    else:
        how = f"exited with status {rc}"
    said = " | ".join(output[-6:])
    verb = "hung" if hung else "crashed"
    report.problems.append(f"the FMU {verb} {where} ({how})" + (f"; its last output: {said}" if said else ""))
    return report


def _lines(path: Path) -> list[str]:
    """The child's output, each line once, in order."""
    text = path.read_bytes()[-20000:].decode("utf-8", "replace")
    return list(dict.fromkeys(ln.rstrip() for ln in text.splitlines() if ln.strip()))


def main(argv: list[str]) -> int:
    from .api import trace_calls

    fd, trace_path = int(argv[1]), argv[2]
    with open(trace_path, "r+b") as fh:
        trace = mmap.mmap(fh.fileno(), TRACE_SIZE)
    phase = [""]

    def mark(call: str) -> None:
        trace[:TRACE_SIZE] = f"{phase[0]}{_SEP}{call}".encode()[:TRACE_SIZE].ljust(TRACE_SIZE, b"\0")

    def on_phase(name: str) -> None:
        phase[0] = name
        mark("")

    trace_calls(mark)
    sys.stdout.reconfigure(line_buffering=True)  # type: ignore[union-attr]  # (its last lines reach the file)
    logging.basicConfig(level=logging.WARNING, format="%(message)s", stream=sys.stdout)
    conn = Connection(fd)
    try:
        _, fmu, base_dir, ticks, step, seed = conn.recv()
        conn.send(check_fmu(fmu, base_dir=base_dir, ticks=ticks, step=step, seed=seed, on_phase=on_phase))
    finally:
        conn.close()
    return 0


if __name__ == "__main__":
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is for the parent, which kills this process
    raise SystemExit(main(sys.argv))
