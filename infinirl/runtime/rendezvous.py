"""Rendezvous addresses for torch.distributed groups.

A ``WorkerGroup``'s own group: rank 0 binds the group's rendezvous store (a ``TCPStore``) on a port
the OS picks, when its process starts, and holds it for the life of the process (``host_master``);
it publishes ``addr:port`` in Ray's key-value store, where every other rank reads it before its
Worker is built (``await_master``). A port found free and bound only later (when the group forms,
maybe much later) could be taken meanwhile by another group or program. torch's ``env://``
rendezvous in rank 0 then reuses the held store (``multi_tenant``: one server per port and process).

The weight-sync group between a trainer and its rollout ranks does the same: the trainer's rank 0
binds its store on a port the OS picks before the other ranks are told where to join.
"""

from __future__ import annotations

import time
from typing import Any

import ray

__all__ = ["RENDEZVOUS_TIMEOUT_S", "await_master", "forget", "host_master", "new_key"]

# How long a rank waits for rank 0 to publish the rendezvous: rank 0's process may start later
# than the others (a busy node); a rank 0 that never starts fails the launch well before this.
RENDEZVOUS_TIMEOUT_S = 300.0
_KV_NAMESPACE = "infinirl-rendezvous"


def new_key(component: str) -> str:
    """The key one group's rendezvous is published under (one per launch)."""
    import uuid

    return f"{component}-{uuid.uuid4().hex}"


def host_master(key: str) -> tuple[str, int, Any]:
    """In rank 0's process: bind the rendezvous store and publish its address under ``key``.
    Returns ``(addr, port, store)``; the caller keeps the store for the life of the process.

    A restarted rank 0 binds the port its group already knows again (its old process is gone);
    should something else hold it by then, the error names the port."""
    import torch.distributed as dist

    addr = ray.util.get_node_ip_address()
    published = _kv_get(key)
    port = int(published.rpartition(":")[2]) if published else 0
    try:
        store = dist.TCPStore(addr, port, is_master=True, multi_tenant=True, wait_for_workers=False)
    except Exception as exc:
        if not port:
            raise
        raise RuntimeError(f"rank 0 could not bind its group's torch.distributed rendezvous port {port} on {addr} "
                           f"again after a restart ({str(exc).strip()[:200]}); launch the group anew") from None
    _kv_put(key, f"{addr}:{store.port}")
    return addr, store.port, store


def await_master(key: str, timeout_s: float = RENDEZVOUS_TIMEOUT_S) -> tuple[str, int]:
    """In the other ranks' processes: ``(addr, port)`` of the rendezvous rank 0 published."""
    deadline = time.monotonic() + timeout_s
    while True:
        published = _kv_get(key)
        if published:
            addr, _, port = published.rpartition(":")
            return addr, int(port)
        if time.monotonic() > deadline:
            raise TimeoutError(f"rank 0 of the group did not publish its torch.distributed rendezvous "
                               f"(key {key!r}) within {timeout_s:g} s")
        time.sleep(0.05)


def forget(key: str) -> None:
    """Remove a group's published rendezvous (the group is gone)."""
    try:
        from ray.experimental import internal_kv

        if internal_kv._internal_kv_initialized():
            internal_kv._internal_kv_del(key, namespace=_KV_NAMESPACE)
    except Exception:  # Ray is shut down: the store went with it
        pass


def _kv_get(key: str) -> str | None:
    from ray.experimental import internal_kv  # Ray's key-value store in the GCS, seen by every process

    value = internal_kv._internal_kv_get(key, namespace=_KV_NAMESPACE)
    return value.decode() if value else None


def _kv_put(key: str, value: str) -> None:
    from ray.experimental import internal_kv

    internal_kv._internal_kv_put(key, value, overwrite=True, namespace=_KV_NAMESPACE)

