"""Builds the isolation for one sandboxed run and starts the code in it.

:mod:`infinirl.agents.sandbox` executes this file as a script (``python -I -S sandbox_launch.py
CONFIG``, or ``--probe`` to learn whether namespaces can be made here), so it imports only the
standard library and nothing of InfiniRL. Process tree::

    parent (Sandbox.run) -> launcher (this script, new session) -> init -> code

With namespaces (``isolation`` "namespaces"): the launcher unshares the network, PID, IPC and UTS
namespaces (and, when not root, a user namespace first, mapping its own uid); it forks ``init``, PID 1
of the new PID namespace. ``init`` unshares a mount namespace, builds a new root on a tmpfs holding
read-only binds of the system directories and of the Python installation, a fresh /proc, a minimal
/dev and a size-limited tmpfs /tmp (the working directory), pivots into it, and forks the code's
process. That process drops to the sandbox uid (when root), enters a user namespace of its own (so
RLIMIT_NPROC counts only its processes), sets the resource limits and ``no_new_privs``, and execs
the Python runner. When the code's process exits, ``init`` exits and the kernel kills everything
left in the PID namespace; ``init`` dies with the launcher (PDEATHSIG), so killing the launcher's
session kills the whole sandbox.

Without namespaces (``isolation`` "process", only when asked for: "auto" and "namespaces" fail where
the namespaces cannot be made): the code's process drops to the run's own uid when root, sets the
same limits, and the runner refuses sockets: a seccomp filter on the socket syscalls that
every process the code starts inherits (where the kernel takes one), and socket constructors that
raise, for a readable error. Files the uid can read stay readable; see docs/agents.md.

The launcher first sets its ``oom_score_adj`` to 1000 (inherited by the whole run: the OOM killer
takes the run's processes first) and joins the run's cgroup when the parent made one (memory.max
and pids.max for the run's processes together).

Everything the parent must know goes as JSON lines through the status pipe: the isolation achieved,
the cgroup joined, a limit seen (processes), the code's exit status and CPU time, or the error that
stopped the setup.
"""

import ctypes
import json
import os
import resource
import select
import shutil
import signal
import sys
import time

CLONE_NEWNS = 0x00020000
CLONE_NEWUTS = 0x04000000
CLONE_NEWIPC = 0x08000000
CLONE_NEWUSER = 0x10000000
CLONE_NEWPID = 0x20000000
CLONE_NEWNET = 0x40000000
MS_RDONLY = 1
MS_NOSUID = 2
MS_NODEV = 4
MS_NOEXEC = 8
MS_REMOUNT = 32
MS_BIND = 4096
MS_REC = 16384
MS_PRIVATE = 1 << 18
MNT_DETACH = 2
PR_SET_PDEATHSIG = 1
PR_SET_DUMPABLE = 4
PR_SET_NO_NEW_PRIVS = 38
# pivot_root has no glibc wrapper; numbers per architecture (asm-generic's is 41).
SYS_PIVOT_ROOT = {"x86_64": 155, "aarch64": 41, "riscv64": 41, "ppc64le": 203, "s390x": 217}
# Flags statvfs reports that a read-only bind remount must keep (a user namespace may not clear them).
KEPT_MOUNT_FLAGS = MS_NOSUID | MS_NODEV | MS_NOEXEC | 1024 | 2048  # + MS_NOATIME, MS_NODIRATIME

SYSTEM_PATHS = ("/usr", "/bin", "/sbin", "/lib", "/lib32", "/lib64", "/libx32", "/etc")
DEVICES = ("null", "zero", "full", "random", "urandom")
SANDBOX_TMP = "/tmp"
PROCESS_POLL_S = 0.05

LIBC = ctypes.CDLL(None, use_errno=True)
LIBC.mount.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_char_p, ctypes.c_ulong, ctypes.c_char_p]
LIBC.umount2.argtypes = [ctypes.c_char_p, ctypes.c_int]
LIBC.prctl.argtypes = [ctypes.c_int, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong]


class Status:
    """JSON lines to the parent through the status pipe (a line is one write: atomic on a pipe)."""

    def __init__(self, fd: int) -> None:
        os.set_inheritable(fd, False)  # the code's process must not write here
        self.fd = fd

    def send(self, **fields) -> None:
        os.write(self.fd, (json.dumps(fields) + "\n").encode())


def check(result: int, what: str) -> None:
    if result != 0:
        errno = ctypes.get_errno()
        raise OSError(errno, f"{what}: {os.strerror(errno)}")


