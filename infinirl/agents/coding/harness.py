"""The test harness that runs inside the sandbox as ``main.py`` (standard library only).

It reads one JSON line from stdin (``nonce``, ``entry_point``, ``max_failures``, ``preamble``)
and writes one report line on stdout, ``<nonce> <json>``: how many of the tests in ``tests.py`` (the
body of ``check(candidate)``, one top-level statement at a time; a statement is a test when it contains an
``assert``) pass against the ``entry_point`` function of ``solution.py`` (the model's code), with
the first failures described (for an ``assert f(x) == y`` that failed, the value ``f(x)`` returned)
and what the code printed (bounded).

The model's code never runs in the process that judges it. The harness forks first; the forked *code
process* closes its stdin, executes ``solution.py`` (as module ``solution``, so a ``__main__`` block
does not run) and then only answers calls. The *test process* reads the spec (so the nonce never
exists in the code process's memory), forbids being traced or read through /proc
(``PR_SET_DUMPABLE`` 0), and runs the tests with ``candidate`` (and every other function the code
defines under a name that is not a builtin) bound to a proxy, and then the problem's ``preamble``
(what its stub declares before the function: helpers such as HumanEval's ``encode_shift`` or
``poly``) executed in the tests' namespace, so the tests call the problem's own helpers, never ones
the code redefined. Calling a proxy sends the arguments to the code process, the call runs there,
and the result comes back encoded as data. Only plain built-in values cross: ``None``, ``bool``,
``int``, ``float``, ``complex``, ``str``, ``bytes`` and ``list``, ``tuple``, ``dict``, ``set``,
``frozenset`` of them, each of exactly that type (a subclass, e.g. an ``int`` with its own
``__eq__``, is refused), and the test process rebuilds them itself. So a result's comparisons are
Python's own, a result of any other type fails its test, and nothing the code does in its process
can change a verdict or the report; it can only return values, raise, or end its process (a test
that fails, with the tests after it; a process killed by a signal, e.g. at the CPU limit, ends the
harness by the same signal, so the sandbox reports the limit as for one process).

Limits that remain: a helper the tests call that the problem's preamble does not define is the
code's (a test that checks ``f(candidate(x))`` with such an ``f`` trusts it); a call's arguments are
copies (a function that should change its argument in place cannot be tested that way), and a test
that passes something other than a plain value to the code fails. If ``prctl`` is unavailable, or
the sandbox's user may trace processes of its uid regardless, the code process could read the nonce
from the test process through /proc; the sandbox (not this harness) bounds what code can reach.
"""

import ast
import builtins
import io
import json
import os
import signal
import struct
import sys
import time
import traceback
import types

MAX_CAPTURED_CHARS = 2000
MAX_TEXT = 300
MAX_DEPTH = 100  # nesting of a value passed to or from the code; deeper (or cyclic) values are refused
MAX_MESSAGE_BYTES = 256 << 20
MAX_CONSTANT_CHARS = 1 << 16  # a module-level value of the code the tests may read
PR_SET_DUMPABLE = 4
EXIT_GRACE_S = 2.0  # a process closing its pipes is exiting: it is reaped within microseconds
SOLUTION = "solution.py"
TESTS = "tests.py"
PLAIN_NAMES = "None, bool, int, float, complex, str, bytes, and list, tuple, dict, set, frozenset of them"
CONTAINER_TAGS = {list: "l", tuple: "t", set: "s", frozenset: "F"}
CONTAINER_TYPES = {tag: kind for kind, tag in CONTAINER_TAGS.items()}
HEADER = struct.Struct(">Q")


class CappedText(io.TextIOBase):
    """A text stream keeping the first ``limit`` characters written to it."""

    def __init__(self, limit):
        super().__init__()
        self.limit, self.parts, self.size = limit, [], 0

    def writable(self):
        return True

    def write(self, text):
        room = self.limit - self.size
        if room > 0:
            self.parts.append(text[:room])
            self.size += min(len(text), room)
        return len(text)

    def getvalue(self):
        return "".join(self.parts)


class NotPlain(TypeError):
    """A value that is not made of plain built-in values only."""


class CodeError(Exception):
    """An exception of the code's own class, raised again in the test process."""


