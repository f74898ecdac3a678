"""Which isolation a sandbox gets, and what one run can do to another under the ``process`` isolation.

A trainer where namespaces cannot be made is simulated as Docker's default seccomp profile makes it:
a child process whose ``unshare`` system call fails with EPERM (a seccomp filter installed before it
starts); a trainer that is not root is the same child running as uid 65534.
"""

import asyncio
import ctypes
import json
import os
import platform
import shutil
import struct
import subprocess
import sys
import tempfile

import pytest

from infinirl.agents.sandbox import Sandbox, SandboxLimits

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
SHORT = {"wall_time_s": 8.0, "cpu_time_s": 6.0, "memory_bytes": 512 << 20, "max_processes": 8}
UNSHARE_X86_64 = 272
NOBODY = 65534


def become(uid: int):
    def preexec() -> None:
        os.setgroups([])
        os.setresgid(uid, uid, uid)
        os.setresuid(uid, uid, uid)

    return preexec


def process_python() -> str | None:
    """An interpreter a uid other than root can execute (the project's may sit in /root)."""
    for python in (sys.executable, shutil.which("python3") or "", "/usr/bin/python3"):
        if python and os.path.isfile(python):
            try:
                subprocess.run([python, "-c", "pass"], check=True, capture_output=True, preexec_fn=become(NOBODY))
            except (OSError, subprocess.CalledProcessError):
                continue
            return python
    return None


def trainer_python_for_nobody() -> str:
    """An interpreter uid 65534 can run that can import this checkout (a skip otherwise: the
    checkout may sit in a folder closed to that uid)."""
    if os.getuid() != 0:
        pytest.skip("needs root to start a trainer as another uid")
    python = process_python()
    if python is None:
        pytest.skip("no interpreter that uid 65534 can execute")
    probe = subprocess.run([python, "-c", "import infinirl.agents.sandbox"], capture_output=True, cwd="/tmp",
                           env={"PYTHONPATH": REPO}, preexec_fn=become(NOBODY))
    if probe.returncode != 0:
        pytest.skip(f"uid 65534 cannot import the checkout at {REPO}")
    return python


@pytest.fixture(scope="module")
def python_for_others():
    if os.getuid() != 0:
        pytest.skip("needs root: the process isolation's separate uids")
    python = process_python()
    if python is None:
        pytest.skip("no interpreter that uid 65534 can execute")
    return python


@pytest.fixture(scope="module")
def process_sandbox(python_for_others):
    return Sandbox(SandboxLimits(**SHORT, isolation="process"), max_concurrent=4, python=python_for_others)


def block_unshare_then(uid: int | None):
    """A preexec function: refuse ``unshare`` with EPERM (as Docker's seccomp profile does), then
    become ``uid`` (when given)."""

    def preexec() -> None:
        load, jump_eq, ret = 0x20, 0x15, 0x06
        allow, eperm = 0x7FFF0000, 0x00050000 | 1
        program = [(load, 0, 0, 0), (jump_eq, 0, 1, UNSHARE_X86_64), (ret, 0, 0, eperm), (ret, 0, 0, allow)]
        code = ctypes.create_string_buffer(b"".join(struct.pack("HBBI", *op) for op in program))

        class Program(ctypes.Structure):
            _fields_ = [("len", ctypes.c_ushort), ("filter", ctypes.c_void_p)]

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl.argtypes = [ctypes.c_int, ctypes.c_ulong, ctypes.c_void_p, ctypes.c_ulong, ctypes.c_ulong]
        fprog = Program(len(program), ctypes.addressof(code))
        if libc.prctl(38, 1, None, 0, 0) or libc.prctl(22, 2, ctypes.addressof(fprog), 0, 0):
            os._exit(99)
        if uid is not None:
            os.setgroups([])
            os.setresgid(uid, uid, uid)
            os.setresuid(uid, uid, uid)

    return preexec


