"""Trainer -> rollout weight sync: bucketed by dtype, stamped with a version.

The trainer group's ranks mix in ``WeightSource`` and implement ``weights_for_sync()`` (every rank
is called, so a sharded trainer can gather; rank 0's tensors are the ones sent). The rollout
group's ranks mix in ``WeightSink`` and implement ``load_weights(named_tensors, version)``.
``sync_weights(trainer, rollout, version)`` moves them and returns per-sync statistics.
``changed_only=True`` sends only the weights training can change (``weights_for_sync(changed_only=True)``,
e.g. the merged LoRA layers), to receivers that loaded a full sync before (``load_weights(...,
changed_only=True)`` refuses otherwise).

Paths (``method=``):
- ``object_store`` (CPU default): each bucket is one flat byte buffer ``ray.put`` once and mapped
  zero-copy by every receiver on the node.
- ``cuda_ipc``: trainer and receiver share a GPU (collocated): buckets go as CUDA IPC handles.
- ``collective``: a dedicated process group spanning trainer rank 0 and every receiver (NCCL on
  GPU, gloo on CPU) broadcasts each bucket; set up once with ``WeightSyncGroup``.
Every sync carries a version number that receivers stamp on the samples they generate, so the
staleness of each sample is measurable and boundable.
"""

from __future__ import annotations

import datetime
import threading
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import ray
import torch

from infinirl.runtime.p2p import nccl_options
from infinirl.runtime.payload import DTYPE_BY_NAME, box, unbox

DEFAULT_BUCKET_BYTES = 256 * 1024 * 1024


@dataclass
class TensorMeta:
    name: str
    dtype: str
    shape: tuple[int, ...]
    offset: int
    nbytes: int


def make_buckets(named_tensors: Iterable[tuple[str, torch.Tensor]], bucket_bytes: int,
                 copy: bool = False) -> Iterator[tuple[torch.Tensor, list[TensorMeta]]]:
    """Group tensors by dtype into flat uint8 buffers of at most ``bucket_bytes`` (one big tensor alone).

    A bucket of several tensors is always a new buffer; one of a single tensor is a view of it
    unless ``copy`` (a buffer the trainer's next step must not overwrite)."""
    open_buckets: dict[torch.dtype, tuple[list[torch.Tensor], list[TensorMeta], int]] = {}

    def flush(dtype):
        parts, metas, _ = open_buckets.pop(dtype)
        if len(parts) > 1:
            return torch.cat(parts), metas
        return (parts[0].clone() if copy else parts[0]), metas

    for name, tensor in named_tensors:
        tensor = tensor.detach().contiguous()
        raw = tensor.reshape(-1).view(torch.uint8)
        nbytes = raw.numel()
        parts, metas, size = open_buckets.get(tensor.dtype, ([], [], 0))
        if parts and size + nbytes > bucket_bytes:
            yield flush(tensor.dtype)
            parts, metas, size = [], [], 0
        metas.append(TensorMeta(name, str(tensor.dtype), tuple(tensor.shape), size, nbytes))
        parts.append(raw)
        open_buckets[tensor.dtype] = (parts, metas, size + nbytes)
    for dtype in list(open_buckets):
        yield flush(dtype)


def split_bucket(flat: torch.Tensor, metas: list[TensorMeta]) -> list[tuple[str, torch.Tensor]]:
    """Views into one received bucket, one per original tensor (no copies)."""
    out = []
    for meta in metas:
        piece = flat[meta.offset : meta.offset + meta.nbytes]
        out.append((meta.name, piece.view(DTYPE_BY_NAME[meta.dtype]).reshape(meta.shape)))
    return out


