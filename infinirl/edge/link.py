"""One authenticated, encrypted connection between an edge and the cloud, carrying named streams.

The edge dials out (:func:`dial`); the cloud listens (:class:`CloudListener`), so the edge needs no
open port and works behind NAT and firewalls that allow outgoing connections. Both ends prove who
they are with certificates of one private CA (mutual TLS 1.3, :mod:`infinirl.edge.credentials`):
a peer whose certificate does not verify is refused during the handshake with a one-line
:class:`LinkAuthError` on both ends, before any frame is exchanged.

After the handshake the edge sends a hello frame and the cloud answers; both carry a small JSON
object (protocol version, and whatever the services put there, e.g. the weight version the edge
holds). Then one I/O thread per :class:`Link` moves frames (:mod:`infinirl.edge.frames`) both ways
over the non-blocking socket: :meth:`Link.send` queues a frame (bounded by ``max_outgoing_bytes``,
so a slow link pushes back on the producer), :meth:`Link.recv` takes the next frame of one stream.
Every call takes a timeout. A link on which nothing arrives for ``dead_after_s`` (each end sends a
heartbeat after ``heartbeat_s`` without sending) is closed, so a cable pulled without a TCP reset
is noticed; after that every call raises :class:`LinkClosedError` with the reason. Outgoing frames
wait in one queue per stream and go out in deficit round-robin (:mod:`infinirl.edge.fair_queue`), so
a stream with a backlog of large frames (episodes) does not hold up small messages of other
streams (weights announcements, call replies, acknowledgements, heartbeats).
"""

from __future__ import annotations

import collections
import json
import logging
import queue
import selectors
import socket
import ssl
import threading
import time
from dataclasses import dataclass

from infinirl.edge.credentials import CLOUD_NAME
from infinirl.edge.fair_queue import FairQueue
from infinirl.edge.frames import FrameError, FrameReader, encode_frame

__all__ = ["PROTOCOL_VERSION", "CloudListener", "Link", "LinkAuthError", "LinkClosedError", "LinkError",
           "LinkOptions", "dial"]

logger = logging.getLogger(__name__)

PROTOCOL_VERSION = 1
HELLO, WELCOME, HEARTBEAT = "link.hello", "link.welcome", "link.heartbeat"
# The cloud's answer instead of a welcome when it refuses a hello: the edge must tell a refusal, which
# is permanent, from a connection that merely dropped during the hello, which is worth retrying.
REFUSED = "link.refused"
_CHUNK = 1 << 16
_POLL_S = 0.05
# Bytes one direction may move per turn of the I/O loop: a sustained one-way flood must not keep the
# other direction (and the peer's heartbeats) waiting until the link looks dead.
_TURN_BYTES = 1 << 20
# Credit per stream and turn of the outgoing fair queue: a small frame waits for at most this much of
# each busy stream (or one of its frames, when larger) after the frame being written.
_QUANTUM = 1 << 16


class LinkError(ConnectionError):
    """The link failed (the message says why)."""


class LinkAuthError(LinkError):
    """The peer was refused (or refused us): certificates that do not verify, or another protocol."""


class LinkClosedError(LinkError):
    """The link is closed; the message holds the reason."""


@dataclass(frozen=True, kw_only=True)
class LinkOptions:
    """Timeouts and bounds of one link (seconds, bytes, frames)."""

    connect_timeout_s: float = 10.0
    heartbeat_s: float = 1.0
    dead_after_s: float = 6.0
    max_outgoing_bytes: int = 64 << 20
    max_queued_frames: int = 256

    def __post_init__(self) -> None:
        if not 0 < self.heartbeat_s < self.dead_after_s:
            raise ValueError(f"link heartbeat_s ({self.heartbeat_s}) must be > 0 and < dead_after_s "
                             f"({self.dead_after_s}), or a quiet link would be declared dead")


def _peer_name(sock: ssl.SSLSocket) -> str:
    for entry in (sock.getpeercert() or {}).get("subject", ()):
        for key, value in entry:
            if key == "commonName":
                return value
    return "?"


