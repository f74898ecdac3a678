"""Errors raised by the runtime. Each one carries enough context to act on without reading logs."""

from __future__ import annotations


class InfiniRLError(Exception):
    """Base of every InfiniRL error, so callers can catch ours without catching everything."""


class ClusterError(InfiniRLError):
    """Ray could not be started or joined, or the cluster lacks what the job asks for."""


class WorkerError(InfiniRLError):
    """A method failed on one rank of a worker group: the *root cause*, not a secondary symptom.

    The message names the component, the rank, the node and host, the method, and carries the
    original traceback text from the worker process, so the driver shows what went wrong where.
    """

    def __init__(
        self,
        component: str,
        rank: int,
        method: str,
        node_ip: str,
        hostname: str,
        pid: int | None,
        traceback_text: str,
        cause: str = "raised",
    ):
        self.component = component
        self.rank = rank
        self.method = method
        self.node_ip = node_ip
        self.hostname = hostname
        self.pid = pid
        self.traceback_text = traceback_text
        self.cause = cause
        super().__init__(self._format())

    def _format(self) -> str:
        where = f"{self.component}[rank {self.rank}].{self.method}()"
        host = f"node {self.node_ip} (host {self.hostname}, pid {self.pid})"
        body = self.traceback_text.rstrip()
        return f"{where} {self.cause} on {host}:\n{body}"

    def __reduce__(self):
        return (
            WorkerError,
            (
                self.component,
                self.rank,
                self.method,
                self.node_ip,
                self.hostname,
                self.pid,
                self.traceback_text,
                self.cause,
            ),
        )


class ChannelClosed(InfiniRLError):
    """The channel was closed and holds no more items for this key."""


class ChannelError(InfiniRLError):
    """A channel operation cannot succeed as asked (e.g. an item that can never fit maxsize, or the
    channel itself is gone)."""


class ChannelPeerDied(ChannelError):
    """A channel wait can never end: every producer of the channel died (for a getter that
    finds no item) or every consumer did (for a putter waiting for space). Names the channel,
    the key and the dead processes."""


class CallCancelled(InfiniRLError):
    """The call was cancelled (``GroupHandle.cancel()``) before it finished."""
