"""Run model-written Python code in a separate, limited, isolated process.

``await Sandbox().run(code, stdin=..., files=...)`` returns a :class:`SandboxResult`; it never raises
for anything the code does. Limits (:class:`SandboxLimits`): CPU time (RLIMIT_CPU), wall time (the
whole sandbox is killed), address space (RLIMIT_AS), output size (each stream read concurrently and
cut at the limit, which ends the run), processes (RLIMIT_NPROC counted in a user namespace of the
run's own), file size and disk (a size-limited tmpfs), open files. Isolation (the default, which
needs Linux namespaces: root, or a user with unprivileged user namespaces): no network (a fresh
network namespace), a private PID namespace, a root filesystem holding only the system directories and
the Python installation read-only, a fresh /tmp as the working directory, and an unprivileged uid.
Where namespaces cannot be made, a Sandbox refuses to start unless the weaker ``process`` isolation
is asked for by name: the code then runs as a uid of its own (root) with sockets refused (a seccomp
filter where the kernel takes one, else in Python only), and processes that leave its session are
hunted down afterwards. ``docs/agents.md`` has the details.
"""

from __future__ import annotations

import asyncio
import dataclasses
import enum
import errno
import fcntl
import functools
import json
import logging
import math
import os
import pwd
import secrets
import shutil
import signal
import stat
import subprocess
import sys
import tempfile
import time
import weakref
from collections.abc import Mapping
from pathlib import Path

from infinirl.agents.sandbox_launch import SYSTEM_PATHS
from infinirl.agents.sandbox_runner import MEMORY_EXIT_CODE

__all__ = ["ISOLATIONS", "LimitHit", "Sandbox", "SandboxLimits", "SandboxResult"]

logger = logging.getLogger(__name__)

ISOLATIONS = ("auto", "namespaces", "process")
LAUNCHER = Path(__file__).with_name("sandbox_launch.py")
RUNNER_SOURCE = Path(__file__).with_name("sandbox_runner.py").read_text(encoding="utf-8")
CODE_NAME = "main.py"
NOBODY = 65534
# Under the "process" isolation as root, each run gets a uid (and gid) of this many from
# SandboxLimits.process_uid_base, held exclusively machine-wide for the run (a lock file per uid).
PROCESS_UID_COUNT = 1024
PROBE_TIMEOUT_S = 60.0
MAX_REMOVE_PASSES = 4096  # each opens one more level of folders the code closed; paths end at 4096 bytes
CGROUP_NAME = "infinirl-sandbox"  # under the cgroup v2 root: one child cgroup per run
CGROUP_EXTRA_TASKS = 2  # the launcher and init (namespaces) share the run's pids.max with the code
CGROUP_REMOVE_S = 2.0  # killed processes leave the cgroup within milliseconds; this only bounds a bug
READ_CHUNK = 65536
DRAIN_AFTER_EXIT_S = 5.0  # after the sandbox is dead its pipes close at once; this only bounds a bug
ESCAPE_GRACE_S = 0.5  # after the launcher is gone, how long its pipes may stay open before holders are hunted
EXIT_POLL_S = 0.01
ESCAPE_SWEEPS = 5  # rounds of killing escaped processes: each round also gets the children of the last
# Every process the code starts inherits this variable (unless it clears its environment), so the ones
# that leave the launcher's session can still be found and killed under the "process" isolation.
RUN_TOKEN_VARIABLE = "INFINIRL_SANDBOX_RUN"
# Numeric libraries start one thread per core by default, each reserving address space.
CODE_ENV = {
    "PATH": "/usr/local/bin:/usr/bin:/bin",
    "LANG": "C.UTF-8",
    "PYTHONDONTWRITEBYTECODE": "1",
    "PYTHONIOENCODING": "utf-8",
    "PYTHONUNBUFFERED": "1",
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
}


class LimitHit(enum.StrEnum):
    """The limit that ended (or, for processes, constrained) a run."""

    WALL_TIME = "wall_time"
    CPU_TIME = "cpu_time"
    MEMORY = "memory"
    OUTPUT = "output"
    PROCESSES = "processes"