class CodeEnded(Exception):
    """The code process ended before answering."""


def cut(text, limit=MAX_TEXT):
    return text if len(text) <= limit else text[: limit - 3] + "..."


def describe(error):
    """``Type: message`` and the last line of the solution it came from."""
    remote = getattr(error, "_harness_description", None)
    if isinstance(remote, str):
        return cut(remote)
    text = "".join(traceback.format_exception_only(type(error), error)).strip()
    frames = [f for f in traceback.extract_tb(error.__traceback__) if f.filename == SOLUTION]
    if frames:
        text += f" (solution.py line {frames[-1].lineno})"
    return cut(text)


# --------------------------------------------------------------------------- values as data
def encode(value, depth=0):
    """JSON-able form of a plain value; NotPlain for anything else. Ints and floats go as hex:
    exact, with no limit on digits, and inf/nan included."""
    kind = type(value)
    if depth > MAX_DEPTH:
        raise NotPlain(f"a value nested more than {MAX_DEPTH} levels deep (or containing itself)")
    if value is None or kind is bool or kind is str:
        return value
    if kind is int:
        return ["i", format(value, "x")]
    if kind is float:
        return ["f", value.hex()]
    if kind is complex:
        return ["c", value.real.hex(), value.imag.hex()]
    if kind is bytes:
        return ["y", value.hex()]
    if kind is dict:
        return ["d", [[encode(k, depth + 1), encode(v, depth + 1)] for k, v in value.items()]]
    if kind in CONTAINER_TAGS:
        return [CONTAINER_TAGS[kind], [encode(item, depth + 1) for item in value]]
    raise NotPlain(f"a value of type {kind.__qualname__}")


def decode(data, depth=0):
    """The value `encode` describes, rebuilt from built-in types only (ValueError on bad data)."""
    if depth > MAX_DEPTH:
        raise ValueError("value nested too deeply")
    if data is None or type(data) is bool or type(data) is str:
        return data
    if type(data) is not list or not data or type(data[0]) is not str:
        raise ValueError("malformed value")
    tag, rest = data[0], data[1:]
    if tag == "i" and len(rest) == 1:
        return int(rest[0], 16)
    if tag == "f" and len(rest) == 1:
        return float.fromhex(rest[0])
    if tag == "c" and len(rest) == 2:
        return complex(float.fromhex(rest[0]), float.fromhex(rest[1]))
    if tag == "y" and len(rest) == 1:
        return bytes.fromhex(rest[0])
    if len(rest) != 1 or type(rest[0]) is not list:
        raise ValueError("malformed value")
    if tag == "d":
        pairs = rest[0]
        if any(type(pair) is not list or len(pair) != 2 for pair in pairs):
            raise ValueError("malformed dict")
        return {decode(k, depth + 1): decode(v, depth + 1) for k, v in pairs}
    if tag in CONTAINER_TYPES:
        return CONTAINER_TYPES[tag](decode(item, depth + 1) for item in rest[0])
    raise ValueError("malformed value")


# --------------------------------------------------------------------------- messages between the processes
def send(fd, message):
    data = json.dumps(message).encode("utf-8")
    view = memoryview(HEADER.pack(len(data)) + data)
    while view:
        view = view[os.write(fd, view):]


def read_exactly(fd, size):
    chunks, left = [], size
    while left:
        chunk = os.read(fd, min(left, 1 << 20))
        if not chunk:
            return None
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def receive(fd):
    """The next message, or None when the other process closed its end (or ended)."""
    header = read_exactly(fd, HEADER.size)
    if header is None:
        return None
    (size,) = HEADER.unpack(header)
    if size > MAX_MESSAGE_BYTES:
        raise ValueError(f"a message of {size} bytes from the code process")
    data = read_exactly(fd, size)
    return None if data is None else json.loads(data)


