"""TCP connections through the edge link: the cloud reaches a service beside the robot (the
intervention page) although the edge opens no port.

The cloud listens on a local TCP port (:class:`TunnelListener`); every connection accepted there
becomes a virtual connection on the link's ``tunnel`` stream, and the edge (:class:`TunnelEnd`
with ``targets``) opens a TCP connection to the service the cloud named and pumps bytes both ways.
Only the services the edge lists can be reached, by name; the cloud's end accepts no connection
opened by an edge.

Messages (:func:`encode_message`): ``[u8 kind][u32 connection id][body]``; the cloud picks the ids.

* ``open`` (cloud -> edge), body the service name; the edge answers ``opened`` once connected, or
  ``close`` with the reason (a refused target, an unknown service, too many connections).
* ``data``: at most ``chunk_bytes`` of the byte stream.
* ``credit``, body a u32: the receiver wrote that many bytes to its socket, the sender may send
  them again. Each direction of each connection has at most ``window_bytes`` unacknowledged, so
  a receiver's buffer never exceeds the window and a slow reader slows its sender only, never the
  link: the link stops reading from the socket when one of its stream inboxes is full, which would
  hold up the episode and weight streams too.
* ``eof``: the sender's side finished sending (TCP half-close; the receiver shuts its socket's
  write side once it wrote everything). A connection ends when both sides sent ``eof``.
* ``close``, body the reason: ends the connection at once in both directions (a failed socket,
  a peer breaking the window).

The tunnel's frames wait on the link at most ``max_connections * window_bytes``, and the link
takes its streams in turns (:mod:`infinirl.edge.fair_queue`), so frames of other streams go out
between the tunnel's chunks. Every blocking call has a timeout: writes to a socket and sends on
the link wait ``io_timeout_s``, the edge's connect ``connect_timeout_s``, and the cloud waits
``open_timeout_s`` for the edge to answer an ``open``. When the link closes, every connection on it
closes (their TCP clients see the connection end).
"""

from __future__ import annotations

import collections
import itertools
import logging
import selectors
import socket
import struct
import threading
import time
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from infinirl.edge import protocol
from infinirl.edge.link import Link, LinkError

__all__ = ["CLOSE", "CREDIT", "DATA", "EOF", "OPEN", "OPENED", "TunnelEnd", "TunnelListener", "TunnelOptions",
           "decode_message", "encode_message"]

logger = logging.getLogger(__name__)

OPEN, OPENED, DATA, CREDIT, EOF, CLOSE = range(6)
_HEADER = struct.Struct(">BI")
_COUNT = struct.Struct(">I")
_POLL_S = 0.1


def encode_message(kind: int, connection: int, body: bytes = b"") -> bytes:
    return _HEADER.pack(kind, connection) + body


def decode_message(payload: bytes) -> tuple[int, int, bytes]:
    """``(kind, connection id, body)``; ``ValueError`` for a payload shorter than the header."""
    if len(payload) < _HEADER.size:
        raise ValueError(f"tunnel message of {len(payload)} bytes is shorter than its {_HEADER.size}-byte header")
    kind, connection = _HEADER.unpack_from(payload)
    return kind, connection, payload[_HEADER.size:]


@dataclass(frozen=True, kw_only=True)
class TunnelOptions:
    """Sizes (bytes), the connection limit per link and the timeouts (s); see the module docstring."""

    chunk_bytes: int = 16 << 10
    window_bytes: int = 128 << 10
    max_connections: int = 16
    connect_timeout_s: float = 5.0
    open_timeout_s: float = 15.0
    io_timeout_s: float = 30.0

    def __post_init__(self) -> None:
        if not 0 < self.chunk_bytes <= self.window_bytes:
            raise ValueError(f"tunnel chunk_bytes ({self.chunk_bytes}) must be > 0 and <= window_bytes "
                             f"({self.window_bytes})")
        if self.max_connections < 1:
            raise ValueError(f"tunnel max_connections must be >= 1, got {self.max_connections}")
        for name in ("connect_timeout_s", "open_timeout_s", "io_timeout_s"):
            if getattr(self, name) <= 0:
                raise ValueError(f"tunnel {name} must be > 0, got {getattr(self, name)}")


class _Relay:
    """One virtual connection: its socket, what arrived for it, what it may send (under ``cond``)."""

    def __init__(self, connection: int, sock: socket.socket | None, window: int, what: str) -> None:
        self.id, self.sock, self.what = connection, sock, what
        self.cond = threading.Condition()
        self.inbound = bytearray()
        self.credit = window
        self.unreturned = 0
        self.opened = False
        self.remote_eof = self.local_eof = self.written_eof = False
        self.closed_reason: str | None = None
        self.pumps = 0