def encode(text):
    return None if text is None else os.fsencode(text)


def unshare(flags: int) -> None:
    check(LIBC.unshare(flags), "unshare")


def mount(source, target, fstype, flags, data=None) -> None:
    check(LIBC.mount(encode(source), encode(target), encode(fstype), flags, encode(data)), f"mount {target}")


def prctl(option: int, value: int) -> None:
    check(LIBC.prctl(option, value, 0, 0, 0), f"prctl {option}")


def write_file(path: str, text: str) -> None:
    with open(path, "w") as handle:
        handle.write(text)


def map_own_ids(uid: int, gid: int) -> None:
    """Map the caller's uid/gid to themselves in the user namespace it just entered (the one mapping
    an unprivileged process may write)."""
    write_file("/proc/self/setgroups", "deny")
    write_file("/proc/self/uid_map", f"{uid} {uid} 1")
    write_file("/proc/self/gid_map", f"{gid} {gid} 1")


# ----------------------------------------------------------------------------- the new root


def bind_read_only(source: str, target: str) -> None:
    if os.path.isdir(source):
        os.makedirs(target, exist_ok=True)
    else:
        os.makedirs(os.path.dirname(target), exist_ok=True)
        open(target, "a").close()
    mount(source, target, None, MS_BIND | MS_REC)
    kept = os.statvfs(source).f_flag & KEPT_MOUNT_FLAGS
    mount(None, target, None, MS_REMOUNT | MS_BIND | MS_RDONLY | MS_NOSUID | kept)


def add_system_path(root: str, path: str) -> None:
    if os.path.islink(path):  # merged-/usr layouts: /lib -> usr/lib
        os.symlink(os.readlink(path), root + path)
    elif os.path.isdir(path):
        bind_read_only(path, root + path)


def add_devices(root: str) -> None:
    os.makedirs(root + "/dev")
    for name in DEVICES:
        if os.path.exists("/dev/" + name):
            open(f"{root}/dev/{name}", "a").close()
            mount("/dev/" + name, f"{root}/dev/{name}", None, MS_BIND)
    for name, target in (("fd", "/proc/self/fd"), ("stdin", "/proc/self/fd/0"),
                         ("stdout", "/proc/self/fd/1"), ("stderr", "/proc/self/fd/2")):
        os.symlink(target, f"{root}/dev/{name}")


def add_work_dir(root: str, config: dict) -> None:
    """A fresh tmpfs of the disk budget as /tmp, holding the run's files (copied from the host
    folder, which the code never sees)."""
    target = root + SANDBOX_TMP
    os.makedirs(target)
    size = config["limits"]["disk_bytes"]
    mount("tmpfs", target, "tmpfs", MS_NOSUID | MS_NODEV, f"size={size},mode=0700")
    shutil.copytree(config["host_work_dir"], target, dirs_exist_ok=True, symlinks=True)
    uid, gid = config["sandbox_uid"], config["sandbox_gid"]
    for folder, dirs, files in os.walk(target):
        for name in [folder] + [os.path.join(folder, entry) for entry in dirs + files]:
            os.lchown(name, uid, gid)


def pivot_into(root: str) -> None:
    """Make ``root`` the filesystem root of this mount namespace and drop the old one entirely."""
    number = SYS_PIVOT_ROOT.get(os.uname().machine)
    if number is None:
        raise OSError(f"pivot_root: no syscall number known for {os.uname().machine}")
    os.chdir(root)
    check(LIBC.syscall(number, b".", b"."), "pivot_root")
    check(LIBC.umount2(b".", MNT_DETACH), "umount old root")
    os.chdir("/")


def build_root(config: dict) -> None:
    unshare(CLONE_NEWNS)
    mount(None, "/", None, MS_REC | MS_PRIVATE)
    root = config["host_root_dir"]
    mount("tmpfs", root, "tmpfs", MS_NOSUID | MS_NODEV, "size=1m,mode=0755")
    for path in SYSTEM_PATHS:
        add_system_path(root, path)
    add_devices(root)
    os.makedirs(root + "/proc")
    mount("proc", root + "/proc", "proc", MS_NOSUID | MS_NODEV | MS_NOEXEC)
    add_work_dir(root, config)
    # After /tmp exists: an interpreter installed under /tmp (a virtualenv made with mktemp) is then
    # mounted inside the work tmpfs instead of claiming /tmp before it.
    for path in config["read_only_paths"]:
        if not os.path.exists(root + path):
            bind_read_only(path, root + path)
    # site-packages inside a mounted folder (the standard library's, /usr's): an empty read-only tmpfs
    # over each, so no installed package, nor its data (a benchmark's answer key), can be read.
    for path in config["hidden_paths"]:
        if os.path.isdir(root + path) and not os.path.islink(root + path):
            mount("tmpfs", root + path, "tmpfs", MS_RDONLY | MS_NOSUID | MS_NODEV | MS_NOEXEC, "size=4k,mode=0555")
    mount(None, root, None, MS_REMOUNT | MS_RDONLY | MS_NOSUID | MS_NODEV)
    pivot_into(root)


