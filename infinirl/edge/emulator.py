"""A user-space network link emulator: a TCP proxy that adds one-way latency, caps the bandwidth of
each direction and can cut and restore the link on command (for hosts without ``tc netem``).

Every byte a client sends to the emulator's port goes to ``target`` and back through two pumps per
connection and direction. A pump reads what arrived, waits for the direction's token bucket (rate
``*_bytes_per_s``, depth ``burst_bytes``: the wire's serialisation time), then holds the bytes for
``latency_s`` before writing them on (propagation). Reading stops while the bucket is empty, so a
sender faster than the cap fills TCP's window and is slowed, like behind a real bottleneck.

:meth:`LinkEmulator.cut` models an outage: ``"stall"`` (default) stops forwarding without telling
either end, like a pulled cable or a dead radio link: bytes wait in the TCP buffers and flow again
after :meth:`~LinkEmulator.restore`, unless an end gave up meanwhile (its heartbeat timeout), and
new connections are accepted but carry nothing; ``"reset"`` closes every connection and refuses new
ones until restored.

    python -m infinirl.edge.emulator --listen 0.0.0.0:7000 --target 127.0.0.1:7001 --latency-ms 30 --mbit 20

prints one JSON line ``{"listening": [host, port]}`` and then reads commands from stdin, one a line:
``cut``, ``cut reset``, ``restore``, ``stats`` (answers one JSON line), ``quit``.
"""

from __future__ import annotations

import argparse
import collections
import json
import socket
import sys
import threading
import time
from dataclasses import dataclass

__all__ = ["EmulatorSpec", "LinkEmulator", "TokenBucket"]

_CHUNK = 4096
_POLL_S = 0.05


@dataclass(frozen=True, kw_only=True)
class EmulatorSpec:
    """One-way ``latency_s`` and per-direction rates in bytes/s (None: unlimited). ``up``: from the
    connecting client (the edge) to the target (the cloud); ``down``: back."""

    latency_s: float = 0.0
    up_bytes_per_s: float | None = None
    down_bytes_per_s: float | None = None
    burst_bytes: int = 16 * 1024

    @classmethod
    def from_rtt(cls, *, rtt_ms: float, mbit_per_s: float | None) -> EmulatorSpec:
        rate = None if mbit_per_s is None else mbit_per_s * 1e6 / 8
        return cls(latency_s=rtt_ms / 2000.0, up_bytes_per_s=rate, down_bytes_per_s=rate)


class TokenBucket:
    """``rate`` tokens (bytes) per second, at most ``depth`` saved up; :meth:`take` waits for them."""

    def __init__(self, rate: float | None, depth: int, clock=time.monotonic, sleep=time.sleep) -> None:
        self.rate, self.depth = rate, depth
        self._clock, self._sleep = clock, sleep
        self._tokens, self._last = float(depth), clock()
        self._lock = threading.Lock()

    def delay_for(self, count: int) -> float:
        """Take ``count`` tokens, going into debt if needed; returns how long to wait for the debt."""
        if self.rate is None:
            return 0.0
        with self._lock:
            now = self._clock()
            self._tokens = min(float(self.depth), self._tokens + (now - self._last) * self.rate)
            self._last = now
            self._tokens -= count
            return max(0.0, -self._tokens / self.rate)

    def take(self, count: int) -> None:
        delay = self.delay_for(count)
        if delay > 0:
            self._sleep(delay)


class _Pump:
    """One direction of one connection: read, rate-limit, delay, write."""

    def __init__(self, emulator: LinkEmulator, source: socket.socket, sink: socket.socket, direction: str,
                 bucket: TokenBucket, on_done) -> None:
        self.emulator, self.source, self.sink, self.direction = emulator, source, sink, direction
        self.bucket, self.on_done = bucket, on_done
        self.queue: collections.deque = collections.deque()
        self.ready = threading.Condition()
        self.reader = threading.Thread(target=self._read, daemon=True, name=f"emulator-{direction}-read")
        self.writer = threading.Thread(target=self._write, daemon=True, name=f"emulator-{direction}-write")

    def start(self) -> None:
        self.reader.start()
        self.writer.start()

    def _read(self) -> None:
        self.source.settimeout(_POLL_S)
        try:
            while not self.emulator.closing:
                if self.emulator.stalled:
                    time.sleep(_POLL_S)
                    continue
                try:
                    data = self.source.recv(_CHUNK)
                except TimeoutError:
                    continue
                if not data:
                    break
                self.bucket.take(len(data))
                self._push((time.monotonic() + self.emulator.spec.latency_s, data))
        except OSError:
            pass
        self._push(None)

    def _push(self, item) -> None:
        with self.ready:
            self.queue.append(item)
            self.ready.notify()

    def _write(self) -> None:
        try:
            while True:
                with self.ready:
                    while not self.queue:
                        self.ready.wait(_POLL_S)
                    item = self.queue.popleft()
                if item is None:
                    break
                due, data = item
                while time.monotonic() < due or self.emulator.stalled:
                    if self.emulator.closing:
                        return
                    time.sleep(min(max(due - time.monotonic(), 0.0005), _POLL_S))
                self.emulator.count(self.direction, len(data))  # before: the receiver may read at once
                self.sink.sendall(data)
        except OSError:
            pass
        finally:
            self.on_done()