# --------------------------------------------------------------------------- the code process
def serve_code(solution, requests, replies):
    """Execute the solution, report the names it defines, then answer calls until told to stop."""
    close_stdin()
    close_stdout()
    captured = CappedText(MAX_CAPTURED_CHARS)
    sys.stdout = sys.stderr = captured
    sent = 0

    def reply(*message):
        nonlocal sent
        text = captured.getvalue()
        send(replies, [*message, text[sent:]])
        sent = len(text)

    module = types.ModuleType("solution")  # registered, so dataclasses and pickling find the code's module
    sys.modules["solution"] = module
    namespace = module.__dict__
    try:
        exec(compile(solution, SOLUTION, "exec"), namespace)  # noqa: S102
    except BaseException as error:  # noqa: BLE001 - whatever the code does is reported
        reply("failed", describe(error))
        return
    reply("loaded", *defined_names(namespace))
    while True:
        request = receive(requests)
        if request is None:
            return
        name, args, kwargs = request
        try:
            result = namespace[name](*[decode(a) for a in args], **{k: decode(v) for k, v in kwargs.items()})
        except BaseException as error:  # noqa: BLE001 - raised again in the test process
            try:
                message = str(error)
            except BaseException:  # noqa: BLE001
                message = ""
            reply("raised", type(error).__name__, cut(message, 2000), describe(error))
            continue
        try:
            reply("returned", encode(result))
        except (NotPlain, RecursionError) as error:
            reply("not_plain", str(error))


def close_stdin():
    """The test process reads the spec, and its nonce, from this stdin after the fork."""
    try:
        devnull = os.open(os.devnull, os.O_RDONLY)
    except OSError:
        os.close(0)
        return
    os.dup2(devnull, 0)
    os.close(devnull)


def close_stdout():
    """Only the test process holds the sandbox's stdout (the report's pipe): the code's fds 1 and 2
    are /dev/null, so what it writes there (``os.write(1, ...)``, ``sys.__stdout__``, a child
    process) can neither reach the output limit, which would cut the report, nor mix with it."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.dup2(devnull, 2)
    os.close(devnull)


def defined_names(namespace):
    """``(names of the functions, {name: encoded value} of the plain constants)`` the code defines."""
    functions, constants = [], {}
    for name, value in list(namespace.items()):
        if name.startswith("__"):
            continue
        if callable(value):
            functions.append(name)
            continue
        try:
            encoded = encode(value)
        except (NotPlain, RecursionError):
            continue
        if len(json.dumps(encoded)) <= MAX_CONSTANT_CHARS:
            constants[name] = encoded
    return functions, constants


# --------------------------------------------------------------------------- the test process
def forbid_tracing():
    """Make this process's memory and /proc entries unreadable to processes of the same uid."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_DUMPABLE, 0, 0, 0, 0)
    except Exception:  # noqa: BLE001 - best effort: not every platform has prctl or ctypes
        pass


def raised_again(name, message, description):
    """The exception the code raised, as an instance of the builtin class of that name (so a
    test's ``except ValueError`` still catches it), else a CodeError."""
    kind = getattr(builtins, name, None)
    error = None
    if isinstance(kind, type) and issubclass(kind, BaseException):
        try:
            error = kind(message)
        except Exception:  # noqa: BLE001 - a builtin needing other arguments
            error = None
    if error is None:
        error = CodeError(f"{name}: {message}" if message else name)
    error._harness_description = description
    return error