class WeightSource:
    """Mixin for the trainer's Worker. Implement ``weights_for_sync``."""

    def weights_for_sync(self) -> Iterable[tuple[str, torch.Tensor]]:
        """Every weight; a source that can tell which ones training changes also takes
        ``changed_only`` (see :func:`sync_weights`)."""
        raise NotImplementedError(f"{type(self).__name__} must implement weights_for_sync()")

    def _infinirl_publish_weights(self, bucket_bytes: int, cuda_ipc: bool, changed_only: bool = False) -> list | None:
        """Rank 0's buckets: object-store copies, or (``cuda_ipc``) IPC handles to private GPU
        copies. Torch keeps a sent CUDA block alive until every receiver has released it, so the
        trainer may step on (and drop its references) before the receivers have loaded."""
        # every rank runs this (a sharded gather needs all ranks)
        named = self.weights_for_sync(changed_only=True) if changed_only else self.weights_for_sync()
        if self.rank != 0:
            for _ in named:  # drain generators so collective gathers complete on every rank
                pass
            return None
        published = []
        for flat, metas in make_buckets(named, bucket_bytes, copy=cuda_ipc):
            if cuda_ipc and flat.is_cuda:
                published.append(("cuda_ipc", box(flat, cuda_ipc=True), metas))
            else:
                published.append(("object_store", [ray.put(box(flat.cpu()))], metas))
        return published

    def _infinirl_broadcast_weights(self, bucket_bytes: int) -> list[list[TensorMeta]] | None:
        """Collective path, step 1 on rank 0: bucket metadata; step 2 (below) the broadcasts."""
        named = self.weights_for_sync()
        if self.rank != 0:
            for _ in named:
                pass
            return None
        self._pending_buckets = list(make_buckets(named, bucket_bytes))
        return [metas for _, metas in self._pending_buckets]

    def _infinirl_send_buckets(self) -> int:
        sent = 0
        for flat, _ in self._pending_buckets:
            _broadcast(self._sync_group, flat)
            sent += flat.numel()
        self._pending_buckets = []
        return sent