def run_trainer(script: str, *, python: str = sys.executable, uid: int | None = None) -> dict:
    """Run ``script`` (which prints one JSON line) as a trainer process that cannot unshare."""
    if platform.machine() != "x86_64":
        pytest.skip("the unshare-refusing filter is written for x86_64")
    env = {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "PYTHONPATH": REPO, "HOME": "/tmp"}
    run = subprocess.run([python, "-c", script], capture_output=True, text=True, timeout=120, cwd="/tmp", env=env,
                         preexec_fn=block_unshare_then(uid))
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout.strip().splitlines()[-1])


TRY = """
import json, logging
from infinirl.agents.sandbox import Sandbox, SandboxLimits
warnings = []
logging.getLogger("infinirl.agents.sandbox").addHandler(logging.Handler())
logging.getLogger("infinirl.agents.sandbox").handlers[-1].emit = lambda record: warnings.append(record.getMessage())
def attempt(make):
    try:
        sandbox = make()
    except ValueError as error:
        return {"refused": str(error)}
    result = sandbox.run_sync("import os; print(os.getuid())")
    return {"isolation": result.isolation, "stdout": result.stdout, "error": result.error}
"""


def test_auto_without_namespaces_refuses_to_start_and_names_the_option():
    script = TRY + """
from infinirl.agents.coding.verifier import CodeTestsVerifier
from infinirl.agents.coding.env import CodeRunnerEnv
from infinirl.agents.tools import make_tool
print(json.dumps({
    "sandbox": attempt(lambda: Sandbox(SandboxLimits())),
    "verifier": attempt(lambda: CodeTestsVerifier().sandbox),
    "env": attempt(lambda: CodeRunnerEnv().sandbox),
    "tool": attempt(lambda: make_tool("python").sandbox),
    "namespaces": attempt(lambda: Sandbox(SandboxLimits(isolation="namespaces"))),
}))
"""
    outcome = run_trainer(script)
    for name, attempt in outcome.items():
        assert "refused" in attempt, (name, attempt)  # never a silent fallback to "process"
        message = attempt["refused"]
        assert "isolation" in message and "'process'" in message and "\n" not in message, message
        assert "unshare" in message, message


def test_an_explicit_process_isolation_as_root_runs_with_a_warning(python_for_others):
    script = TRY + f"""
result = attempt(lambda: Sandbox(SandboxLimits(isolation="process"), python={python_for_others!r}))
print(json.dumps({{**result, "warnings": warnings}}))
"""
    outcome = run_trainer(script)
    assert outcome["isolation"] == "process" and outcome["error"] is None, outcome
    assert int(outcome["stdout"]) not in (0, os.getuid()), outcome  # a uid of its own
    assert any("process" in warning and "namespaces" in warning for warning in outcome["warnings"]), outcome


def test_process_isolation_without_root_needs_its_own_opt_in():
    python = trainer_python_for_nobody()
    script = TRY + """
print(json.dumps({
    "auto": attempt(lambda: Sandbox(SandboxLimits())),
    "process": attempt(lambda: Sandbox(SandboxLimits(isolation="process"))),
    "opted_in": attempt(lambda: Sandbox(SandboxLimits(isolation="process", allow_same_uid=True))),
}))
"""
    outcome = run_trainer(script, python=python, uid=NOBODY)
    assert "refused" in outcome["auto"], outcome  # no fallback under auto
    assert "allow_same_uid" in outcome["process"].get("refused", ""), outcome
    assert outcome["opted_in"]["isolation"] == "process" and outcome["opted_in"]["stdout"] == f"{NOBODY}\n", outcome