# ----------------------------------------------------------------------------- the code's process


def set_limits(limits: dict, nproc: int) -> None:
    cpu = limits["cpu_time_s"]
    memory = limits["memory_bytes"]
    for name, soft, hard in (
        (resource.RLIMIT_CPU, cpu, cpu + 1),  # SIGXCPU at soft, SIGKILL at hard
        (resource.RLIMIT_AS, memory, memory),
        (resource.RLIMIT_FSIZE, limits["max_file_bytes"], limits["max_file_bytes"]),
        (resource.RLIMIT_NOFILE, limits["max_open_files"], limits["max_open_files"]),
        (resource.RLIMIT_NPROC, nproc, nproc),
        (resource.RLIMIT_CORE, 0, 0),
    ):
        resource.setrlimit(name, (soft, hard))


def drop_privileges(config: dict) -> bool:
    """Become the sandbox uid (when root) and enter a user namespace of its own, in which
    RLIMIT_NPROC counts only this run's processes. Returns whether that namespace was made."""
    uid, gid = config["sandbox_uid"], config["sandbox_gid"]
    if os.getuid() == 0:
        os.setgroups([])
        os.setresgid(gid, gid, gid)
        os.setresuid(uid, uid, uid)
    try:
        unshare(CLONE_NEWUSER)
        map_own_ids(uid, gid)
        return True
    except OSError:
        return False


def count_own_processes(uid: int) -> int:
    """Processes of ``uid`` now (the fallback RLIMIT_NPROC is this plus the budget)."""
    count = 0
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                count += os.stat("/proc/" + entry).st_uid == uid
            except OSError:
                pass
    return count


def exec_code(config: dict, work_dir: str, block_sockets: bool, own_user_namespace: bool) -> None:
    limits = config["limits"]
    nproc = limits["max_processes"]
    if not own_user_namespace:  # RLIMIT_NPROC counts every process of the uid, not only ours
        nproc += count_own_processes(os.getuid())
    set_limits(limits, nproc)
    prctl(PR_SET_NO_NEW_PRIVS, 1)
    os.chdir(work_dir)
    if not os.access(config["python"], os.X_OK):
        raise OSError(f"uid {os.getuid()} cannot execute {config['python']} (a folder on its path is closed "
                      "to it); give the Sandbox a python that uid can run, or use the namespaces isolation")
    env = dict(config["env"], HOME=work_dir, TMPDIR=work_dir)
    # -S: no site-packages (under namespaces none is mounted anyway; under "process" it is not imported).
    argv = [config["python"], "-I", "-S", "-c", config["runner"], config["code_name"], work_dir,
            str(int(block_sockets))]
    os.execve(config["python"], argv, env)


def exit_status(status: int, rusage) -> dict:
    cpu = rusage.ru_utime + rusage.ru_stime
    if os.WIFSIGNALED(status):
        return {"signal": os.WTERMSIG(status), "cpu_time_s": cpu}
    return {"returncode": os.WEXITSTATUS(status), "cpu_time_s": cpu}


def wait_reaping(child: int, status: Status, max_processes: int) -> dict:
    """As PID 1: reap every orphan until ``child`` exits, and report when the namespace holds as
    many processes as the budget allows."""
    reported = False
    while True:
        pid, wait_status, rusage = os.wait4(-1, os.WNOHANG)
        if pid == child:
            return exit_status(wait_status, rusage)
        if pid == 0:
            if not reported and sum(entry.isdigit() for entry in os.listdir("/proc")) > max_processes:
                status.send(limit="processes")
                reported = True
            time.sleep(PROCESS_POLL_S)