class WeightSink:
    """Mixin for the rollout's Worker. Implement ``load_weights``; read ``weight_version``.

    Weights arrive in one of two ways. Received (:func:`start_weight_sync`): loaded by a call
    queued behind the rank's earlier calls. Staged (``interrupt=True``, partial rollouts): fetched
    at once beside whatever the rank is running, and loaded by the rank itself the next time it
    calls :meth:`apply_staged_weights` (its generation loop does between decode steps); a newer
    staged version replaces an older one not yet loaded."""

    weight_version: int = -1

    def load_weights(self, named_tensors: list[tuple[str, torch.Tensor]], version: int) -> None:
        raise NotImplementedError(f"{type(self).__name__} must implement load_weights()")

    def _infinirl_receive_weights(self, published: list, version: int, changed_only: bool = False) -> int:
        # Every bucket is fetched before the first is loaded: a bucket lost on its way (its owner
        # died, an object was evicted) then fails the sync with the weights untouched, instead of
        # leaving the earlier buckets loaded and the rest old.
        refs = [body[0] for path, body, _ in published if path == "object_store"]
        fetched = iter(ray.get(refs))
        buckets = [(unbox(next(fetched)) if path == "object_store" else unbox(body), metas)
                   for path, body, metas in published]
        # one pass over every bucket: engines may require the full state at once
        self._load((kv for flat, metas in buckets for kv in split_bucket(flat, metas)), version, changed_only)
        self._drop_staged(up_to=version)  # an older staged version must not come back later
        return sum(flat.numel() for flat, _ in buckets)

    def _load(self, named_tensors, version: int, changed_only: bool = False) -> None:
        """``load_weights``, then the version. A load that fails after taking a tensor may have
        copied it: the rank's weights are torn (two versions mixed, stamped with neither) until a
        load replaces what the failed one may have touched, and ``check_weights`` says so."""
        taken = [0]

        def counted():
            for named in named_tensors:
                taken[0] += 1
                yield named

        try:
            if changed_only:
                self.load_weights(counted(), version, changed_only=True)
            else:
                self.load_weights(counted(), version)
        except BaseException:
            if taken[0]:
                self._torn_weights = (version, changed_only)
            raise
        torn = self.__dict__.get("_torn_weights")
        # A changed-only load rewrites what a failed changed-only load touched, not a failed full one
        if torn is not None and (not changed_only or torn[1]):
            self._torn_weights = None
        self.weight_version = version

    def check_weights(self) -> None:
        """Raise if a weight load failed partway, leaving this rank's weights a mix of two versions.
        Generation must not run on them: its samples would carry a version that did not make them."""
        torn = self.__dict__.get("_torn_weights")
        if torn is not None:
            where = f"{getattr(self, 'component', type(self).__name__)}[rank {getattr(self, 'rank', 0)}]"
            raise RuntimeError(f"{where}: loading weights version {torn[0]} failed partway, so this rank's weights "
                               f"mix it with version {self.weight_version}; nothing is generated with them until a "
                               f"later sync loads (that load's own error is raised where its sync is waited for)")

    async def _infinirl_stage_weights(self, published: list, version: int) -> int:
        """Runs on the rank's event loop beside its running method: fetch, then stage."""
        buckets = []
        for path, body, metas in published:
            buckets.append((unbox(await body[0]) if path == "object_store" else unbox(body), metas))
        with _staging_lock(self):
            staged = getattr(self, "_staged_weights", None)
            if staged is None or staged[1] < version:
                self._staged_weights = (buckets, version)
        return sum(flat.numel() for flat, _ in buckets)

    def apply_staged_weights(self) -> bool:
        """Load the newest staged version, if it is newer than the loaded one. Call it only where
        a weight change is allowed (between requests, or between decode steps of a partial
        rollout). True when new weights were loaded. Raises (``check_weights``) if the weights are
        torn by a failed load, so a request that calls it first never runs on them."""
        staged = self._take_staged(newer_than=self.weight_version)
        if staged is None:
            self.check_weights()
            return False
        buckets, version = staged
        self._load((kv for flat, metas in buckets for kv in split_bucket(flat, metas)), version)
        self.check_weights()
        return True

    def _drop_staged(self, up_to: int) -> None:
        with _staging_lock(self):
            staged = getattr(self, "_staged_weights", None)
            if staged is not None and staged[1] <= up_to:
                self._staged_weights = None

    def _take_staged(self, newer_than: int):
        with _staging_lock(self):
            staged = getattr(self, "_staged_weights", None)
            self._staged_weights = None
        return staged if staged is not None and staged[1] > newer_than else None

    def _infinirl_receive_broadcast(self, bucket_metas: list[list[TensorMeta]], version: int) -> int:
        device = "cuda" if self._sync_backend == "nccl" else "cpu"
        received = [0]

        def tensors():  # buckets arrive in the sender's order; receive each as it is needed
            for metas in bucket_metas:
                size = sum(m.nbytes for m in metas)
                flat = torch.empty(size, dtype=torch.uint8, device=device)
                _broadcast(self._sync_group, flat)
                received[0] += size
                yield from split_bucket(flat, metas)

        named = tensors()
        try:
            self._load(named, version)
        finally:
            # A sink that stopped early, or failed, must still take part in every broadcast: the
            # trainer would otherwise wait in one until the group's timeout, hiding this error.
            for _ in named:
                pass
        return received[0]


def _host_sync_store(self, timeout_s: float) -> tuple[str, int]:
    """On the trainer's rank 0: bind the sync group's rendezvous store on a port the OS picks and
    keep it; a port found free and bound only when the ranks join could be taken meanwhile."""
    import torch.distributed as dist

    addr = ray.util.get_node_ip_address()
    self._sync_store = dist.TCPStore(addr, 0, is_master=True, wait_for_workers=False,
                                     timeout=datetime.timedelta(seconds=timeout_s))
    return addr, self._sync_store.port


def _join_sync_group(self, addr: str, port: int, rank: int, world: int, backend: str, timeout_s: float):
    import torch.distributed as dist

    timeout = datetime.timedelta(seconds=timeout_s)
    # Rank 0 (the trainer) hosts the store it bound in _host_sync_store; the rollout ranks connect.
    store = self._sync_store if rank == 0 else dist.TCPStore(addr, port, world, is_master=False, timeout=timeout)
    if backend == "nccl":
        from torch.distributed import ProcessGroupNCCL  # only exists in CUDA builds

        # NCCL's collectives have their own timeout (10 min by default), unrelated to the store's
        self._sync_group = ProcessGroupNCCL(store, rank, world, nccl_options(timeout))
    else:
        self._sync_group = dist.ProcessGroupGloo(store, rank, world, timeout)
    self._sync_backend = backend
    return rank


