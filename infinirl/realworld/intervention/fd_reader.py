"""Non-blocking reads from a file descriptor: a terminal, a joystick device, a pipe.

A control loop must never wait for a person, so the devices read whatever bytes are waiting and
return at once. :class:`NonBlockingReader` opens a path (or adopts a descriptor), switches it to
non-blocking mode, optionally puts a terminal in raw mode (keys arrive one by one, unechoed), and
restores every setting it changed on :meth:`close`.
"""

from __future__ import annotations

import errno
import fcntl
import logging
import os
import termios
import tty

__all__ = ["NonBlockingReader"]

_READ_CHUNK = 4096

logger = logging.getLogger(__name__)


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
        """Every byte waiting now (``b""`` when none); never blocks. Once :attr:`eof` is set (the other
        side closed, or the device went away) nothing more is read."""
        if self.closed:
            raise RuntimeError(f"{self.what}: read after close()")
        if self.eof:
            return b""
        chunks = []
        while True:
            try:
                chunk = os.read(self.fd, _READ_CHUNK)
            except BlockingIOError:
                break
            except OSError as exc:
                # A terminal whose other side closed reads EIO; an unplugged joystick reads ENODEV.
                # Both are the device going away, not a failure of the caller.
                if exc.errno in (errno.EIO, errno.ENODEV):
                    self.eof = True
                    break
                raise
            if not chunk:
                self.eof = True
                break
            chunks.append(chunk)
        return b"".join(chunks)

    def read_or_lost(self) -> bytes:
        """:meth:`read_available`, except that any read error also counts as the device being gone
        (:attr:`eof` set): a device that fails mid-run must release the robot, not stop the control
        loop or keep replaying its last state. Logs once when the device is lost."""
        was_eof = self.eof
        try:
            data = self.read_available()
        except OSError as exc:
            data, self.eof = b"", True
            logger.warning("%s: reading the device failed (%s); treating it as gone", self.what, exc)
        if self.eof and not was_eof:
            logger.warning("%s: the device is gone (closed or unplugged); the human no longer holds control "
                           "and the policy acts", self.what)
        return data

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            if self._termios is not None:
                termios.tcsetattr(self.fd, termios.TCSADRAIN, self._termios)
            fcntl.fcntl(self.fd, fcntl.F_SETFL, self._flags)
        except (OSError, termios.error):  # the terminal went away; nothing left to restore
            pass
        if self._owned:
            os.close(self.fd)
