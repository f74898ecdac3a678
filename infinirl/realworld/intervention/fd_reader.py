"""Non-blocking reads from a file descriptor: a terminal, a joystick device, a pipe.

A control loop must never wait for a person, so the devices read whatever bytes are waiting and
return at once. :class:`NonBlockingReader` opens a path (or adopts a descriptor), switches it to
non-blocking mode, optionally puts a terminal in raw mode (keys arrive one by one, unechoed), and
restores every setting it changed on :meth:`close`.
"""

from __future__ import annotations

import fcntl
import os
import termios
import tty

__all__ = ["NonBlockingReader"]

_READ_CHUNK = 4096


class NonBlockingReader:
    """``path`` is opened read-only (``what`` names the device in errors); or ``fd`` is adopted
    (not closed on :meth:`close`, only restored). ``raw``: a terminal descriptor is put in raw mode."""

    def __init__(self, *, what: str, path: str | None = None, fd: int | None = None, raw: bool = False) -> None:
        if (path is None) == (fd is None):
            raise ValueError(f"{what}: give exactly one of path or fd")
        self.what = what
        if path is not None:
            try:
                fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY)
            except OSError as exc:
                raise OSError(f"{what}: cannot open {path} ({exc.strerror}); check the device exists and this "
                              "user may read it, or set the device's path option") from exc
        self.fd, self._owned = int(fd), path is not None
        self._flags = fcntl.fcntl(self.fd, fcntl.F_GETFL)
        fcntl.fcntl(self.fd, fcntl.F_SETFL, self._flags | os.O_NONBLOCK)
        self._termios = None
        if raw and os.isatty(self.fd):
            self._termios = termios.tcgetattr(self.fd)
            tty.setraw(self.fd, termios.TCSANOW)
        self.closed = False
        self.eof = False

    def read_available(self) -> bytes:
        """Every byte waiting now (``b""`` when none); never blocks."""
        if self.closed:
            raise RuntimeError(f"{self.what}: read after close()")
        chunks = []
        while True:
            try:
                chunk = os.read(self.fd, _READ_CHUNK)
            except BlockingIOError:
                break
            except OSError as exc:  # a terminal whose other side closed reads EIO
                if exc.errno == 5:
                    self.eof = True
                    break
                raise
            if not chunk:
                self.eof = True
                break
            chunks.append(chunk)
        return b"".join(chunks)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            if self._termios is not None:
                termios.tcsetattr(self.fd, termios.TCSADRAIN, self._termios)
            fcntl.fcntl(self.fd, fcntl.F_SETFL, self._flags)
        except OSError:  # the terminal went away; nothing left to restore
            pass
        if self._owned:
            os.close(self.fd)
