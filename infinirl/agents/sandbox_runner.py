"""The first Python the sandboxed process runs: it executes the model's code as ``__main__``.

Its source is passed as ``python -I -c <source>`` (the sandbox cannot see the project's files), so it
uses only the standard library. argv: code file name, working directory, "1" to refuse sockets.
A MemoryError that reaches the top ends the process with :data:`MEMORY_EXIT_CODE`, which the parent
reports as the memory limit.
"""

import os
import sys
import traceback
import types

MEMORY_EXIT_CODE = 77


def refuse_sockets() -> None:
    """Best-effort network refusal where no network namespace could be made: every socket
    constructor raises. Code that reaches the kernel by other means (ctypes) is not stopped."""
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