WeightSource._infinirl_host_sync_store = _host_sync_store
WeightSource._infinirl_join_sync_group = _join_sync_group
WeightSink._infinirl_join_sync_group = _join_sync_group


def _broadcast(group, tensor: torch.Tensor) -> None:
    import torch.distributed as dist

    opts = dist.BroadcastOptions()
    opts.rootRank = 0
    group.broadcast([tensor], opts).wait()


class WeightSyncGroup:
    """A process group over trainer rank 0 + all rollout ranks, for the ``collective`` path."""

    def __init__(self, source, sink, backend: str | None = None, timeout_s: float = 300.0):
        if backend is None:
            backend = "nccl" if torch.cuda.is_available() and source.contexts[0].local_devices else "gloo"
        addr, port = source.call("_infinirl_host_sync_store", timeout_s, ranks=[0]).wait(timeout=timeout_s)[0]
        world = 1 + sink.world_size
        handles = [source.call("_infinirl_join_sync_group", addr, port, 0, world, backend, timeout_s, ranks=[0])]
        handles += [
            sink.call("_infinirl_join_sync_group", addr, port, 1 + r, world, backend, timeout_s, ranks=[r])
            for r in range(sink.world_size)
        ]
        # All together: a rank that fails at once (a backend it lacks) is raised as it happens, not
        # hidden behind the others' store timing out for want of it.
        _wait_first_failure(handles)
        self.source, self.sink, self.backend = source, sink, backend


@dataclass
class SyncStats:
    version: int
    method: str
    bytes: int
    buckets: int
    seconds: float


def sync_weights(
    source,
    sink,
    version: int,
    method: str = "auto",
    bucket_bytes: int = DEFAULT_BUCKET_BYTES,
    group: WeightSyncGroup | None = None,
    changed_only: bool = False,
) -> SyncStats:
    """Copy the trainer's weights into every rollout rank and stamp them with ``version``;
    ``changed_only``: only those training can change, to ranks that loaded a full sync before."""
    return start_weight_sync(source, sink, version, method, bucket_bytes, group, changed_only=changed_only).wait()


@dataclass
class PendingSync:
    """A weight sync on its way to the rollout ranks. The trainer's part (publishing) is done when
    this exists; each rollout rank applies the weights after the calls queued on it before (a
    rank's synchronous methods run in call order), so generation requests sent after this use them."""

    version: int
    method: str
    buckets: int
    started: float
    handles: list  # the sender's handle, if any, and one per receiving rank (its result: bytes received)
    bytes_from: int = 0  # which handle's first result is the byte count

    def done(self) -> bool:
        return all(handle.done() for handle in self.handles)

    def wait(self, timeout: float | None = None) -> SyncStats:
        sender = self.handles[0] if self.method == "collective" else None
        results = _wait_first_failure(self.handles, timeout, sender)
        return SyncStats(self.version, self.method, results[self.bytes_from][0], self.buckets,
                         time.perf_counter() - self.started)


def _wait_first_failure(handles: list, timeout: float | None = None, sender=None) -> list:
    """Every handle's results, in order. The first failure of any side is raised as it happens: a
    receiver that died would otherwise be reported only once the others are done, which in a
    collective means after the sender's wait ran into its timeout. (A handle over several ranks is
    done only when all are: give each rank its own handle.) ``sender``: the handle of a collective's
    sender, whose failure may only be the symptom of a receiver's (see ``_raise_root_cause``)."""
    deadline = None if timeout is None else time.monotonic() + timeout
    pending = list(handles)
    while len(pending) > 1:
        for handle in [h for h in pending if h.done()]:
            if handle is sender:
                _raise_root_cause(sender, [h for h in handles if h is not sender])
            handle.wait(0)  # raises its failure
            pending.remove(handle)
        if deadline is not None and time.monotonic() > deadline:
            break  # the wait below names what is still running
        time.sleep(0.01)
    remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
    return [handle.wait(remaining) for handle in handles]


ROOT_CAUSE_WAIT_S = 5.0
"""How long a collective's failed sender waits for a receiver's failure to be known."""