# A run that looks for the other runs' folders (listing the temporary folder, or reading the config
# path off a launcher's command line) and replaces their main.py with a forged one.
ATTACKER = """
import glob, os, time
forged = "print('forged')\\n"
hits = set()
deadline = time.monotonic() + {seconds}
while time.monotonic() < deadline:
    paths = set()
    for root in {roots!r}:
        for depth in ("*", "*/*", "*/*/*"):
            paths.update(glob.glob(os.path.join(root, "infinirl-sandbox*", depth, "main.py")))
    for pid in os.listdir("/proc"):
        try:
            argv = open(f"/proc/{{pid}}/cmdline", "rb").read().split(b"\\0")
        except OSError:
            continue
        for arg in argv:
            if arg.endswith(b"config.json"):
                folder = os.path.dirname(arg.decode())
                paths.update(os.path.join(folder, sub, "main.py") for sub in ("", "work"))
    for path in paths:
        if os.path.realpath(os.path.dirname(path)) == os.path.realpath(os.getcwd()):
            continue
        try:
            os.unlink(path)
        except OSError:
            pass
        try:
            with open(path, "w") as handle:
                handle.write(forged)
            hits.add(path)
        except OSError:
            pass
print(len(hits))
"""


def test_a_process_run_cannot_replace_another_runs_code(process_sandbox):
    roots = sorted({"/tmp", tempfile.gettempdir()})

    async def main():
        attacker = asyncio.ensure_future(process_sandbox.run(ATTACKER.format(seconds=3.0, roots=roots)))
        await asyncio.sleep(0.5)
        victims = []
        while not attacker.done():
            victims.append(await process_sandbox.run("print('honest')"))
        return await attacker, victims

    attacker, victims = asyncio.run(main())
    assert attacker.exit_code == 0, attacker
    assert attacker.stdout == "0\n", attacker  # no other run's main.py could be written
    assert victims and all(v.stdout == "honest\n" for v in victims), victims


def test_a_process_run_cannot_list_the_runs_nor_change_its_own_files(process_sandbox):
    code = """
import os
base = os.path.dirname(os.path.dirname(os.getcwd()))
for attempt in (lambda: os.listdir(base), lambda: open("main.py", "w"), lambda: os.unlink("main.py"),
                lambda: os.rename("main.py", "other.py"), lambda: open("data.txt", "a")):
    try:
        attempt()
        print("allowed")
    except OSError as error:
        print(type(error).__name__)
open("mine.txt", "w").write("x")
print(open("mine.txt").read())
"""
    result = process_sandbox.run_sync(code, files={"data.txt": "given"})
    assert result.stdout.split() == ["PermissionError"] * 5 + ["x"], result


def test_concurrent_process_runs_get_uids_of_their_own(process_sandbox):
    async def main():
        return await asyncio.gather(*(process_sandbox.run("import os, time\ntime.sleep(1)\nprint(os.getuid())")
                                      for _ in range(3)))

    uids = [int(r.stdout) for r in asyncio.run(main())]
    assert len(set(uids)) == 3 and not {0, NOBODY, os.getuid()} & set(uids), uids


def test_cleanup_never_raises_even_for_folders_the_code_closed():
    """As a trainer without root (whose permissions the code's files can refuse), a run that leaves a
    folder it closed (mode 0) returns normally and leaves nothing; a folder that cannot be removed at
    all is logged, not raised."""
    python = trainer_python_for_nobody()
    script = TRY + """
import os, tempfile
from infinirl.agents.sandbox import base_dir, remove_tree
sandbox = Sandbox(SandboxLimits(isolation="process", allow_same_uid=True, wall_time_s=8.0))
before = set(os.listdir(base_dir()))
result = sandbox.run_sync("import os\\nos.makedirs('d/x')\\nos.chmod('d', 0)\\nprint('closed')")
left = sorted(set(os.listdir(base_dir())) - before)
stuck = tempfile.mkdtemp()
os.makedirs(os.path.join(stuck, "inner", "x"))
os.chmod(stuck, 0o555)  # its entries cannot be removed by anyone but root
remove_tree(os.path.join(stuck, "inner"))
os.chmod(stuck, 0o755)
remove_tree(stuck)
print(json.dumps({"stdout": result.stdout, "error": result.error, "left": left, "warnings": warnings,
                  "stuck": os.path.exists(stuck)}))
"""
    outcome = run_trainer(script, python=python, uid=NOBODY)
    assert outcome["stdout"] == "closed\n" and outcome["error"] is None, outcome
    assert outcome["left"] == [] and not outcome["stuck"], outcome
    assert any("could not remove" in warning for warning in outcome["warnings"]), outcome