def run_init(config: dict, status: Status, launcher_alive: int) -> None:
    """PID 1 of the sandbox's PID namespace."""
    try:
        prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
        # The launcher may have died before PDEATHSIG was armed; its end of this pipe tells.
        poller = select.poll()
        poller.register(launcher_alive, select.POLLIN)
        if poller.poll(0):
            os._exit(1)
        prctl(PR_SET_DUMPABLE, 0)  # the code's process runs as our uid when not root: no ptrace
        build_root(config)
    except Exception as error:  # noqa: BLE001 - the parent gets the reason, whatever it is
        status.send(error=f"sandbox setup failed: {error}")
        os._exit(1)
    child = os.fork()
    if child == 0:
        try:
            own = drop_privileges(config)
            exec_code(config, SANDBOX_TMP, block_sockets=False, own_user_namespace=own)
        except Exception as error:  # noqa: BLE001
            status.send(error=f"sandbox setup failed: {error}")
        os._exit(1)
    status.send(**wait_reaping(child, status, config["limits"]["max_processes"]))
    os._exit(0)


def enter_namespaces() -> None:
    flags = CLONE_NEWNET | CLONE_NEWPID | CLONE_NEWIPC | CLONE_NEWUTS
    if os.getuid() == 0:
        unshare(flags)
    else:
        uid, gid = os.getuid(), os.getgid()
        unshare(CLONE_NEWUSER | flags)
        map_own_ids(uid, gid)


def run_with_namespaces(config: dict, status: Status) -> None:
    status.send(isolation="namespaces")
    alive_read, alive_write = os.pipe()  # held open by the launcher for as long as it lives
    child = os.fork()
    if child == 0:
        os.close(alive_write)
        run_init(config, status, alive_read)
    os.waitpid(child, 0)


def run_as_process(config: dict, status: Status, reason: str) -> None:
    status.send(isolation="process", reason=reason)
    work_dir = config["host_work_dir"]
    child = os.fork()
    if child == 0:
        try:
            if os.getuid() == 0:
                uid, gid = config["sandbox_uid"], config["sandbox_gid"]
                os.setgroups([])
                os.setresgid(gid, gid, gid)
                os.setresuid(uid, uid, uid)
            exec_code(config, work_dir, block_sockets=True, own_user_namespace=False)
        except Exception as error:  # noqa: BLE001
            status.send(error=f"sandbox setup failed: {error}")
        os._exit(1)
    _, wait_status, rusage = os.wait4(child, 0)
    status.send(**exit_status(wait_status, rusage))
    # Without a PID namespace, whatever the code left running is still in our session: end it
    # (and ourselves) now, while the session id is certainly still ours.
    os.killpg(0, signal.SIGKILL)


def probe() -> None:
    """Exit 0 when this process can build the namespaces isolation (its namespaces, then a private
    mount namespace holding a tmpfs, in a throwaway child), else 1 with the reason on stderr."""
    try:
        enter_namespaces()
        child = os.fork()
        if child == 0:
            try:
                unshare(CLONE_NEWNS)
                mount(None, "/", None, MS_REC | MS_PRIVATE)
                mount("tmpfs", "/tmp", "tmpfs", MS_NOSUID | MS_NODEV, "size=1m")
            except OSError as error:
                os.write(2, f"{error}\n".encode())
                os._exit(1)
            os._exit(0)
        _, wait_status = os.waitpid(child, 0)
    except OSError as error:
        sys.stderr.write(f"{error}\n")
        sys.exit(1)
    sys.exit(0 if wait_status == 0 else 1)


def main() -> None:
    if sys.argv[1] == "--probe":
        probe()
    with open(sys.argv[1]) as handle:
        config = json.load(handle)
    status = Status(config["status_fd"])
    try:
        # Inherited by everything the run starts: under memory pressure the kernel kills the run's
        # processes before any other (the trainer's included), and the code cannot lower it.
        write_file("/proc/self/oom_score_adj", "1000")
        if config["cgroup"]:  # joined before anything is started, so all of the run is inside
            write_file(os.path.join(config["cgroup"], "cgroup.procs"), str(os.getpid()))
            status.send(cgroup=True)
    except OSError as error:
        status.send(error=f"sandbox setup failed: {error}")
        sys.exit(1)
    if config["isolation"] == "process":
        run_as_process(config, status, "isolation 'process' requested")
        return
    # "auto" and "namespaces" alike: never a silent fall back to the weaker isolation.
    try:
        enter_namespaces()
    except OSError as error:
        status.send(error=f"isolation {config['isolation']!r} needs namespaces, unavailable here: {error}")
        sys.exit(1)
    run_with_namespaces(config, status)


if __name__ == "__main__":
    main()