def _raise_root_cause(sender, receivers: list) -> None:
    """The sender of a collective is done; if it failed, a receiver's death may be why, and the
    sender's error then only says that a connection closed. A receiver's failure seen within
    ``ROOT_CAUSE_WAIT_S`` is raised instead (the sender's is its context), else the sender's."""
    try:
        sender.wait(0)
        return
    except Exception:
        give_up = time.monotonic() + ROOT_CAUSE_WAIT_S
        while time.monotonic() < give_up:
            for receiver in [r for r in receivers if r.done()]:
                receiver.wait(0)  # raises its failure
                receivers.remove(receiver)
            time.sleep(0.05)
        raise


def _per_rank(sink, method: str, *args) -> list:
    """``method`` on every rank of ``sink``, one handle per rank (see ``_wait_first_failure``)."""
    return [sink.call(method, *args, ranks=[rank]) for rank in range(sink.world_size)]


def start_weight_sync(
    source,
    sink,
    version: int,
    method: str = "auto",
    bucket_bytes: int = DEFAULT_BUCKET_BYTES,
    group: WeightSyncGroup | None = None,
    interrupt: bool = False,
    changed_only: bool = False,
) -> PendingSync:
    """:func:`sync_weights` without waiting for the receivers: returns once the trainer has
    published its weights, so it can train on while the rollout ranks finish their queued requests
    and then load them (asynchronous RL). Fully detached for the object store and ``cuda_ipc``
    alike: the buckets are copies (on the object store, or private GPU buffers
    that stay allocated until every receiver has loaded them, one model's worth of GPU memory per
    sync in flight); ``collective`` blocks the trainer's next call until the receivers join the broadcast.

    ``interrupt``: stage the weights on each rank beside its running calls instead of queueing
    them behind (see :class:`WeightSink`); the pending sync is done once every rank has them.

    ``changed_only`` (object store and CUDA IPC, queued): see :func:`sync_weights`."""
    start = time.perf_counter()
    if method == "auto":
        method = "collective" if group is not None else ("cuda_ipc" if _share_a_gpu(source, sink) else "object_store")
    if changed_only and (interrupt or method == "collective"):
        raise ValueError("start_weight_sync(changed_only=True) is for queued object-store or CUDA IPC syncs: a "
                         "staged version may replace an older one a rank never loaded, and the collective path "
                         "broadcasts every weight")
    if method == "collective":
        if interrupt:
            raise ValueError("start_weight_sync(interrupt=True) stages object-store or CUDA IPC buckets; "
                             "the collective path cannot run beside the receivers' calls")
        if group is None:
            raise ValueError("sync_weights(method='collective') needs group=WeightSyncGroup(trainer, rollout)")
        metas = source.call("_infinirl_broadcast_weights", bucket_bytes).wait()[0]
        send = source.call("_infinirl_send_buckets", ranks=[0])
        received = _per_rank(sink, "_infinirl_receive_broadcast", metas, version)
        return PendingSync(version, method, len(metas), start, [send, *received], bytes_from=0)
    if method not in ("object_store", "cuda_ipc"):
        raise ValueError(f"unknown weight-sync method {method!r}; use auto, object_store, cuda_ipc or collective")
    published = source.call("_infinirl_publish_weights", bucket_bytes, method == "cuda_ipc", changed_only).wait()[0]
    if interrupt:
        received = _per_rank(sink, "_infinirl_stage_weights", published, version)
    else:
        received = _per_rank(sink, "_infinirl_receive_weights", published, version, changed_only)
    return PendingSync(version, method, len(published), start, received)


_STAGING_LOCKS_GUARD = threading.Lock()


def _staging_lock(sink) -> threading.Lock:
    """The lock between a sink's event loop (staging) and its compute thread (loading)."""
    with _STAGING_LOCKS_GUARD:
        lock = sink.__dict__.get("_staging_lock")
        if lock is None:
            lock = sink.__dict__["_staging_lock"] = threading.Lock()
    return lock


def _share_a_gpu(source, sink) -> bool:
    src = source.contexts[0]
    if not src.local_devices:
        return False
    return all(ctx.node_id == src.node_id and ctx.local_devices == src.local_devices for ctx in sink.contexts)