def _read_frame_blocking(sock: ssl.SSLSocket, reader: FrameReader, deadline: float) -> tuple[str, bytes, list]:
    while True:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise TimeoutError("no hello from the peer within the connect timeout")
        sock.settimeout(remaining)
        data = sock.recv(_CHUNK)
        if not data:
            raise LinkClosedError("the peer closed the connection during the hello")
        frames = reader.feed(data)
        if frames:
            return frames[0][0], frames[0][1], frames[1:]


def _alert_after_close(sock: ssl.SSLSocket, deadline: float) -> ssl.SSLError | None:
    """The TLS alert the peer sent before it closed the connection, if one is still unread."""
    try:
        sock.settimeout(min(max(deadline - time.monotonic(), 0.01), 1.0))
        sock.recv(_CHUNK)
    except (ssl.SSLEOFError, ssl.SSLZeroReturnError):
        return None
    except ssl.SSLError as exc:
        return exc
    except OSError:
        return None
    return None


def _hello_payload(extra: dict | None) -> bytes:
    return json.dumps({"protocol": PROTOCOL_VERSION, **(extra or {})}).encode()


def _parse_hello(stream: str, payload: bytes, expected: str, peer: str) -> dict:
    if stream == REFUSED:
        raise LinkAuthError(f"{peer} refused this edge: {payload.decode(errors='replace')}")
    if stream != expected:
        raise LinkAuthError(f"{peer} sent stream {stream!r} before its {expected!r}: not an InfiniRL edge link peer")
    try:
        hello = json.loads(payload)
    except ValueError:
        hello = None
    if not isinstance(hello, dict):  # anything else is not a peer of this protocol, and .get would fail
        raise LinkAuthError(f"{peer} sent a {expected!r} that is not a JSON object: not an InfiniRL edge link peer")
    if hello.get("protocol") != PROTOCOL_VERSION:
        raise LinkAuthError(f"{peer} speaks edge link protocol {hello.get('protocol')}, this side "
                            f"{PROTOCOL_VERSION}: run the same InfiniRL version on both ends")
    return hello