class TunnelEnd:
    """One end of the tunnel on one :class:`~infinirl.edge.link.Link`. The edge passes ``targets``
    (service name -> ``(host, port)``) and answers the cloud's opens; the cloud calls :meth:`open`
    for each accepted client socket. :meth:`start` begins reading the link's ``tunnel`` stream;
    every end of a link must run, or the peer's messages would fill that stream's inbox."""

    def __init__(self, link: Link, *, targets: Mapping[str, tuple[str, int]] | None = None,
                 options: TunnelOptions | None = None) -> None:
        self.link, self.targets = link, dict(targets or {})
        self.options = options or TunnelOptions()
        self.counts: Counter[str] = Counter()
        self.failures: collections.deque[str] = collections.deque(maxlen=100)
        self._relays: dict[int, _Relay] = {}
        self._lock = threading.Lock()
        self._ids = itertools.count(1)
        self._stop = threading.Event()
        self._handlers: dict[int, Callable[[int, bytes], None]] = {
            OPEN: self._on_open, OPENED: self._on_opened, DATA: self._on_data, CREDIT: self._on_credit,
            EOF: self._on_eof, CLOSE: self._on_close}
        self._thread = threading.Thread(target=self._dispatch, name=f"tunnel-{link.peer}", daemon=True)

    def start(self) -> TunnelEnd:
        self._thread.start()
        return self

    @property
    def alive(self) -> bool:
        return self.link.alive and not self._stop.is_set()

    def connections(self) -> int:
        with self._lock:
            return len(self._relays)

    def buffered_bytes(self) -> int:
        """Bytes received for connections and not yet written to their sockets (at most
        ``window_bytes`` per connection)."""
        with self._lock:
            relays = list(self._relays.values())
        total = 0
        for relay in relays:
            with relay.cond:
                total += len(relay.inbound)
        return total

    def open(self, sock: socket.socket, service: str) -> None:
        """Relay ``sock`` (an accepted client) to the peer's ``service``; returns at once. The socket
        is closed when the connection ends, also when it cannot be opened."""
        with self._lock:
            reason = None
            if not self.alive:
                reason = f"the link to {self.link.peer} is closed"
            elif len(self._relays) >= self.options.max_connections:
                reason = f"{self.options.max_connections} tunnel connections are open to {self.link.peer} already"
            else:
                relay = _Relay(next(self._ids), sock, self.options.window_bytes, f"{service} via {self.link.peer}")
                self._relays[relay.id] = relay
        if reason is not None:
            logger.warning("tunnel to %s refused a connection: %s", service, reason)
            self.failures.append(reason)
            self.counts["refused"] += 1
            _close_socket(sock)
            return
        self.counts["opened"] += 1
        self._spawn(relay, self._run_opener, service)

    def close(self, reason: str = "the tunnel is closing") -> None:
        """End every connection (telling the peer while the link lives) and stop reading."""
        self._stop.set()
        with self._lock:
            relays = list(self._relays.values())
        for relay in relays:
            self._finish(relay, reason, tell_peer=self.link.alive, failed=False)
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=2 * _POLL_S + 1.0)

    # ------------------------------------------------------------------ the link's messages
    def _dispatch(self) -> None:
        """Route the ``tunnel`` stream's messages; never blocks on a connection, so the stream's
        inbox on the link keeps draining."""
        try:
            while not self._stop.is_set():
                try:
                    payload = self.link.recv(protocol.TUNNEL, timeout=_POLL_S * 2)
                except TimeoutError:
                    continue
                try:
                    kind, connection, body = decode_message(payload)
                except ValueError as exc:
                    logger.warning("tunnel from %s: %s", self.link.peer, exc)
                    continue
                handler = self._handlers.get(kind)
                if handler is None:
                    logger.warning("tunnel from %s: unknown message kind %d ignored", self.link.peer, kind)
                    continue
                handler(connection, body)
        except LinkError as exc:
            reason = f"the link to {self.link.peer} closed ({exc})"
        else:
            reason = "the tunnel is closing"
        self._stop.set()
        with self._lock:
            relays = list(self._relays.values())
        for relay in relays:
            self._finish(relay, reason, tell_peer=False, failed=True)

    def _relay(self, connection: int) -> _Relay | None:
        with self._lock:
            return self._relays.get(connection)

    def _on_open(self, connection: int, body: bytes) -> None:
        service = body.decode(errors="replace")
        with self._lock:
            clash = connection in self._relays
            full = len(self._relays) >= self.options.max_connections
            relay = _Relay(connection, None, self.options.window_bytes, f"{service} for {self.link.peer}")
            if not clash and not full:
                self._relays[connection] = relay
        if clash:
            self._send_close(connection, f"tunnel connection {connection} is open already")
            return
        if full:
            self._send_close(connection, f"the edge has {self.options.max_connections} tunnel connections open")
            return
        self._spawn(relay, self._run_target, service)

    def _on_opened(self, connection: int, body: bytes) -> None:
        relay = self._relay(connection)
        if relay is not None:
            with relay.cond:
                relay.opened = True
                relay.cond.notify_all()

    def _on_data(self, connection: int, body: bytes) -> None:
        relay = self._relay(connection)
        if relay is None:
            return  # it ended here; the peer learns that from our close or eof
        with relay.cond:
            overflow = len(relay.inbound) + len(body) > self.options.window_bytes
            if not overflow:
                relay.inbound += body
                relay.cond.notify_all()
        self.counts["bytes_in"] += len(body)
        if overflow:
            self._finish(relay, f"{relay.what}: the peer sent beyond its window of {self.options.window_bytes} "
                                "bytes", tell_peer=True, failed=True)

    def _on_credit(self, connection: int, body: bytes) -> None:
        relay = self._relay(connection)
        if relay is not None and len(body) == _COUNT.size:
            with relay.cond:
                relay.credit += _COUNT.unpack(body)[0]
                relay.cond.notify_all()

    def _on_eof(self, connection: int, body: bytes) -> None:
        relay = self._relay(connection)
        if relay is not None:
            with relay.cond:
                relay.remote_eof = True
                relay.cond.notify_all()

    def _on_close(self, connection: int, body: bytes) -> None:
        relay = self._relay(connection)
        if relay is not None:
            self._finish(relay, body.decode(errors="replace") or "closed by the peer", tell_peer=False, failed=True)

    # ------------------------------------------------------------------ one connection's threads
    def _spawn(self, relay: _Relay, target: Callable, *args) -> None:
        with relay.cond:
            relay.pumps += 1
        threading.Thread(target=self._pump_guard, args=(relay, target, *args), daemon=True,
                         name=f"tunnel-{relay.id}").start()

    def _pump_guard(self, relay: _Relay, target: Callable, *args) -> None:
        try:
            target(relay, *args)
        except (LinkError, TimeoutError) as exc:  # socket errors are handled where they happen
            self._finish(relay, f"{relay.what}: the link failed ({exc})", tell_peer=False, failed=True)
        finally:
            with relay.cond:
                relay.pumps -= 1
                last = relay.pumps == 0
            if last and relay.sock is not None:
                relay.sock.close()  # only now: a pump still inside a socket call would see a reused descriptor

    def _run_opener(self, relay: _Relay, service: str) -> None:
        """The cloud's side: ask the edge to open ``service``, then pump."""
        self._send(relay, OPEN, service.encode())
        self._spawn(relay, self._downlink)
        self._uplink(relay, open_deadline=time.monotonic() + self.options.open_timeout_s)

    def _run_target(self, relay: _Relay, service: str) -> None:
        """The edge's side: connect to the service's target, answer, then pump."""
        target = self.targets.get(service)
        if target is None:
            self._finish(relay, f"{self.link.peer}'s peer offers no tunnel service {service!r} (it offers "
                                f"{sorted(self.targets) or 'none'})", tell_peer=True, failed=True)
            return
        try:
            sock = socket.create_connection(target, timeout=self.options.connect_timeout_s)
        except OSError as exc:
            self._finish(relay, f"tunnel service {service!r} at {target[0]}:{target[1]} is unreachable from the "
                                f"edge ({exc})", tell_peer=True, failed=True)
            return
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        with relay.cond:
            relay.sock, relay.opened = sock, relay.closed_reason is None
        if not relay.opened:  # closed while connecting
            sock.close()
            return
        self._send(relay, OPENED)
        self._spawn(relay, self._downlink)
        self._uplink(relay, open_deadline=None)

    def _uplink(self, relay: _Relay, *, open_deadline: float | None) -> None:
        """Socket -> link, within the credit the peer gave."""
        sock = relay.sock
        sock.settimeout(self.options.io_timeout_s)
        with selectors.DefaultSelector() as selector:
            selector.register(sock, selectors.EVENT_READ)
            while True:
                with relay.cond:
                    if relay.credit <= 0 and relay.closed_reason is None:
                        relay.cond.wait(_POLL_S)
                    if relay.closed_reason is not None:
                        return
                    allowed, opened = min(relay.credit, self.options.chunk_bytes), relay.opened
                if not opened and open_deadline is not None and time.monotonic() > open_deadline:
                    self._finish(relay, f"{relay.what}: the edge did not answer the open within "
                                        f"{self.options.open_timeout_s} s", tell_peer=True, failed=True)
                    return
                if allowed <= 0 or not selector.select(_POLL_S):
                    continue
                try:
                    data = sock.recv(allowed)
                except OSError as exc:
                    self._finish(relay, f"{relay.what}: reading the connection failed ({exc!r})",
                                 tell_peer=True, failed=True)
                    return
                if not data:
                    with relay.cond:
                        if relay.closed_reason is not None:  # our own shutdown, not the client's
                            return
                        relay.local_eof = True
                    self._send(relay, EOF)
                    self._finish_if_done(relay)
                    return
                with relay.cond:
                    relay.credit -= len(data)
                self._send(relay, DATA, data)
                self.counts["bytes_out"] += len(data)

    def _downlink(self, relay: _Relay) -> None:
        """Link -> socket, returning credit as the bytes leave."""
        while True:
            with relay.cond:
                if not relay.inbound and not relay.remote_eof and relay.closed_reason is None:
                    relay.cond.wait(_POLL_S)
                if relay.closed_reason is not None:
                    return
                data = bytes(relay.inbound[:self.options.chunk_bytes])
                del relay.inbound[:len(data)]
                ended = not data and relay.remote_eof
            if ended:
                try:
                    relay.sock.shutdown(socket.SHUT_WR)
                except OSError:
                    pass  # the other side is gone already; nothing more to say to it
                with relay.cond:
                    relay.written_eof = True
                self._finish_if_done(relay)
                return
            if not data:
                continue
            try:
                relay.sock.sendall(data)
            except OSError as exc:  # a reset, or a reader that took nothing for io_timeout_s
                self._finish(relay, f"{relay.what}: writing to the connection failed ({exc!r})",
                             tell_peer=True, failed=True)
                return
            with relay.cond:
                relay.unreturned += len(data)
                returned = relay.unreturned if relay.unreturned >= self.options.window_bytes // 4 else 0
                relay.unreturned -= returned
            if returned:
                self._send(relay, CREDIT, _COUNT.pack(returned))

    # ------------------------------------------------------------------ endings
    def _send(self, relay: _Relay, kind: int, body: bytes = b"") -> None:
        self.link.send(protocol.TUNNEL, encode_message(kind, relay.id, body), timeout=self.options.io_timeout_s)

    def _send_close(self, connection: int, reason: str) -> None:
        logger.warning("tunnel connection %d from %s refused: %s", connection, self.link.peer, reason)
        self.failures.append(reason)
        self.counts["refused"] += 1
        self._tell_close(connection, reason)

    def _finish_if_done(self, relay: _Relay) -> None:
        with relay.cond:
            done = relay.local_eof and relay.written_eof
        if done:
            self._finish(relay, "finished", tell_peer=False, failed=False)

    def _finish(self, relay: _Relay, reason: str, *, tell_peer: bool, failed: bool) -> None:
        """End ``relay`` once: wake its pumps, free its id, say why (to the peer too if asked)."""
        with relay.cond:
            if relay.closed_reason is not None:
                return
            relay.closed_reason = reason
            relay.cond.notify_all()
        with self._lock:
            if self._relays.get(relay.id) is relay:
                del self._relays[relay.id]
        if relay.sock is not None:
            try:
                relay.sock.shutdown(socket.SHUT_RDWR)  # wakes a pump waiting in the socket
            except OSError:
                pass
        self.counts["failed" if failed else "finished"] += 1
        if failed:
            logger.warning("tunnel connection %d (%s) closed: %s", relay.id, relay.what, reason)
            self.failures.append(reason)
        if tell_peer:
            self._tell_close(relay.id, reason)

    def _tell_close(self, connection: int, reason: str) -> None:
        try:
            self.link.send(protocol.TUNNEL, encode_message(CLOSE, connection, reason.encode()),
                           timeout=self.options.io_timeout_s)
        except (LinkError, TimeoutError):
            pass  # the link is going; the peer closes the connection with it


class TunnelListener:
    """The cloud's TCP port for one service at an edge: each accepted connection goes through the
    :class:`TunnelEnd` that ``resolve()`` returns (the link of the edge to reach); with none (no
    edge connected) the client's connection is closed at once and the reason logged."""

    def __init__(self, listen: tuple[str, int], resolve: Callable[[], TunnelEnd | None], *, service: str) -> None:
        self.resolve, self.service = resolve, service
        self.counts: Counter[str] = Counter()
        self._server = socket.create_server(listen)
        self._server.settimeout(_POLL_S * 2)
        self.address = self._server.getsockname()[:2]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._accept_loop, name=f"tunnel-listen-{service}", daemon=True)

    def start(self) -> TunnelListener:
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._server.close()

    def __enter__(self) -> TunnelListener:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                client, address = self._server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            end = self.resolve()
            if end is None or not end.alive:
                logger.warning("tunnel %r: no edge link to carry the connection from %s:%s; closed",
                               self.service, *address[:2])
                self.counts["no_edge"] += 1
                _close_socket(client)
                continue
            self.counts["accepted"] += 1
            end.open(client, self.service)


def _close_socket(sock: socket.socket) -> None:
    try:
        sock.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    sock.close()
