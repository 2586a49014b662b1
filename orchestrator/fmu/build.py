"""Build a C FMU from a source folder: generate, compile, package, validate, cache.

`build_fmu(folder)` returns the ``.fmu`` for one FMI version. Builds are cached by the content hash
of everything that goes into them (fmu.yaml, the model's C files and headers, the glue, the FMI
headers, the compiler's identity, the flags), so an unchanged folder costs a hash and a changed one
is rebuilt. The cache is outside the working tree (see `paths.cache_dir`); a build never writes
into the source folder.
"""

from __future__ import annotations

import functools
import hashlib
import os
import shlex
import shutil
import subprocess
import tempfile
import zipfile
from collections.abc import Iterable, Mapping
from pathlib import Path

from . import codegen
from .codegen1 import model_description1
from .errors import FMUBuildError
from .paths import SHARED_LIB_EXT, binary_dir, cache_dir, fmi_headers_dir, glue_dir
from .spec import FmuSpec, load_spec, spec_digest_inputs

BUILD_FORMAT = "1"
GENERATOR_FILES = tuple(Path(__file__).with_name(n) for n in ("spec.py", "codegen.py", "codegen1.py", "build.py"))
"""The generator's own sources are inputs of every build: changing them rebuilds."""
GLUE_FILES = ("fmu_model.h", "fmu_glue.h", "fmu_core.c", "fmi1_glue.c", "fmi2_glue.c", "fmi3_glue.c")
CFLAGS = ("-std=c11", "-O2", "-fPIC", "-shared", "-fvisibility=hidden", "-Wall",
          "-Werror=implicit-function-declaration", "-Werror=incompatible-pointer-types")
_ZIP_TIME = (1980, 1, 1, 0, 0, 0)


def compiler() -> list[str]:
    """The C compiler command: ``$CC``, else ``cc``, ``gcc`` or ``clang`` from PATH."""
    env = os.environ.get("CC")
    if env:
        return shlex.split(env)
    for name in ("cc", "gcc", "clang"):
        found = shutil.which(name)
        if found:
            return [found]
    raise FMUBuildError("no C compiler found: install gcc or clang, or set CC")


@functools.cache
def compiler_identity(cmd: tuple[str, ...]) -> str:
    try:
        out = subprocess.run([*cmd, "--version"], capture_output=True, text=True, timeout=30, check=False)
    except OSError as exc:
        raise FMUBuildError(f"the C compiler {' '.join(cmd)!r} cannot run: {exc}") from None
    return (out.stdout or out.stderr).splitlines()[0] if (out.stdout or out.stderr) else " ".join(cmd)


def content_digest(spec: FmuSpec, version: int) -> str:
    """SHA-256 of every input of the build of ``spec`` for FMI ``version``."""
    cc = tuple(compiler())
    h = hashlib.sha256()
    for part in (BUILD_FORMAT, str(version), binary_dir(version), compiler_identity(cc), " ".join(CFLAGS)):
        h.update(part.encode() + b"\0")
    files = [(p.name, p) for p in spec_digest_inputs(spec)]
    files += [(f"glue/{n}", glue_dir() / n) for n in GLUE_FILES]
    files += [(f"generator/{p.name}", p) for p in GENERATOR_FILES]
    files += [(f"fmi/{p.name}", p) for p in sorted(fmi_headers_dir().glob(f"fmi{version}*.h"))]
    for name, path in files:
        h.update(name.encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


def build_fmu(folder: str | os.PathLike[str], version: int | None = None, output: str | os.PathLike[str] | None = None,
              *, force: bool = False) -> Path:
    """Build the FMU in ``folder`` (FMI ``version``, default: the first in fmu.yaml) and return the
    ``.fmu`` path: in the cache, or copied to ``output``. Raises `FMUBuildError`."""
    spec = load_spec(folder)
    version = spec.fmi[0] if version is None else version
    if version not in spec.fmi:
        raise FMUBuildError(f"{Path(folder) / 'fmu.yaml'}: FMI {version}.0 is not among the versions it builds "
                            f"(fmi: {list(spec.fmi)})")
    digest = content_digest(spec, version)
    target = cache_dir() / "fmus" / f"{spec.name}-fmi{version}-{digest[:16]}.fmu"
    if force or not target.is_file():
        _build(spec, version, digest, target)
    if output is None:
        return target
    out = Path(output)
    out.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(target, out)
    return out


def build_all(folder: str | os.PathLike[str], output_dir: str | os.PathLike[str] | None = None) -> list[Path]:
    """Every FMI version fmu.yaml lists; into ``output_dir`` as ``<name>-fmi<v>.fmu`` when given."""
    spec = load_spec(folder)
    out = []
    for version in spec.fmi:
        dest = None if output_dir is None else Path(output_dir) / f"{spec.name}-fmi{version}.fmu"
        out.append(build_fmu(folder, version, dest))
    return out


def _build(spec: FmuSpec, version: int, digest: str, target: Path) -> None:
    guid = codegen.token(spec, digest)
    work_root = cache_dir() / "tmp"
    work_root.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f"{spec.name}-", dir=work_root))
    try:
        gen = work / "gen"
        gen.mkdir()
        (gen / "model_data.h").write_text(codegen.model_data_h(spec))
        (gen / "model_tables.inc").write_text(codegen.tables_inc(spec, version, guid))
        lib = work / f"{spec.name}{SHARED_LIB_EXT}"
        glue = glue_dir()
        named = (f"-DMODEL_IDENTIFIER={spec.name}",) if version == 1 else ()  # FMI 1.0 prefixes its functions
        compile_library([glue / "fmu_core.c", glue / f"fmi{version}_glue.c", *spec.sources], lib,
                        include=[gen, glue, spec.folder], flags=(*spec.cflags, *named), what=f"FMU {spec.folder}")
        xml = model_description1(spec, guid) if version == 1 else codegen.model_description(spec, version, guid)
        packed = work / "out.fmu"
        package_fmu(packed, xml, {binary_dir(version): lib})
        validate_built(packed, spec.folder)
        target.parent.mkdir(parents=True, exist_ok=True)
        os.replace(packed, target)
    finally:
        shutil.rmtree(work, ignore_errors=True)