class CloudListener:
    """The cloud's listening socket; :meth:`accept` returns one authenticated :class:`Link`."""

    def __init__(self, host: str, port: int, context: ssl.SSLContext, *, options: LinkOptions | None = None,
                 welcome: dict | None = None) -> None:
        self.options = options or LinkOptions()
        self._context, self._welcome = context, welcome or {}
        self._sock = socket.create_server((host, port), reuse_port=False)
        self.address = self._sock.getsockname()[:2]

    def accept(self, timeout: float) -> Link:
        """The next edge that connects and verifies, within ``timeout`` (``TimeoutError`` otherwise).
        A client that fails the handshake raises :class:`LinkAuthError` naming it; accept again."""
        return self.handshake(*self.accept_connection(timeout))

    def accept_connection(self, timeout: float) -> tuple[socket.socket, tuple]:
        """The next TCP connection, not yet authenticated (pass it to :meth:`handshake`, e.g. on a
        thread of its own, so a slow client does not hold up the others)."""
        self._sock.settimeout(timeout)
        return self._sock.accept()

    def handshake(self, raw: socket.socket, address: tuple) -> Link:
        """TLS and hello on an accepted connection, within ``connect_timeout_s``."""
        who = f"edge at {address[0]}:{address[1]}"
        deadline = time.monotonic() + self.options.connect_timeout_s
        try:
            raw.settimeout(self.options.connect_timeout_s)
            sock = self._context.wrap_socket(raw, server_side=True)
        except ssl.SSLError as exc:
            raw.close()
            raise LinkAuthError(f"{who} refused: TLS handshake failed ({exc.reason or exc}); an edge needs a "
                                "certificate issued by this cloud's CA") from None
        except OSError as exc:
            raw.close()
            raise LinkError(f"{who}: connection failed during the TLS handshake ({exc})") from None
        peer = _peer_name(sock)
        try:
            reader = FrameReader()
            stream, payload, rest = _read_frame_blocking(sock, reader, deadline)
            hello = _parse_hello(stream, payload, HELLO, f"{who} ({peer})")
            sock.sendall(encode_frame(WELCOME, _hello_payload(self._welcome)))
        except LinkAuthError as exc:
            try:  # say so: the edge takes a bare close during the hello for an outage and retries
                sock.sendall(encode_frame(REFUSED, str(exc).encode()))
            except OSError:
                pass
            sock.close()
            raise
        except (OSError, ValueError, FrameError) as exc:
            sock.close()
            raise LinkError(f"{who} ({peer}): hello failed ({exc})") from None
        except BaseException:
            sock.close()
            raise
        return Link(sock, peer=peer, hello=hello, options=self.options, reader=reader, early=rest)

    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> CloudListener:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def dial(address: tuple[str, int], context: ssl.SSLContext, *, options: LinkOptions | None = None,
         hello: dict | None = None) -> Link:
    """Connect to the cloud at ``address``; raises :class:`LinkAuthError` when either side refuses
    the other's certificate, :class:`LinkError` / ``TimeoutError`` / ``OSError`` when unreachable."""
    options = options or LinkOptions()
    where = f"cloud at {address[0]}:{address[1]}"
    deadline = time.monotonic() + options.connect_timeout_s
    raw = socket.create_connection(address, timeout=options.connect_timeout_s)
    try:
        sock = context.wrap_socket(raw, server_hostname=CLOUD_NAME)
    except ssl.SSLCertVerificationError as exc:
        raw.close()
        raise LinkAuthError(f"{where} refused by this edge: its certificate does not verify against this edge's "
                            f"CA ({exc.verify_message}); is it the right cloud and the right ca.pem?") from None
    except (ssl.SSLEOFError, ConnectionResetError) as exc:  # dropped, not refused: a refusal is a TLS alert
        raw.close()
        raise LinkError(f"{where} closed the connection during the TLS handshake ({exc}); retrying") from None
    except ssl.SSLError as exc:
        raw.close()
        raise LinkAuthError(f"{where} refused this edge during the TLS handshake ({exc.reason or exc})") from None
    try:
        sock.settimeout(options.connect_timeout_s)
        sock.sendall(encode_frame(HELLO, _hello_payload(hello)))
        reader = FrameReader()
        stream, payload, rest = _read_frame_blocking(sock, reader, deadline)
        welcome = _parse_hello(stream, payload, WELCOME, where)
    except LinkAuthError:
        sock.close()
        raise
    except (ssl.SSLEOFError, ssl.SSLZeroReturnError, ConnectionError) as exc:  # LinkClosedError included
        # A refusal is a TLS alert (or a link.refused frame); a bare close is a drop (a proxy, NAT or a
        # cloud restarting), worth retrying, as giving up would keep the edge offline for good. Writing
        # the hello can meet the close before the alert that came with it has been read: read it now.
        alert = _alert_after_close(sock, deadline)
        sock.close()
        if alert is not None:
            raise LinkAuthError(f"{where} refused this edge's certificate ({alert.reason or alert}); use the "
                                "certificate and key the cloud's CA issued for this edge") from None
        raise LinkError(f"{where} closed the connection during the hello ({exc}); retrying") from None
    except ssl.SSLError as exc:  # TLS 1.3: the server checks our certificate after our side finished
        sock.close()
        raise LinkAuthError(f"{where} refused this edge's certificate ({exc.reason or exc}); use the "
                            "certificate and key the cloud's CA issued for this edge") from None
    except BaseException:
        sock.close()
        raise
    return Link(sock, peer=_peer_name(sock), hello=welcome, options=options, reader=reader, early=rest)