class Code:
    """The code process, seen from the test process: calls by name, what it printed, how it ended."""

    def __init__(self, pid, requests, replies, output):
        self.pid, self.requests, self.replies, self.output = pid, requests, replies, output
        self.reaped, self.status, self.ended = False, None, None

    def receive(self):
        """The next message of the code process, what it printed since the last one taken off."""
        try:
            message = receive(self.replies)
        except (ValueError, RecursionError) as error:
            self.end(f"the code process sent a malformed message ({type(error).__name__})")
        if message is None:
            self.end()
        if type(message) is not list or not message or type(message[-1]) is not str:
            self.end("the code process sent a malformed message")
        self.output.write(message[-1])
        return message[:-1]

    def call(self, name, args, kwargs):
        if self.ended is not None:
            raise CodeEnded(self.ended)
        try:
            request = [name, [encode(a) for a in args], {k: encode(v) for k, v in kwargs.items()}]
        except (NotPlain, RecursionError) as error:
            raise TypeError(f"the tests pass {error} to {name}(); only plain built-in values ({PLAIN_NAMES}) "
                            "can be passed to the code") from None
        try:
            send(self.requests, request)
        except OSError:
            self.end()
        reply = self.receive()
        if reply[:1] == ["returned"] and len(reply) == 2:
            try:
                return decode(reply[1])
            except (ValueError, TypeError, OverflowError, RecursionError) as error:
                self.end(f"the code process sent a malformed value ({type(error).__name__})")
        strings = all(type(part) is str for part in reply[1:])
        if reply[:1] == ["raised"] and len(reply) == 4 and strings:
            raise raised_again(*reply[1:])
        if reply[:1] == ["not_plain"] and len(reply) == 2 and strings:
            raise TypeError(f"{name}() returned {cut(reply[1], 120)}, not a plain built-in value ({PLAIN_NAMES})")
        self.end("the code process sent a malformed reply")

    def end(self, problem=None):
        """Raise CodeEnded: the code process ended (``problem`` None) or misbehaved. When a signal
        killed it (a limit: CPU time, memory), this process dies by the same signal."""
        if self.ended is None:
            status = self.reap(0.0 if problem else EXIT_GRACE_S)
            if problem is None and status is not None and os.WIFSIGNALED(status):
                die_by(os.WTERMSIG(status))
            if problem is None:
                problem = ("the code's process stopped answering" if status is None else
                           f"the code's process ended (exit code {os.WEXITSTATUS(status)})")
            self.ended = problem
        raise CodeEnded(self.ended)

    def reap(self, grace_s):
        """The code process's wait status once it exits (within ``grace_s``), or None when it had
        to be killed."""
        if self.reaped:
            return self.status
        self.reaped = True
        try:
            os.close(self.requests)  # the code process ends when its requests end
        except OSError:
            pass
        deadline = time.monotonic() + grace_s
        while True:
            pid, status = os.waitpid(self.pid, os.WNOHANG)
            if pid:
                self.status = status
                return status
            if time.monotonic() >= deadline:
                break
            time.sleep(0.002)
        os.kill(self.pid, signal.SIGKILL)
        os.waitpid(self.pid, 0)
        return None


def die_by(signal_number):
    """End this process by ``signal_number``, as the code process was: the sandbox reads a limit
    (SIGXCPU: CPU time) from how the process it started ended."""
    sys.stdout.flush()
    try:
        signal.signal(signal_number, signal.SIG_DFL)
    except (OSError, ValueError):  # SIGKILL and SIGSTOP keep their action
        pass
    os.kill(os.getpid(), signal_number)
    os._exit(1)


class Remote:
    """A function of the code, called in the code process."""

    def __init__(self, code, name):
        self._code, self.__name__ = code, name

    def __call__(self, *args, **kwargs):
        return self._code.call(self.__name__, args, kwargs)

    def __repr__(self):
        return f"<function {self.__name__}>"


def check_statements(source):
    """``(parameter name, [(statement text, code, is_test)])`` of the tests' ``check`` function."""
    tree = ast.parse(source, TESTS)
    checks = [n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "check"]
    if not checks or not checks[-1].args.args:
        raise ValueError("tests.py defines no check(candidate) function")
    check = checks[-1]
    statements = []
    for statement in check.body:
        module = ast.Module(body=[statement], type_ignores=[])
        is_test = any(isinstance(node, ast.Assert) for node in ast.walk(statement))
        text = ast.get_source_segment(source, statement) or ast.dump(statement)
        statements.append((statement, text, compile(module, TESTS, "exec"), is_test))
    if not any(is_test for *_, is_test in statements):  # no asserts: every statement is a test
        statements = [(s, t, c, True) for s, t, c, _ in statements]
    return check.args.args[0].arg, statements


def returned_value(statement, namespace):
    """For a failed ``assert f(x) == y``: ``repr(f(x))``, else None."""
    test = getattr(statement, "test", None)
    if not (isinstance(test, ast.Compare) and len(test.ops) == 1 and isinstance(test.ops[0], ast.Eq)):
        return None
    try:
        value = eval(compile(ast.Expression(body=test.left), TESTS, "eval"), namespace)  # noqa: S307
    except BaseException:  # noqa: BLE001 - it already failed once; the message says how
        return None
    return cut(repr(value), 120)