def compile_library(sources: Iterable[Path], output: Path, *, include: Iterable[Path] = (), flags: Iterable[str] = (),
                    what: str = "library") -> Path:
    """Compile C ``sources`` into the shared library ``output`` (with the FMI headers on the include
    path). A compiler error raises `FMUBuildError` with the compiler's messages."""
    cmd = [*compiler(), *CFLAGS, *[f"-I{p}" for p in include], f"-I{fmi_headers_dir()}", *flags,
           *[str(s) for s in sources], "-o", str(output), "-lm"]
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=300, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise FMUBuildError(f"{what}: the C compiler failed to run: {exc}") from None
    if done.returncode != 0:
        log = (done.stderr or done.stdout).strip()
        if len(log) > 6000:
            log = log[:6000] + "\n..."
        raise FMUBuildError(f"{what}: compilation failed:\n{log}")
    return output


def package_fmu(dest: Path, model_description: str, binaries: Mapping[str, Path],
                extra: Mapping[str, bytes] | None = None) -> Path:
    """Zip an FMU: ``modelDescription.xml`` and each library under ``binaries`` (platform folder ->
    library path), with fixed timestamps so equal inputs give equal files."""
    items: list[tuple[str, bytes, int]] = [("modelDescription.xml", model_description.encode("utf-8"), 0o644)]
    for folder, lib in binaries.items():
        items.append((f"{folder}/{lib.name}", lib.read_bytes(), 0o755))
    for name, data in (extra or {}).items():
        items.append((name, data, 0o644))
    tmp = dest.with_suffix(dest.suffix + ".part")
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data, mode in sorted(items):
            info = zipfile.ZipInfo(name, _ZIP_TIME)
            info.external_attr = mode << 16
            info.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(info, data)
    os.replace(tmp, dest)
    return dest


def validate_built(fmu: Path, folder: Path) -> None:
    """FMPy's full validation of the model description, then the adapter's own reading of it."""
    from fmpy.validation import validate_fmu

    from .info import read_fmu_info

    problems = validate_fmu(str(fmu))
    if problems:
        raise FMUBuildError(f"FMU {folder}: the generated model description does not validate:\n"
                            + "\n".join(f"  - {p}" for p in problems))
    read_fmu_info(fmu, label=str(folder))


def is_source_folder(path: Path) -> bool:
    return path.is_dir() and (path / "fmu.yaml").is_file()


def ensure_built(path: Path, version: int | None = None) -> Path:
    """A ``.fmu`` for ``path``: the file itself, or the cached build of a source folder (rebuilt when
    its sources changed)."""
    if path.is_dir():
        if not is_source_folder(path):
            raise FMUBuildError(f"{path} is a folder without fmu.yaml: an FMU is a .fmu file or a source folder "
                                "with fmu.yaml (see `dynabrain fmu new`)")
        return build_fmu(path, version)
    if version is not None:
        raise FMUBuildError(f"{path}: @fmi{version} selects the version to build from a source folder; "
                            "a .fmu file has the version it was built with")
    return path
