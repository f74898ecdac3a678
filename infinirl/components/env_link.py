"""The per-step stream between one env rank and one rollout rank: observations one way, actions back.

Two transports behind one tiny interface (``send(obj)``, ``recv()``, ``close()``):

* ``socket`` (default): a dedicated connection between the two processes
  (``multiprocessing.connection``: a Unix socket when both ranks share a node, TCP otherwise,
  authenticated with a random key). Messages are a few small numpy arrays per env step, so the
  cost that matters is the latency of one message, paid twice per stage and step.
* ``channel``: two :class:`~infinirl.runtime.Channel` queues (one per direction). Works wherever
  Ray does and needs no port, at the price of a round trip through the channel actor per message.

Why a socket is the default: a round trip of one small observation and its actions must cost less
than the simulator step it feeds, or the pipeline mostly waits on itself. A direct socket is one
kernel hand-off per message with little CPU on either side; a Channel adds a round trip through
its actor per message, a Ray actor call goes through Ray's scheduling, and gloo's send/recv spins
a core while it waits. Of these, only the socket stays well below a cheap simulator's step. Bulk
data (trajectories to the trainer, weights) still moves through Ray, where its size, not its
latency, matters.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import tempfile
from multiprocessing.reduction import ForkingPickler
from typing import Any

from infinirl.runtime.errors import InfiniRLError

__all__ = ["TRANSPORTS", "EnvLinkClosed", "accept", "close_server", "connect", "open_server"]

TRANSPORTS = ("socket", "channel")


class EnvLinkClosed(InfiniRLError):
    """The other end of the link closed it: a *symptom*. The side that closed it failed (or was
    stopped) and reports its own error; the runner prefers that one as the root cause."""


class _SocketLink:
    """``bytes_sent``: the pickled bytes this end has sent (what the scheduler's cost model charges
    a link between nodes); pickled as ``Connection.send`` would, only counted on the way."""

    def __init__(self, conn):
        self._conn = conn
        self.bytes_sent = 0

    def send(self, obj: Any) -> None:
        payload = ForkingPickler.dumps(obj)
        try:
            self._conn.send_bytes(payload)
        except (BrokenPipeError, ConnectionError) as exc:
            raise EnvLinkClosed(f"the env link's other end is gone ({exc!r})") from None
        self.bytes_sent += len(payload)

    def recv(self) -> Any:
        try:
            return ForkingPickler.loads(self._conn.recv_bytes())
        except (EOFError, ConnectionError) as exc:
            raise EnvLinkClosed(f"the env link's other end closed it ({exc!r})") from None

    def fileno(self) -> int:
        """For ``multiprocessing.connection.wait``: serve whichever link has a message."""
        return self._conn.fileno()

    def close(self) -> None:
        self._conn.close()


class _ChannelLink:
    """Each end is the only producer of its outbox. Closing the link closes the outbox, so the other
    end's next ``recv`` drains what was sent and then fails with :class:`EnvLinkClosed`, as over a
    socket: a side that only flushed would leave its peer waiting forever for a message that never
    comes (a failed env rank, a failed rollout)."""

    def __init__(self, outbox, inbox):
        self._outbox, self._inbox = outbox, inbox
        self._closed = False

    def send(self, obj: Any) -> None:
        from infinirl.runtime.errors import ChannelClosed, ChannelPeerDied

        try:
            self._outbox.put(obj)
        except (ChannelClosed, ChannelPeerDied) as exc:
            raise EnvLinkClosed(f"the env link's other end is gone ({exc!r})") from None

    def recv(self) -> Any:
        from infinirl.runtime.errors import ChannelClosed, ChannelPeerDied

        try:
            return self._inbox.get()
        except (ChannelClosed, ChannelPeerDied) as exc:
            raise EnvLinkClosed(f"the env link's other end closed it ({exc!r})") from None

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        from infinirl.runtime.errors import ChannelError

        try:
            self._outbox.close()  # flushes the puts in flight first
        except ChannelError:  # the channel's actor or the peer is gone already: nobody is left to tell
            pass


class _SocketServer:
    def __init__(self, listener, path: str | None):
        self.listener, self.path = listener, path


def open_server(transport: str, channel_names: tuple[str, str] | None = None, *, family: str | None = None):
    """The env side's listening end and the address the rollout connects to."""
    if transport == "channel":
        if channel_names is None:
            raise ValueError("the channel transport needs channel_names=(to_rollout, to_env)")
        return ("channel", channel_names), {"transport": "channel", "names": channel_names}
    if transport != "socket":
        raise ValueError(f"unknown env link transport {transport!r}; choose one of {TRANSPORTS}")
    from multiprocessing.connection import Listener

    authkey = secrets.token_bytes(16)
    if family is None:
        family = "AF_UNIX"
    if family == "AF_UNIX":
        path = os.path.join(tempfile.mkdtemp(prefix="infinirl-link-"), "env.sock")
        listener = Listener(path, family="AF_UNIX", authkey=authkey)
        address = {"transport": "socket", "family": "AF_UNIX", "address": path, "authkey": authkey,
                   "host": _host_ip()}
        return _SocketServer(listener, path), address
    listener = Listener((_host_ip(), 0), family="AF_INET", authkey=authkey)
    address = {"transport": "socket", "family": "AF_INET", "address": listener.address, "authkey": authkey,
               "host": _host_ip()}
    return _SocketServer(listener, None), address


def accept(server) -> Any:
    """Wait for the rollout to connect; the env side's link."""
    if isinstance(server, tuple) and server[0] == "channel":
        from infinirl.runtime import Channel

        to_rollout, to_env = server[1]
        outbox = Channel.connect(to_rollout)
        inbox = Channel.connect(to_env)
        inbox.register_consumer()
        return _ChannelLink(outbox, inbox)
    conn = server.listener.accept()
    close_server(server)
    return _SocketLink(conn)


def close_server(server) -> None:
    """Stop listening and remove a Unix socket's temporary directory (idempotent). Called once
    the rollout has connected, and by the env side's close in case it never did.

    The listener's own close already unlinks the socket file, so the directory is removed on its
    own: unlinking and removing the directory in one ``try`` left every directory behind."""
    if not isinstance(server, _SocketServer):
        return  # the channel transport listens on nothing
    server.listener.close()
    if server.path:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(server.path)
        with contextlib.suppress(FileNotFoundError):
            os.rmdir(os.path.dirname(server.path))


def connect(address: dict) -> Any:
    """The rollout side's link to the env rank that published ``address``. A Unix-socket address
    from another node is reached over TCP instead (the env rank must then listen on TCP)."""
    if address["transport"] == "channel":
        from infinirl.runtime import Channel

        to_rollout, to_env = address["names"]
        inbox = Channel.connect(to_rollout)
        inbox.register_consumer()
        outbox = Channel.connect(to_env)
        return _ChannelLink(outbox, inbox)
    from multiprocessing.connection import Client

    conn = Client(address["address"], family=address["family"], authkey=address["authkey"])
    return _SocketLink(conn)


def _host_ip() -> str:
    try:
        import ray

        return ray.util.get_node_ip_address()
    except Exception:  # outside Ray (tests)
        return "127.0.0.1"
