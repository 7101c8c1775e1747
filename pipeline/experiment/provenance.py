"""Which code produced a run, recorded on every job (records column and MLflow tag).

``code_version()``: the git commit of the checkout the package runs from, with ``-dirty`` when
tracked files have uncommitted changes; outside a git checkout (an image), the commit the image was
built from (``GOPRE_CODE_VERSION``, which ``docker/Dockerfile`` sets from its ``GIT_COMMIT`` build
argument), else ``gopre <installed version>``.
A sweep relaunched after the code changed keeps its finished jobs (they are identified by what
they compute, not by the code) and says so, naming both versions.

``environment()``: which installed packages and which CPU ran it (``Environment``): the hash of
every installed distribution's name and version, whether they are exactly ``requirements.lock``
(what ``make env``, the image and every node install), and the CPU model. Two machines with the
same code and the same ``packages`` id run the same library code; the executors refuse a worker
whose code version or packages differ from the driver's.
"""

from __future__ import annotations

import hashlib
import os
import platform
import subprocess
from dataclasses import asdict, dataclass
from functools import lru_cache
from importlib import metadata
from pathlib import Path

PACKAGE_ROOT = Path(__file__).resolve().parents[2]
LOCK_FILE = PACKAGE_ROOT / "requirements.lock"
OWN_DISTRIBUTION = "gopre"
CODE_VERSION_ENV = "GOPRE_CODE_VERSION"  # an image's commit (docker/Dockerfile's GIT_COMMIT build argument)
INSTALLERS = {"pip", "setuptools", "wheel"}  # what installs packages, not what runs (pip freeze omits them)


def _git(root: Path, *args: str) -> str | None:
    try:
        out = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


@lru_cache(maxsize=None)
def code_version(root: Path = PACKAGE_ROOT) -> str:
    commit = _git(root, "rev-parse", "--short=12", "HEAD")
    if commit:
        dirty = _git(root, "status", "--porcelain", "--untracked-files=no")
        return commit + ("-dirty" if dirty else "")
    baked = os.environ.get(CODE_VERSION_ENV, "").strip()
    if baked and baked != "unknown":
        return baked
    try:
        return f"gopre {metadata.version('gopre')}"
    except metadata.PackageNotFoundError:
        return "unknown"


def stale_versions(finished: dict[str, str | None], current: str) -> dict[str, int]:
    """Of the finished jobs (config hash -> code version), how many each older version made."""
    counts: dict[str, int] = {}
    for version in finished.values():
        if version != current:
            key = version or "unrecorded"
            counts[key] = counts.get(key, 0) + 1
    return counts


@dataclass(frozen=True)
class Environment:
    """packages: sha256 (12 hex) of the sorted ``name==version`` of every installed distribution
    but gopre itself; locked: they are exactly the lock file's pins (None: no lock file beside the
    code); cpu: the CPU model; python: the interpreter's version; numerics: the arithmetic's code
    paths on this machine (``numeric_paths``), which move the last digits of a result."""

    packages: str
    locked: bool | None
    cpu: str
    python: str
    numerics: str = ""

    def to_dict(self) -> dict:
        return asdict(self)


def _canonical(name: str) -> str:
    return name.lower().replace("_", "-").replace(".", "-")


def installed_pins() -> dict[str, str]:
    """Every distribution installed in site-packages (canonical name -> version), gopre itself and
    the installers (pip, setuptools, wheel) left out."""
    import site
    sites = [*site.getsitepackages(), site.getusersitepackages()]
    pins = {}
    # site-packages only: what pip installed, not what a package vendors onto sys.path (Ray puts
    # its thirdparty_files first once imported, which would make a driver and its workers differ)
    for dist in metadata.distributions(path=[p for p in sites if Path(p).is_dir()]):
        name = dist.metadata["Name"]
        if name and _canonical(name) != OWN_DISTRIBUTION and _canonical(name) not in INSTALLERS:
            pins[_canonical(name)] = dist.version
    return pins


def read_lock(path: Path = LOCK_FILE) -> dict[str, str]:
    """``requirements.lock``'s pins (canonical name -> version); comments and blank lines skipped."""
    pins = {}
    for number, line in enumerate(path.read_text().splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        name, sep, version = line.partition("==")
        if not sep:
            raise ValueError(f"{path}:{number}: every line pins one version (name==version), got {line!r}")
        pins[_canonical(name.split("[", 1)[0].strip())] = version.strip()
    return pins


def lock_differences(installed: dict[str, str], locked: dict[str, str]) -> list[str]:
    """What differs from the lock: a locked package missing or at another version (a local build
    label such as torch's ``+cpu`` is the same release), or a package the lock does not list."""
    out = []
    for name, version in sorted(locked.items()):
        have = installed.get(name)
        if have is None:
            out.append(f"{name}: locked {version}, not installed")
        elif have.split("+", 1)[0] != version.split("+", 1)[0]:
            out.append(f"{name}: locked {version}, installed {have}")
    out += [f"{name}: installed {installed[name]}, not in the lock" for name in sorted(set(installed) - set(locked))]
    return out


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def numeric_paths() -> str:
    """Which vector code paths the arithmetic takes here, as one line: torch's CPU kernels (its
    capability: DEFAULT, AVX2, AVX512; ``ATEN_CPU_CAPABILITY`` lowers it), MKL's branch
    (``MKL_CBWR``; auto: MKL picks by the CPU) and the CPU numba compiles the kernels for
    (``NUMBA_CPU_NAME``, else the host's). The same code and packages give other digits on
    another path (measured in ``reports/reproduce/README.md``)."""
    import torch  # when asked: reading records needs no torch
    try:
        import llvmlite.binding as llvm
        numba_cpu = os.environ.get("NUMBA_CPU_NAME") or llvm.get_host_cpu_name()
    except Exception:  # noqa: BLE001 - provenance must never fail a job
        numba_cpu = "unknown"
    return (f"torch {torch.backends.cpu.get_cpu_capability()}, MKL {os.environ.get('MKL_CBWR', 'auto')}, "
            f"numba {numba_cpu}")


def packages_digest(pins: dict[str, str]) -> str:
    """The short digest of installed packages (``installed_pins``), local version labels ignored."""
    text = "\n".join(f"{name}=={version.split('+', 1)[0]}" for name, version in sorted(pins.items()))
    return hashlib.sha256(text.encode()).hexdigest()[:12]


@lru_cache(maxsize=None)
def environment() -> Environment:
    installed = installed_pins()
    locked = None
    if LOCK_FILE.exists():
        locked = not lock_differences(installed, read_lock())
    return Environment(packages_digest(installed), locked, cpu_model(), platform.python_version(), numeric_paths())