class LinkEmulator:
    """The proxy (see the module docstring); a context manager; ``address``: where clients connect."""

    def __init__(self, spec: EmulatorSpec, target: tuple[str, int], listen: tuple[str, int] = ("127.0.0.1", 0)):
        self.spec, self.target = spec, target
        self.closing = False
        self.stalled = False
        self._refusing = False
        self.bytes = {"up": 0, "down": 0}
        self.connections = 0
        self._lock = threading.Lock()
        self._live: set[socket.socket] = set()
        self._buckets = {"up": TokenBucket(spec.up_bytes_per_s, spec.burst_bytes),
                         "down": TokenBucket(spec.down_bytes_per_s, spec.burst_bytes)}
        self._server = socket.create_server(listen)
        self._server.settimeout(_POLL_S)
        self.address = self._server.getsockname()[:2]
        self._thread = threading.Thread(target=self._accept_loop, daemon=True, name="emulator-accept")
        self._thread.start()

    def count(self, direction: str, nbytes: int) -> None:
        with self._lock:
            self.bytes[direction] += nbytes

    def stats(self) -> dict:
        with self._lock:
            return {"bytes_up": self.bytes["up"], "bytes_down": self.bytes["down"], "connections": self.connections,
                    "live": len(self._live) // 2, "cut": self.stalled or self._refusing}

    def cut(self, mode: str = "stall") -> None:
        if mode == "stall":
            self.stalled = True
        elif mode == "reset":
            self._refusing = True
            with self._lock:
                live = list(self._live)
            for sock in live:
                _close(sock)
        else:
            raise ValueError(f"emulator cut mode {mode!r}: choose 'stall' or 'reset'")

    def restore(self) -> None:
        self.stalled = self._refusing = False

    def close(self) -> None:
        self.closing = True
        self._thread.join(timeout=2.0)
        self._server.close()
        with self._lock:
            live = list(self._live)
        for sock in live:
            _close(sock)

    def __enter__(self) -> LinkEmulator:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _accept_loop(self) -> None:
        while not self.closing:
            try:
                client, _ = self._server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            if self._refusing:
                _close(client)
                continue
            try:
                upstream = socket.create_connection(self.target, timeout=5.0)
            except OSError:
                _close(client)
                continue
            self._join(client, upstream)

    def _join(self, client: socket.socket, upstream: socket.socket) -> None:
        for sock in (client, upstream):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        with self._lock:
            self._live.update((client, upstream))
            self.connections += 1

        def finished() -> None:  # either direction ending ends the connection, like a TCP reset
            with self._lock:
                self._live.difference_update((client, upstream))
            _close(client)
            _close(upstream)

        _Pump(self, client, upstream, "up", self._buckets["up"], finished).start()
        _Pump(self, upstream, client, "down", self._buckets["down"], finished).start()


def _close(sock: socket.socket) -> None:
    try:
        sock.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    try:
        sock.close()
    except OSError:
        pass


def _address(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    return host, int(port)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--listen", type=_address, default=("127.0.0.1", 0))
    parser.add_argument("--target", type=_address, required=True)
    parser.add_argument("--rtt-ms", type=float, default=60.0)
    parser.add_argument("--mbit", type=float, default=20.0, help="per direction; 0: unlimited")
    args = parser.parse_args(argv)
    spec = EmulatorSpec.from_rtt(rtt_ms=args.rtt_ms, mbit_per_s=args.mbit or None)
    with LinkEmulator(spec, args.target, args.listen) as emulator:
        print(json.dumps({"listening": list(emulator.address)}), flush=True)
        for line in sys.stdin:
            command = line.split()
            if not command:
                continue
            if command[0] == "quit":
                break
            if command[0] == "cut":
                emulator.cut(*command[1:2])
            elif command[0] == "restore":
                emulator.restore()
            elif command[0] != "stats":
                print(json.dumps({"error": f"unknown command {command[0]!r}: cut [stall|reset], restore, stats, quit"}),
                      flush=True)
                continue
            print(json.dumps(emulator.stats()), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