@dataclasses.dataclass(kw_only=True, frozen=True)
class SandboxLimits:
    """What one run may use. Sizes in bytes, times in seconds."""

    wall_time_s: float = 10.0
    cpu_time_s: float = 5.0
    memory_bytes: int = 1 << 30  # address space: an interpreter with numpy needs a few hundred MiB
    max_output_bytes: int = 64 << 10  # per stream
    max_processes: int = 32
    max_file_bytes: int = 16 << 20
    disk_bytes: int = 64 << 20  # the working directory's tmpfs (namespaces isolation)
    max_open_files: int = 256
    isolation: str = "auto"  # "auto" and "namespaces" need namespaces; "process" never tries them
    sandbox_uid: int = NOBODY  # the uid the code runs as under namespaces when the sandbox is started by root
    sandbox_gid: int = NOBODY
    # "process" as root: each run's uid is one of PROCESS_UID_COUNT from here (without an account).
    process_uid_base: int = 62000
    # "process" without root runs the code as this process's own uid: it could signal this process
    # or change its files. Refused unless this is set.
    allow_same_uid: bool = False

    def __post_init__(self) -> None:
        for name in ("wall_time_s", "cpu_time_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"SandboxLimits.{name} must be > 0 seconds, got {getattr(self, name)!r}")
        for name in ("memory_bytes", "max_output_bytes", "max_processes", "max_file_bytes", "disk_bytes",
                     "max_open_files"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"SandboxLimits.{name} must be a positive integer, got {value!r}")
        if self.isolation not in ISOLATIONS:
            raise ValueError(f"SandboxLimits.isolation must be one of {ISOLATIONS}, got {self.isolation!r}")
        if self.sandbox_uid == 0 or self.sandbox_gid == 0:
            raise ValueError("SandboxLimits.sandbox_uid/sandbox_gid must not be 0 (root); use e.g. 65534")
        if not isinstance(self.process_uid_base, int) or self.process_uid_base < 1:
            raise ValueError(f"SandboxLimits.process_uid_base must be a positive uid, got {self.process_uid_base!r}")
        if not isinstance(self.allow_same_uid, bool):
            raise ValueError(f"SandboxLimits.allow_same_uid must be true or false, got {self.allow_same_uid!r}")


@dataclasses.dataclass(kw_only=True, frozen=True)
class SandboxResult:
    """What a run produced. ``exit_code`` is None when the process was killed (``signal`` says by
    what, when known); ``limit`` names the limit hit, if any; ``error`` is set when the sandbox
    itself could not run the code (then nothing ran)."""

    stdout: str
    stderr: str
    exit_code: int | None
    signal: int | None = None
    limit: LimitHit | None = None
    wall_time_s: float
    cpu_time_s: float | None = None
    stdout_truncated: bool = False
    stderr_truncated: bool = False
    isolation: str = ""  # "namespaces" or "process"
    isolation_note: str = ""  # under "process": that it was asked for
    cgroup: bool = False  # the run had a cgroup of its own holding its memory and processes in total
    error: str | None = None

    @property
    def ok(self) -> bool:
        """Ran to completion with exit code 0 and within every limit."""
        return self.exit_code == 0 and self.limit is None and self.error is None


class BoundedReader:
    """Reads a pipe to EOF, keeping the first ``limit`` bytes; ``overflow`` is set past it."""

    def __init__(self, stream: asyncio.StreamReader, limit: int, overflow: asyncio.Event) -> None:
        self.stream, self.limit, self.overflow = stream, limit, overflow
        self.data = bytearray()
        self.truncated = False

    async def read(self) -> None:
        while chunk := await self.stream.read(READ_CHUNK):
            room = self.limit - len(self.data)
            self.data += chunk[:room]
            if len(chunk) > room:
                self.truncated = True
                self.overflow.set()

    def text(self) -> str:
        return self.data.decode("utf-8", errors="replace")


# Run by the code's interpreter (``-I -S``): what of its installation the code needs, and where its
# site-packages would be. The shared libraries it has mapped (libpython, when it is not in a system
# folder) and those beside libpython are needed too; a virtual environment's pyvenv.cfg keeps a copied
# interpreter finding its standard library.
INTERPRETER_PROBE = """
import glob, json, os, site, sys, sysconfig
executable = os.path.realpath(sys.executable)
libraries = set()
with open("/proc/self/maps") as maps:
    for line in maps:
        parts = line.split(None, 5)
        if len(parts) == 6 and parts[5].startswith("/") and os.path.isfile(parts[5].strip()):
            libraries.add(parts[5].strip())
libdir = sysconfig.get_config_var("LIBDIR") or ""
libraries.update(path for path in glob.glob(os.path.join(libdir, "*.so*")) if os.path.isfile(path))
folder = os.path.dirname(executable)
configs = [os.path.join(f, "pyvenv.cfg") for f in (folder, os.path.dirname(folder))]
print(json.dumps({
    "executable": executable,
    "paths": [executable] + [p for p in sys.path if os.path.isdir(p)] + sorted(libraries)
             + [c for c in configs if os.path.isfile(c)],
    "site": site.getsitepackages() + [site.getusersitepackages()],
}))
"""


@functools.cache
def interpreter_files(python: str) -> dict:
    """``executable`` (the real file, run in the sandbox), ``paths`` (the files and folders of the
    interpreter to mount read-only: the binary, the standard library with lib-dynload, its shared
    libraries, never site-packages) and ``site`` (site-packages folders, hidden where a mounted
    folder holds them) of ``python``, asked of it once per process. ValueError if it cannot run."""
    try:
        probe = subprocess.run([python, "-I", "-S", "-c", INTERPRETER_PROBE], capture_output=True, text=True,
                               timeout=PROBE_TIMEOUT_S, stdin=subprocess.DEVNULL, env=CODE_ENV)
        found = json.loads(probe.stdout)
    except (OSError, subprocess.TimeoutExpired, ValueError) as error:
        raise ValueError(f"Sandbox python {python!r} could not tell where its standard library is: {error}") from None
    system = tuple(path.rstrip("/") + "/" for path in SYSTEM_PATHS)
    # What a system folder holds is mounted with it; site-packages are left out.
    paths = sorted({path for path in found["paths"] if not (path + "/").startswith(system) and path != "/"})
    return {"executable": found["executable"], "paths": paths, "site": sorted(set(found["site"]))}


def check_file_name(name: str) -> str:
    parts = Path(name).parts
    if not name or Path(name).is_absolute() or ".." in parts or name == CODE_NAME:
        raise ValueError(f"sandbox file name {name!r} must be a relative path inside the working directory "
                         f"(no '..', not {CODE_NAME!r})")
    return name


def to_bytes(text: str | bytes) -> bytes:
    """UTF-8, lone surrogates included as their (invalid) three bytes: text no encoder takes is the
    code's to fail on (Python reports what it cannot decode), not a reason for the sandbox to raise."""
    return text.encode("utf-8", "surrogatepass") if isinstance(text, str) else text


def write_files(work_dir: Path, code: str, files: Mapping[str, str | bytes]) -> None:
    (work_dir / CODE_NAME).write_bytes(to_bytes(code))
    for name, content in files.items():
        target = work_dir / check_file_name(name)
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(to_bytes(content))


def close_to_the_code(work: Path, gid: int) -> None:
    """The "process" isolation's working directory (root): every folder root's, writable by the run's
    group and sticky, every file given (``main.py`` included) root's and read-only. The code can add
    files but cannot change, remove or rename the ones it was given; no other run's uid can enter."""
    for folder, _, files in os.walk(work):
        os.chown(folder, 0, gid)
        os.chmod(folder, 0o1770)
        for name in files:
            os.lchown(os.path.join(folder, name), 0, 0)
            os.chmod(os.path.join(folder, name), 0o444)


def base_dir() -> Path:
    """The folder holding every run's folder: this uid's own, and listable by no one else (root's is
    0o711 so that a "process" run's uid can pass through it to its own run's folder, whose random
    name it cannot learn from a listing)."""
    path = Path(tempfile.gettempdir()) / f"infinirl-sandbox-{os.getuid()}"
    mode = 0o711 if os.getuid() == 0 else 0o700
    try:
        path.mkdir(mode=mode)
    except FileExistsError:
        pass
    info = os.lstat(path)
    if not stat.S_ISDIR(info.st_mode) or info.st_uid != os.getuid():
        raise OSError(f"{path} is not a folder of uid {os.getuid()} (someone else made it); remove it")
    if stat.S_IMODE(info.st_mode) != mode:
        os.chmod(path, mode)
    return path


def has_account(uid: int) -> bool:
    try:
        pwd.getpwuid(uid)
    except KeyError:
        return False
    return True


class UidLease:
    """A uid (and the gid of the same number) for one "process" run under root, held by no other run
    of any process on this machine until :meth:`release` (an exclusive lock on a file per uid).
    Uids with an account are skipped: the code must not get someone's files."""

    def __init__(self, first: int) -> None:
        locks = base_dir() / "uids"
        locks.mkdir(mode=0o700, exist_ok=True)
        start = secrets.randbelow(PROCESS_UID_COUNT)
        for step in range(PROCESS_UID_COUNT):
            uid = first + (start + step) % PROCESS_UID_COUNT
            if has_account(uid):
                continue
            fd = os.open(locks / str(uid), os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                continue
            self.uid, self.fd = uid, fd
            return
        raise OSError(f"every sandbox uid of {first}..{first + PROCESS_UID_COUNT - 1} is in use or has an account; "
                      "set SandboxLimits.process_uid_base to a free range")

    def release(self) -> None:
        os.close(self.fd)


@functools.cache
def namespaces_problem() -> str | None:
    """Why this process cannot build the namespaces isolation (None when it can): the launcher tries
    the namespaces, a private mount namespace and a tmpfs in a throwaway child. Asked once per process."""
    try:
        probe = subprocess.run([sys.executable, "-I", "-S", str(LAUNCHER), "--probe"], capture_output=True,
                               text=True, timeout=PROBE_TIMEOUT_S, stdin=subprocess.DEVNULL)
    except (OSError, subprocess.TimeoutExpired) as error:
        return f"the namespaces probe failed: {error}"
    if probe.returncode == 0:
        return None
    return (probe.stderr.strip().splitlines() or [f"exit code {probe.returncode}"])[-1]


def isolation_problem(limits: SandboxLimits) -> str | None:
    """Why runs with ``limits`` must not start here (one line naming the option), or None."""
    if limits.isolation == "process":
        if os.getuid() != 0 and not limits.allow_same_uid:
            return ("SandboxLimits.isolation='process' without root runs the code as this process's own uid, which "
                    "could kill this process or change its files; run as root, use isolation='auto' (namespaces), "
                    "or set SandboxLimits.allow_same_uid=True to accept that")
        return None
    problem = namespaces_problem()
    if problem is None:
        return None
    return (f"SandboxLimits.isolation={limits.isolation!r} needs Linux namespaces, which this process cannot make "
            f"({problem}); run as root or with unprivileged user namespaces (in Docker: a seccomp profile that "
            "allows unshare and CAP_SYS_ADMIN), or set isolation='process' to accept the weaker process isolation "
            "(docs/agents.md)")


def remove_tree(path: Path) -> None:
    """Remove a run's folder whatever the code did to the modes of what it wrote there (a folder
    closed with mode 0, nested ones too). Never raises: what cannot be removed is logged."""
    opened = 0
    top = os.path.abspath(path)

    def open_up(function, failed_path, _):
        # The next pass retries; the failed entry and its folder are opened up for it (one more
        # level of closed folders per pass), never a folder above the tree (the runs' base folder).
        nonlocal opened
        for folder in (failed_path, os.path.dirname(failed_path)):
            try:
                inside = os.path.abspath(folder) == top or os.path.abspath(folder).startswith(top + os.sep)
                mode = os.lstat(folder).st_mode
                if inside and stat.S_ISDIR(mode) and stat.S_IMODE(mode) & 0o700 != 0o700:
                    os.chmod(folder, stat.S_IMODE(mode) | 0o700)
                    opened += 1
            except OSError:
                pass

    try:
        for _ in range(MAX_REMOVE_PASSES):
            opened = 0
            shutil.rmtree(path, onerror=open_up)
            if not os.path.lexists(path):
                return
            if not opened:  # nothing more could be opened up: another pass would fail the same way
                break
    except Exception as error:  # noqa: BLE001 - cleanup must not turn a run's result into an exception
        logger.warning("could not remove the sandbox folder %s: %s", path, error)
        return
    logger.warning("could not remove the sandbox folder %s: some entries refuse removal", path)


async def read_status(fd: int) -> dict:
    """Merge the JSON lines the launcher wrote. Its writers are dead or dying by now; the deadline
    only bounds a bug, so a stuck writer cannot hang the caller."""
    os.set_blocking(fd, False)
    chunks = []
    deadline = time.monotonic() + DRAIN_AFTER_EXIT_S
    while time.monotonic() < deadline:
        try:
            chunk = os.read(fd, READ_CHUNK)
        except BlockingIOError:
            await asyncio.sleep(0.01)
            continue
        if not chunk:
            break
        chunks.append(chunk)
    status: dict = {}
    for line in b"".join(chunks).decode("utf-8", errors="replace").splitlines():
        try:
            status.update(json.loads(line))
        except json.JSONDecodeError:
            status.setdefault("error", f"unreadable sandbox status line {line[:200]!r}")
    return status


def limit_from(status: dict, limits: SandboxLimits, killed_for: LimitHit | None, truncated: bool,
               cgroup_events: dict[str, int] | None = None) -> LimitHit | None:
    """The limit to report: the one the run was killed for, except that a process limit reached
    on the way explains a fork bomb's wall-time kill better. ``cgroup_events``: what the run's
    cgroup counted (``oom_kill``: processes the memory limit killed; ``pids_max``: forks refused)."""
    events = cgroup_events or {}
    if killed_for is not None:
        return LimitHit.PROCESSES if status.get("limit") == "processes" or events.get("pids_max") else killed_for
    if truncated:
        return LimitHit.OUTPUT
    if status.get("returncode") == MEMORY_EXIT_CODE or events.get("oom_kill"):
        return LimitHit.MEMORY
    sig = status.get("signal")
    if sig == signal.SIGXCPU or (sig == signal.SIGKILL and status.get("cpu_time_s", 0) >= limits.cpu_time_s):
        return LimitHit.CPU_TIME
    if status.get("limit") == "processes" or events.get("pids_max"):
        return LimitHit.PROCESSES
    return None


def cgroup2_mount(mountinfo: str) -> Path | None:
    """Where the cgroup v2 hierarchy is mounted, from /proc/self/mountinfo's text; None if nowhere."""
    for line in mountinfo.splitlines():
        fields, _, filesystem = line.partition(" - ")
        if filesystem.split(" ", 1)[0] == "cgroup2" and len(fields.split()) > 4:
            return Path(fields.split()[4].replace("\\040", " "))
    return None


def enable_controllers(folder: Path, controllers: tuple[str, ...]) -> None:
    """Make ``controllers`` available to the child cgroups of ``folder`` (a no-op where they are)."""
    enabled = (folder / "cgroup.subtree_control").read_text().split()
    missing = [name for name in controllers if name not in enabled]
    if missing:
        (folder / "cgroup.subtree_control").write_text(" ".join(f"+{name}" for name in missing))


@functools.cache
def cgroup_parent() -> tuple[Path | None, str]:
    """The cgroup v2 folder that holds each run's own cgroup, with the memory and pids controllers on
    for its children: ``(folder, "")``, or ``(None, why there is none)``. It is made at the root of
    the hierarchy (a cgroup holding processes cannot give controllers to children). Once per process."""
    if os.getuid() != 0:
        return None, "not root"
    try:
        mount = cgroup2_mount(Path("/proc/self/mountinfo").read_text())
        if mount is None:
            return None, "no cgroup v2 hierarchy is mounted"
        missing = {"memory", "pids"} - set((mount / "cgroup.controllers").read_text().split())
        if missing:
            return None, f"the cgroup v2 hierarchy at {mount} lacks the {sorted(missing)} controllers (v1 has them)"
        enable_controllers(mount, ("memory", "pids"))
        parent = mount / CGROUP_NAME
        parent.mkdir(mode=0o755, exist_ok=True)
        enable_controllers(parent, ("memory", "pids"))
    except OSError as error:
        return None, f"cannot set up the runs' cgroups: {error}"
    return parent, ""


@functools.cache
def warn_without_cgroup(why: str) -> None:
    logger.warning("Sandbox runs get no cgroup of their own (%s): memory_bytes then limits each process's address "
                   "space only, so a run of several processes may use up to max_processes times it", why)


class RunCgroup:
    """One run's cgroup: memory.max (swap 0) of ``memory_bytes`` and pids.max of ``max_processes``
    (plus the launcher and init) for all its processes together. The launcher joins it before it
    starts anything, so everything of the run is inside; closing it kills whatever is left."""

    def __init__(self, parent: Path, limits: SandboxLimits) -> None:
        self.path = parent / secrets.token_hex(16)
        self.path.mkdir(mode=0o755)
        try:
            (self.path / "memory.max").write_text(str(limits.memory_bytes))
            if (self.path / "memory.swap.max").exists():
                (self.path / "memory.swap.max").write_text("0")
            (self.path / "pids.max").write_text(str(limits.max_processes + CGROUP_EXTRA_TASKS))
        except OSError:
            self.path.rmdir()
            raise

    def events(self) -> dict[str, int]:
        """``oom_kill`` (processes the memory limit killed) and ``pids_max`` (forks refused)."""
        counts = {}
        for name, key, field in (("memory.events", "oom_kill", "oom_kill"), ("pids.events", "pids_max", "max")):
            try:
                for line in (self.path / name).read_text().splitlines():
                    if line.split()[:1] == [field]:
                        counts[key] = int(line.split()[1])
            except (OSError, ValueError, IndexError):
                pass
        return counts

    async def close(self) -> None:
        """Kill every process left in the cgroup and remove it; a failure is logged, never raised."""
        try:
            if (self.path / "cgroup.kill").exists():
                (self.path / "cgroup.kill").write_text("1")
            else:
                for pid in (self.path / "cgroup.procs").read_text().split():
                    try:
                        os.kill(int(pid), signal.SIGKILL)
                    except ProcessLookupError:
                        pass
        except OSError as error:
            logger.warning("could not kill what was left in the sandbox cgroup %s: %s", self.path, error)
        deadline = time.monotonic() + CGROUP_REMOVE_S
        while True:
            try:
                self.path.rmdir()
                return
            except OSError as error:
                if error.errno != errno.EBUSY or time.monotonic() > deadline:
                    logger.warning("could not remove the sandbox cgroup %s: %s", self.path, error)
                    return
            await asyncio.sleep(0.01)


class Sandbox:
    """Runs code with :class:`SandboxLimits`; at most ``max_concurrent`` runs at once (per event loop).
    ``python`` is the interpreter for the code (default: this one); with the "process" isolation
    under root, the sandbox uid must be able to execute it.

    Safe to share between coroutines; each run gets its own folder, processes and namespaces.
    """

    def __init__(
        self, limits: SandboxLimits | None = None, *, max_concurrent: int = 4, python: str | None = None
    ) -> None:
        if max_concurrent < 1:
            raise ValueError(f"Sandbox max_concurrent must be >= 1, got {max_concurrent}")
        self.python = python or sys.executable  # the interpreter that runs the code
        if not (os.path.isfile(self.python) and os.access(self.python, os.X_OK)):
            raise ValueError(f"Sandbox python {self.python!r} is not an executable file")
        self.interpreter = interpreter_files(os.path.abspath(self.python))
        self.limits = limits or SandboxLimits()
        problem = isolation_problem(self.limits)
        if problem is not None:
            raise ValueError(problem)
        if cgroup_parent()[0] is None:
            warn_without_cgroup(cgroup_parent()[1])
        if self.limits.isolation == "process":
            logger.warning("Sandbox with isolation='process': the code runs without namespaces, so it can read every "
                           "world-readable file (installed data sets' answer keys included) and see the machine's "
                           "processes; use it only where namespaces cannot be had (docs/agents.md)")
        self.max_concurrent = max_concurrent
        self._slots: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()

    def _semaphore(self) -> asyncio.Semaphore:
        loop = asyncio.get_running_loop()
        if loop not in self._slots:
            self._slots[loop] = asyncio.Semaphore(self.max_concurrent)
        return self._slots[loop]

    async def run(
        self,
        code: str,
        *,
        stdin: str | bytes | None = None,
        files: Mapping[str, str | bytes] | None = None,
        limits: SandboxLimits | None = None,
    ) -> SandboxResult:
        """Run ``code`` as a Python program; ``files`` (relative names) are written into its working
        directory first. Raises ValueError only for a bad file name; whatever the code does is in the
        result, and so is a ``limits`` whose isolation cannot be had here (``error``)."""
        limits = limits or self.limits
        for name in files or {}:
            check_file_name(name)
        problem = isolation_problem(limits)
        if problem is not None:
            return SandboxResult(stdout="", stderr="", exit_code=None, wall_time_s=0.0, error=problem)
        async with self._semaphore():
            try:
                folder = base_dir() / secrets.token_hex(16)
                folder.mkdir(mode=0o700)
            except OSError as error:
                return SandboxResult(stdout="", stderr="", exit_code=None, wall_time_s=0.0,
                                     error=f"sandbox could not make the run's folder: {error}")
            try:
                return await self._run_in(folder, code, stdin, files or {}, limits)
            finally:
                remove_tree(folder)

    def run_sync(self, code: str, **kwargs) -> SandboxResult:
        """:meth:`run` from synchronous code (not from inside a running event loop)."""
        return asyncio.run(self.run(code, **kwargs))

    def _config(self, folder: Path, limits: SandboxLimits, status_fd: int, token: str, uid: int,
                cgroup: RunCgroup | None) -> dict:
        return {
            "status_fd": status_fd,
            "cgroup": str(cgroup.path) if cgroup is not None else None,
            "isolation": limits.isolation,
            "limits": {
                "cpu_time_s": math.ceil(limits.cpu_time_s),
                "memory_bytes": limits.memory_bytes,
                "max_file_bytes": limits.max_file_bytes,
                "max_open_files": limits.max_open_files,
                "max_processes": limits.max_processes,
                "disk_bytes": limits.disk_bytes,
            },
            "sandbox_uid": uid,
            "sandbox_gid": uid if limits.isolation == "process" and os.getuid() == 0 else code_gid(limits),
            "host_work_dir": str(folder / "work"),
            "host_root_dir": str(folder / "root"),
            "read_only_paths": self.interpreter["paths"],
            "hidden_paths": self.interpreter["site"],
            "python": self.interpreter["executable"],
            "runner": RUNNER_SOURCE,
            "code_name": CODE_NAME,
            "env": {**CODE_ENV, RUN_TOKEN_VARIABLE: token},
        }

    def _prepare(self, folder: Path, code: str, files: Mapping[str, str | bytes], limits: SandboxLimits,
                 lease: UidLease | None) -> None:
        work = folder / "work"
        work.mkdir()
        (folder / "root").mkdir()
        write_files(work, code, files)
        if lease is not None:  # "process" under root: the code runs as the leased uid in this folder
            folder.chmod(0o711)
            close_to_the_code(work, lease.uid)

    async def _run_in(self, folder, code, stdin, files, limits) -> SandboxResult:
        started = time.monotonic()
        lease = None
        try:
            if limits.isolation == "process" and os.getuid() == 0:
                lease = UidLease(limits.process_uid_base)
            self._prepare(folder, code, files, limits, lease)
        except OSError as error:
            if lease is not None:
                lease.release()
            return SandboxResult(stdout="", stderr="", exit_code=None, wall_time_s=0.0,
                                 error=f"sandbox could not prepare the run: {error}")
        uid = lease.uid if lease is not None else code_uid(limits)
        cgroup, cgroup_events = None, {}
        parent, _ = cgroup_parent()
        if parent is not None:
            try:
                cgroup = RunCgroup(parent, limits)
            except OSError as error:
                logger.warning("sandbox run without a cgroup of its own: %s", error)
        status_read, status_write = os.pipe()
        token = secrets.token_hex(16)
        status: dict = {}
        try:
            config_path = folder / "config.json"
            config_path.touch(mode=0o600)
            config_path.write_text(json.dumps(self._config(folder, limits, status_write, token, uid, cgroup)))
            process = await asyncio.create_subprocess_exec(
                sys.executable, "-I", "-S", str(LAUNCHER), str(config_path),
                stdin=asyncio.subprocess.PIPE if stdin is not None else asyncio.subprocess.DEVNULL,
                stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
                pass_fds=(status_write,), start_new_session=True, env=CODE_ENV,
            )
            os.close(status_write)
            status_write = -1
            outcome = await self._supervise(process, stdin, limits, token, uid)
            status = await read_status(status_read)
        finally:
            os.close(status_read)
            if status_write >= 0:
                os.close(status_write)
            if status.get("isolation") != "namespaces":
                # Killing the launcher's session misses processes that left it (setsid, setpgid) with
                # their stdio closed; a PID namespace takes everything, so only "process" needs this.
                # A leased uid is the run's alone: every process of it goes, whatever it did.
                kill_escaped(uid, token, every_process=lease is not None)
            if cgroup is not None:
                cgroup_events = cgroup.events()
                await cgroup.close()
            if lease is not None:
                lease.release()
        killed_for, out, err = outcome
        return SandboxResult(
            stdout=out.text(), stderr=err.text(),
            exit_code=status.get("returncode") if killed_for is None else None,
            signal=status.get("signal") if killed_for is None else signal.SIGKILL,
            limit=limit_from(status, limits, killed_for, out.truncated or err.truncated, cgroup_events),
            wall_time_s=time.monotonic() - started,
            cpu_time_s=status.get("cpu_time_s"),
            stdout_truncated=out.truncated, stderr_truncated=err.truncated,
            isolation=status.get("isolation", ""),
            isolation_note=status.get("reason", ""),
            cgroup=bool(status.get("cgroup")),
            error=status.get("error"),
        )

    async def _supervise(self, process, stdin, limits: SandboxLimits, token: str, uid: int):
        """Feed stdin, read both streams, and kill the sandbox's session at the wall-time limit or
        when an output stream passes its limit.

        A process that left the session (possible under the "process" isolation) may hold the
        output pipes open after the launcher is gone: such holders are killed, and every wait after
        the launcher's end or the wall-time kill is bounded, so whatever could not be killed cannot
        hang the caller (the run then reports the wall-time limit and the output read so far)."""
        loop = asyncio.get_running_loop()
        started = loop.time()
        overflow = asyncio.Event()
        out = BoundedReader(process.stdout, limits.max_output_bytes, overflow)
        err = BoundedReader(process.stderr, limits.max_output_bytes, overflow)
        pipes = pipe_inodes(process)
        readers = [asyncio.ensure_future(out.read()), asyncio.ensure_future(err.read())]
        feeder = asyncio.ensure_future(feed(process, stdin)) if stdin is not None else None
        # Not process.wait(): it also waits for the pipes to close, which an escaped process can prevent.
        exited = asyncio.ensure_future(wait_exit(process))
        overflowed = asyncio.ensure_future(overflow.wait())
        killed_for = None
        try:
            await asyncio.wait([exited, overflowed], timeout=limits.wall_time_s,
                               return_when=asyncio.FIRST_COMPLETED)
            if exited.done():
                # The launcher killed its session on the way out, so the pipes close at once unless a
                # process that left the session holds them: kill those, within the wall time.
                if not await settled(readers, ESCAPE_GRACE_S):
                    kill_escaped(uid, token, pipes)
                    left = limits.wall_time_s - (loop.time() - started)
                    if not await settled(readers, max(left, ESCAPE_GRACE_S)):
                        killed_for = LimitHit.WALL_TIME
            else:
                killed_for = LimitHit.OUTPUT if overflow.is_set() else LimitHit.WALL_TIME
                kill_session(process)
            if killed_for is not None and not await settled([exited, *readers], ESCAPE_GRACE_S):
                kill_escaped(uid, token, pipes)
                await settled([exited, *readers], DRAIN_AFTER_EXIT_S)
        finally:
            drained = all(reader.done() for reader in readers)
            for task in [*readers, overflowed, exited] + ([feeder] if feeder else []):
                task.cancel()
            if process.returncode is None:  # cancelled from outside: leave nothing running, and reap it
                kill_session(process)
                reaper = asyncio.ensure_future(wait_exit(process))
                await settled([reaper], DRAIN_AFTER_EXIT_S)
                reaper.cancel()
            if not drained:  # whatever still holds the pipes is not to keep these fds open here too
                kill_escaped(uid, token, pipes)
                close_pipes(process)
        return killed_for, out, err


async def feed(process, stdin: str | bytes) -> None:
    data = to_bytes(stdin)
    try:
        process.stdin.write(data)
        await process.stdin.drain()
        process.stdin.close()
    except (BrokenPipeError, ConnectionResetError):
        pass  # the code exited without reading all of it


def kill_session(process) -> None:
    """SIGKILL the launcher's session (its init follows by PDEATHSIG and takes the PID namespace)."""
    if process.returncode is None:
        try:
            os.killpg(process.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


async def wait_exit(process) -> int:
    """The launcher's exit status, as soon as it has exited (whatever still holds its pipes)."""
    while process.returncode is None:
        await asyncio.sleep(EXIT_POLL_S)
    return process.returncode


async def settled(tasks, timeout: float) -> bool:
    """Whether every task finished within ``timeout`` seconds (they are left running either way)."""
    _, pending = await asyncio.wait(tasks, timeout=timeout)
    return not pending


def code_uid(limits: SandboxLimits) -> int:
    """The uid the code runs as (as the host sees it), but for "process" under root (a leased one)."""
    return limits.sandbox_uid if os.getuid() == 0 else os.getuid()


def code_gid(limits: SandboxLimits) -> int:
    return limits.sandbox_gid if os.getuid() == 0 else os.getgid()


def pipe_inodes(process) -> set[int]:
    """The inodes of the run's stdout and stderr pipes: a process holding a write end of one of them
    belongs to the run (this process holds only the read ends)."""
    inodes = set()
    for fd in (1, 2):
        transport = process._transport.get_pipe_transport(fd)  # asyncio has no public accessor
        pipe = transport.get_extra_info("pipe") if transport is not None else None
        if pipe is not None:
            inodes.add(os.fstat(pipe.fileno()).st_ino)
    return inodes


def close_pipes(process) -> None:
    transport = getattr(process, "_transport", None)
    if transport is not None:
        transport.close()  # the launcher has exited: this only closes our ends of its pipes


def real_uid(pid: str) -> int:
    """The process's real uid. /proc/PID's owner is it, except that a process that made itself
    non-dumpable may show as root; its status file still tells."""
    owner = os.stat(f"/proc/{pid}").st_uid
    if owner != 0 or os.getuid() != 0:
        return owner
    with open(f"/proc/{pid}/status", "rb") as handle:
        for line in handle:
            if line.startswith(b"Uid:"):
                return int(line.split()[1])
    return owner


def belongs_to_run(pid: str, token: str, pipes: set[int]) -> bool:
    """Whether process ``pid`` carries the run's token in its environment or holds a write end of
    one of its output pipes."""
    try:
        with open(f"/proc/{pid}/environ", "rb") as handle:
            if f"{RUN_TOKEN_VARIABLE}={token}".encode() in handle.read().split(b"\0"):
                return True
        links = {f"pipe:[{inode}]" for inode in pipes}
        for fd in os.listdir(f"/proc/{pid}/fd") if links else ():
            if os.readlink(f"/proc/{pid}/fd/{fd}") in links:
                with open(f"/proc/{pid}/fdinfo/{fd}", "rb") as info:
                    flags = next(int(line.split()[1], 8) for line in info if line.startswith(b"flags:"))
                if flags & (os.O_WRONLY | os.O_RDWR):
                    return True
    except (OSError, StopIteration, ValueError):  # gone meanwhile, or not ours to inspect
        pass
    return False


def kill_if_of_run(pid: str, token: str, pipes: set[int], every_process: bool = False) -> bool:
    """SIGKILL process ``pid`` if it belongs to the run; whether it did. The signal goes through a
    pidfd opened before the process is inspected, so a pid recycled meanwhile is never hit (kernels
    without pidfds get a plain kill)."""
    try:
        handle = os.pidfd_open(int(pid))
    except OSError as error:
        if error.errno != errno.ENOSYS:
            return False  # gone already
        handle = None
    try:
        if not every_process and not belongs_to_run(pid, token, pipes):
            return False
        if handle is None:
            os.kill(int(pid), signal.SIGKILL)
        else:
            signal.pidfd_send_signal(handle, signal.SIGKILL)
        return True
    except OSError:
        return False
    finally:
        if handle is not None:
            os.close(handle)


def kill_escaped(uid: int, token: str, pipes: set[int] = frozenset(), every_process: bool = False) -> int:
    """SIGKILL every process of ``uid`` that belongs to the run (its token or its pipes; with
    ``every_process``, a uid leased to the run, all of them); the number killed. For the "process"
    isolation; without a leased uid it is best effort: a process that leaves the session, clears its
    environment and closes the run's pipes is not found."""
    me, total = os.getpid(), 0
    for _ in range(ESCAPE_SWEEPS):
        killed = 0
        for entry in os.listdir("/proc"):
            if not entry.isdigit() or int(entry) == me:
                continue
            try:
                if real_uid(entry) != uid:
                    continue
            except (OSError, ValueError):
                continue
            killed += kill_if_of_run(entry, token, pipes, every_process)
        total += killed
        if not killed:
            break
    return total