def code_namespace(code, entry_point, functions, constants):
    """What the tests see of the code: its functions as proxies and its plain constants, except
    under builtin names (a ``def abs`` of the code must not change what the tests' ``abs`` does)."""
    namespace = types.ModuleType("solution").__dict__
    for name, encoded in constants.items():
        if type(name) is str and name.isidentifier() and not name.startswith("__") and not hasattr(builtins, name):
            namespace[name] = decode(encoded)
    for name in functions:
        if type(name) is str and name.isidentifier() and not name.startswith("__") and (
                name == entry_point or not hasattr(builtins, name)):
            namespace[name] = Remote(code, name)
    return namespace


def run_tests(code, entry_point, tests_source, max_failures, report, preamble=""):
    loaded = code.receive()
    if loaded[0] == "failed" and len(loaded) == 2 and type(loaded[1]) is str:
        report["error"] = cut(loaded[1])
        return
    if loaded[0] != "loaded" or len(loaded) != 3 or type(loaded[1]) is not list or type(loaded[2]) is not dict:
        code.end("the code process sent a malformed message")
    if entry_point not in loaded[1]:
        report["error"] = f"the code defines no function {entry_point!r}"
        return
    namespace = code_namespace(code, entry_point, loaded[1], loaded[2])
    report["loaded"] = True
    try:
        # The problem's helpers, defined here after the code's: the tests use these, whatever the code defines.
        exec(compile(preamble, "stub.py", "exec"), namespace)  # noqa: S102
        exec(compile(tests_source, TESTS, "exec"), namespace)  # noqa: S102
        parameter, statements = check_statements(tests_source)
    except (SyntaxError, ValueError) as error:  # the problem's tests, not the code, are broken
        report["harness_error"] = f"{type(error).__name__}: {error}"
        return
    namespace[parameter] = Remote(code, entry_point)
    report["total"] = sum(is_test for *_, is_test in statements)
    for statement, text, compiled, is_test in statements:
        try:
            exec(compiled, namespace)  # noqa: S102
        except BaseException as error:  # noqa: BLE001 - SystemExit from the candidate is a failure too
            if len(report["failures"]) < max_failures:
                failure = {"test": cut(text), "error": describe(error)}
                got = returned_value(statement, namespace) if isinstance(error, AssertionError) else None
                if got is not None:
                    failure["got"] = got
                report["failures"].append(failure)
        else:
            report["passed"] += is_test


def main():
    # Both files are read before the code runs: it may rewrite the files of the working directory.
    with open(SOLUTION, encoding="utf-8") as handle:
        solution = handle.read()
    with open(TESTS, encoding="utf-8") as handle:
        tests_source = handle.read()
    forbid_tracing()
    requests_read, requests_write = os.pipe()
    replies_read, replies_write = os.pipe()
    sys.stdout.flush()
    pid = os.fork()
    if pid == 0:
        try:
            os.close(requests_write)
            os.close(replies_read)
            serve_code(solution, requests_read, replies_write)
        finally:
            os._exit(0)  # never return into the test process's code
    os.close(requests_read)
    os.close(replies_write)
    # Modules the tests import must not be files the code wrote into the working directory.
    work_dir = os.path.realpath(os.getcwd())
    sys.path[:] = [p for p in sys.path if p and os.path.realpath(p) != work_dir]
    spec = json.loads(sys.stdin.readline())
    real_stdout = sys.stdout
    captured = CappedText(MAX_CAPTURED_CHARS)
    sys.stdout = sys.stderr = captured
    report = {"loaded": False, "passed": 0, "total": 0, "failures": []}
    code = Code(pid, requests_write, replies_read, captured)
    try:
        run_tests(code, spec["entry_point"], tests_source, spec["max_failures"], report, spec.get("preamble", ""))
    except CodeEnded as error:
        report.setdefault("error", cut(str(error)))
    finally:
        code.reap(EXIT_GRACE_S)
        sys.stdout, sys.stderr = real_stdout, sys.__stderr__
        report["output"] = captured.getvalue()
        real_stdout.write(f"\n{spec['nonce']} {json.dumps(report)}\n")
        real_stdout.flush()


if __name__ == "__main__":
    main()