class Link:
    """An established connection (see the module docstring). ``peer``: the name in the peer's
    certificate (the identity to trust; the hello's contents are the peer's claims)."""

    def __init__(self, sock: ssl.SSLSocket, *, peer: str, hello: dict, options: LinkOptions, reader: FrameReader,
                 early: list | None = None) -> None:
        self.peer, self.peer_hello, self.options = peer, hello, options
        self.bytes_sent = self.bytes_received = 0
        self._sock, self._reader = sock, reader
        self._sock.setblocking(False)
        self._out = FairQueue(_QUANTUM)  # frames not yet begun, by stream
        self._writing: memoryview | None = None  # the rest of the frame on the wire (sent whole, first)
        self._out_bytes = 0
        self._lock = threading.Lock()
        self._space = threading.Condition(self._lock)
        self._inbox: dict[str, queue.Queue] = {}
        self._stalled: collections.deque[tuple[str, bytes]] = collections.deque(early or ())
        self._closed_reason: str | None = None
        self._more_to_read = False  # the last read stopped at its per-turn budget
        self._paused = False  # reading stopped while a stream's inbox is full: recv wakes the I/O thread
        self.closed_at: float | None = None  # time.monotonic() when it closed
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._thread = threading.Thread(target=self._run, name=f"edge-link-{peer}", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ public
    @property
    def alive(self) -> bool:
        return self._closed_reason is None

    @property
    def closed_reason(self) -> str | None:
        return self._closed_reason

    def send(self, stream: str, payload: bytes, timeout: float) -> None:
        """Queue one frame; waits (up to ``timeout``) while the outgoing buffer is full."""
        frame = encode_frame(stream, payload)
        deadline = time.monotonic() + timeout
        with self._space:
            while self._out_bytes and self._out_bytes + len(frame) > self.options.max_outgoing_bytes:
                self._raise_if_closed()
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(f"link to {self.peer}: stream {stream!r} could not queue {len(frame)} bytes "
                                       f"within {timeout} s (the link is slower than the data offered)")
                self._space.wait(min(remaining, _POLL_S * 4))
            self._raise_if_closed()
            self._out.push(stream, memoryview(frame))
            self._out_bytes += len(frame)
        self._wake()

    def recv(self, stream: str, timeout: float) -> bytes:
        """The next frame of ``stream``; ``TimeoutError`` after ``timeout``; frames that arrived
        before the link closed are still returned, then :class:`LinkClosedError`."""
        inbox = self._inbox_of(stream)
        deadline = time.monotonic() + timeout
        while True:
            try:
                payload = inbox.get(timeout=min(max(deadline - time.monotonic(), 0.0), _POLL_S * 4))
            except queue.Empty:
                self._raise_if_closed()
                if time.monotonic() >= deadline:
                    raise TimeoutError(f"link to {self.peer}: nothing on stream {stream!r} "
                                       f"within {timeout} s") from None
                continue
            if self._paused:  # there is room now: the I/O thread reads on without waiting out its poll
                self._wake()
            return payload

    def flush(self, timeout: float) -> None:
        """Wait until every queued frame has been handed to the socket."""
        deadline = time.monotonic() + timeout
        with self._space:
            while self._out_bytes:
                self._raise_if_closed()
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(f"link to {self.peer}: {self._out_bytes} bytes still queued after {timeout} s")
                self._space.wait(min(remaining, _POLL_S * 4))

    def close(self, reason: str = "closed by this side") -> None:
        self._mark_closed(reason)
        self._thread.join(timeout=5.0)

    def __enter__(self) -> Link:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ internals
    def _raise_if_closed(self) -> None:
        if self._closed_reason is not None:
            raise LinkClosedError(f"link to {self.peer} is closed: {self._closed_reason}")

    def _inbox_of(self, stream: str) -> queue.Queue:
        with self._lock:
            if stream not in self._inbox:
                self._inbox[stream] = queue.Queue(maxsize=self.options.max_queued_frames)
            return self._inbox[stream]

    def _wake(self) -> None:
        try:
            self._wake_w.send(b"\0")
        except (BlockingIOError, OSError):
            pass

    def _mark_closed(self, reason: str) -> None:
        with self._space:
            if self._closed_reason is None:
                self._closed_reason, self.closed_at = reason, time.monotonic()
            self._space.notify_all()
        self._wake()

    def _deliver_stalled(self) -> bool:
        """Hand frames to their stream's inbox; False while one is full (then stop reading: the
        peer's sends wait in TCP's window, which is the back-pressure)."""
        while self._stalled:
            stream, payload = self._stalled[0]
            if stream == HEARTBEAT:
                self._stalled.popleft()
                continue
            try:
                self._inbox_of(stream).put_nowait(payload)
            except queue.Full:
                return False
            self._stalled.popleft()
        return True

    def _read_some(self) -> bool:
        """Read what the socket has, up to :data:`_TURN_BYTES`; True when bytes arrived."""
        got, budget = False, _TURN_BYTES
        self._more_to_read = False
        while True:
            if budget <= 0:  # let the writing side have its turn; come straight back (SSL may hold bytes)
                self._more_to_read = True
                return got
            try:
                data = self._sock.recv(_CHUNK)
            except (ssl.SSLWantReadError, ssl.SSLWantWriteError, BlockingIOError):
                return got
            if not data:
                raise LinkClosedError("the peer closed the connection")
            got = True
            budget -= len(data)
            self.bytes_received += len(data)
            self._stalled.extend(self._reader.feed(data))
            if not self._deliver_stalled():
                return got

    def _write_some(self) -> bool:
        """Write queued frames until the socket would block or :data:`_TURN_BYTES` went; True when bytes
        went out."""
        sent, budget = False, _TURN_BYTES
        while budget > 0:
            with self._lock:
                if self._writing is None:
                    if not self._out:
                        return sent
                    self._writing = self._out.pop()[1]
                head = self._writing
            try:
                count = self._sock.send(head[:_CHUNK])
            except (ssl.SSLWantReadError, ssl.SSLWantWriteError, BlockingIOError):
                return sent
            sent = sent or count > 0
            budget -= count
            self.bytes_sent += count
            with self._space:
                self._out_bytes -= count
                self._writing = head[count:] if count < len(head) else None
                self._space.notify_all()
        return sent

    def _watch(self, selector: selectors.BaseSelector, watched: int, events: int) -> int:
        """Select the socket for ``events`` (none: not at all); returns them."""
        if events != watched:
            if not events:
                selector.unregister(self._sock)
            elif not watched:
                selector.register(self._sock, events)
            else:
                selector.modify(self._sock, events)
        return events

    def _run(self) -> None:
        selector = selectors.DefaultSelector()
        selector.register(self._wake_r, selectors.EVENT_READ)
        watched = 0  # the socket's events in the selector (0: not registered)
        last_rx = last_tx = time.monotonic()
        try:
            while self._closed_reason is None:
                with self._lock:
                    pending = self._out_bytes > 0
                # While an inbox is full the socket stays unread, so it stays readable: selecting on that
                # would return at once, every turn, and spin this thread. Wait for a consumer's wake-up
                # (or the poll) instead.
                self._paused = not self._deliver_stalled()
                events = (0 if self._paused else selectors.EVENT_READ) | (selectors.EVENT_WRITE if pending else 0)
                watched = self._watch(selector, watched, events)
                selector.select(timeout=0 if self._more_to_read and not self._paused else _POLL_S)
                try:
                    while self._wake_r.recv(4096):
                        pass
                except (BlockingIOError, OSError):
                    pass
                now = time.monotonic()
                if not self._deliver_stalled() or self._read_some():
                    last_rx = now  # a full inbox is ours to drain, not a silent peer
                if self._write_some():
                    last_tx = now
                if now - last_rx > self.options.dead_after_s:
                    raise LinkClosedError(f"nothing received for {self.options.dead_after_s} s (the link is down)")
                if now - last_tx > self.options.heartbeat_s and not pending:
                    with self._lock:
                        frame = encode_frame(HEARTBEAT, b"")
                        self._out.push(HEARTBEAT, memoryview(frame))
                        self._out_bytes += len(frame)
                    last_tx = now
        except (LinkClosedError, FrameError) as exc:
            self._mark_closed(str(exc))
        except (OSError, ValueError) as exc:
            self._mark_closed(f"connection failed ({exc!r})")
        finally:
            selector.close()
            for closing in (self._sock, self._wake_r, self._wake_w):
                try:
                    closing.close()
                except OSError:
                    pass
            logger.info("link to %s closed: %s", self.peer, self._closed_reason)
