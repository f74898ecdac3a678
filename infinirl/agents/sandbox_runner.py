"""The first Python the sandboxed process runs: it executes the model's code as ``__main__``.

Its source is passed as ``python -I -c <source>`` (the sandbox cannot see the project's files), so it
uses only the standard library. argv: code file name, working directory, "1" to refuse sockets (a
seccomp filter that covers the processes the code starts, where the kernel takes one, and Python's
socket constructors replaced, for a readable error).
A MemoryError that reaches the top ends the process with :data:`MEMORY_EXIT_CODE`, which the parent
reports as the memory limit.
"""

import os
import sys
import traceback
import types

MEMORY_EXIT_CODE = 77


# Per architecture: the audit arch seccomp reports, and the syscalls refused: socket, socketpair and
# io_uring_setup (io_uring can open sockets without the socket syscall).
SECCOMP_ARCHES = {
    "x86_64": (0xC000003E, (41, 53, 425)),
    "aarch64": (0xC00000B7, (198, 199, 425)),
}
X32_SYSCALL_BIT = 0x40000000  # x86_64 also takes the x32 ABI's numbers, which carry this bit
EACCES = 13


def seccomp_program(machine: str) -> list[tuple[int, int, int, int]] | None:
    """A classic-BPF seccomp filter (code, jt, jf, k) refusing the socket syscalls with EACCES, or
    None for an architecture it does not know. Other ABIs on the same kernel (i386 on x86_64,
    arm32 on aarch64) kill the process, since their socket calls have other numbers."""
    if machine not in SECCOMP_ARCHES:
        return None
    arch, refused = SECCOMP_ARCHES[machine]
    load, jump_eq, jump_ge, ret = 0x20, 0x15, 0x35, 0x06  # BPF_LD|W|ABS, BPF_JMP|JEQ|K, JMP|JGE|K, RET|K
    allow, deny, kill = 0x7FFF0000, 0x00050000 | EACCES, 0x80000000  # SECCOMP_RET_ALLOW, _ERRNO, _KILL_PROCESS
    checks = [(jump_eq, len(refused) - i, 0, number) for i, number in enumerate(refused)]  # to deny
    if machine == "x86_64":
        checks.insert(0, (jump_ge, len(refused) + 1, 0, X32_SYSCALL_BIT))
    return [
        (load, 0, 0, 4),  # seccomp_data.arch
        (jump_eq, 1, 0, arch),
        (ret, 0, 0, kill),
        (load, 0, 0, 0),  # seccomp_data.nr
        *checks,
        (ret, 0, 0, allow),
        (ret, 0, 0, deny),
    ]


def refuse_socket_syscalls() -> bool:
    """Install the seccomp filter of :func:`seccomp_program` on this process; it holds for every
    process started from here on, whatever the program (another Python, curl, ctypes). Whether it
    was installed (not on an unknown architecture or a kernel without seccomp filters)."""
    import ctypes
    import struct

    program = seccomp_program(os.uname().machine)
    if program is None:
        return False
    code = ctypes.create_string_buffer(b"".join(struct.pack("HBBI", *instruction) for instruction in program))

    class SockFprog(ctypes.Structure):
        _fields_ = [("len", ctypes.c_ushort), ("filter", ctypes.c_void_p)]

    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl.argtypes = [ctypes.c_int, ctypes.c_ulong, ctypes.c_void_p, ctypes.c_ulong, ctypes.c_ulong]
    pr_set_no_new_privs, pr_set_seccomp, seccomp_mode_filter = 38, 22, 2
    # The launcher set no_new_privs already; an unprivileged filter needs it, so make sure.
    if libc.prctl(pr_set_no_new_privs, 1, None, 0, 0) != 0:
        return False
    fprog = SockFprog(len(program), ctypes.addressof(code))
    return libc.prctl(pr_set_seccomp, seccomp_mode_filter, ctypes.addressof(fprog), 0, 0) == 0


def refuse_sockets() -> None:
    """Network refusal where no network namespace could be made. The seccomp filter refuses the
    socket syscalls to this process and everything it starts; where it cannot be installed, only
    this interpreter's socket constructors raise (child processes and ctypes then get past)."""
    try:
        refuse_socket_syscalls()
    except (ImportError, OSError, AttributeError):  # an interpreter without ctypes, or a libc without prctl
        pass
    import _socket
    import socket

    def refused(*args, **kwargs):
        raise PermissionError("network access is disabled in this sandbox")

    class RefusedSocket(socket.socket):
        def __init__(self, *args, **kwargs):
            refused()

    _socket.socket = RefusedSocket
    socket.socket = RefusedSocket
    socket.SocketType = RefusedSocket
    for name in ("socketpair", "fromfd", "create_connection", "create_server", "getaddrinfo"):
        setattr(socket, name, refused)


def main() -> None:
    code_name, work_dir, block = sys.argv[1], sys.argv[2], sys.argv[3] == "1"
    if block:
        refuse_sockets()
    path = os.path.join(work_dir, code_name)
    with open(path, encoding="utf-8") as handle:
        source = handle.read()
    sys.argv = [path]
    sys.path.insert(0, work_dir)  # the code may import the files it was given
    module = types.ModuleType("__main__")  # a fresh __main__, so pickling the code's functions works
    module.__file__ = path
    sys.modules["__main__"] = module
    try:
        exec(compile(source, path, "exec"), module.__dict__)
    except SystemExit:
        raise
    except BaseException as error:  # noqa: B036 - report it as Python would, without this file's frame
        traceback.print_exception(type(error), error, error.__traceback__.tb_next)
        sys.stderr.flush()
        os._exit(MEMORY_EXIT_CODE if isinstance(error, MemoryError) else 1)


if __name__ == "__main__":
    main()
