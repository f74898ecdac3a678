"""Weight sync: bucketed, versioned, bit-exact on every receiver, by every CPU path."""

import pytest
import torch

from infinirl.runtime import (
    WeightSink,
    WeightSource,
    WeightSyncGroup,
    Worker,
    WorkerError,
    WorkerGroup,
    start_weight_sync,
    sync_weights,
)
from infinirl.runtime.weights import make_buckets, split_bucket
from tests.conftest import ship_by_value

ship_by_value(__name__)


def build_model(seed: int) -> torch.nn.Module:
    torch.manual_seed(seed)
    model = torch.nn.Sequential(torch.nn.Linear(64, 300), torch.nn.Tanh(), torch.nn.Linear(300, 7))
    model[2].to(torch.bfloat16)  # two dtypes -> at least two buckets
    model.register_buffer("steps", torch.tensor([3], dtype=torch.int64))
    return model


class Trainer(Worker, WeightSource):
    def __init__(self):
        self.model = build_model(seed=1)

    def train_a_bit(self):
        with torch.no_grad():
            for p in self.model.parameters():
                p.add_(torch.randn_like(p.float()).to(p.dtype))

    def weights_for_sync(self, changed_only: bool = False):
        return [(k, v) for k, v in self.model.state_dict().items() if not changed_only or k in self.CHANGING]

    CHANGING = ("2.weight", "2.bias")  # what train_the_head changes

    def train_the_head(self):
        with torch.no_grad():
            for p in self.model[2].parameters():
                p.add_(torch.randn_like(p.float()).to(p.dtype))

    def state(self):
        return {k: v.clone() for k, v in self.model.state_dict().items()}


class Rollout(Worker, WeightSink):
    def __init__(self):
        self.model = build_model(seed=2)

    def generate(self, seconds: float) -> int:
        """A request that keeps the rank busy; returns the version it ran with."""
        import time

        time.sleep(seconds)
        return self.weight_version

    def generate_partially(self, seconds: float) -> list[int]:
        """A partial rollout's shape: a step, staged weights loaded if any, another step."""
        import time

        versions = [self.weight_version]
        for _ in range(2):
            time.sleep(seconds / 2)
            self.apply_staged_weights()
            versions.append(self.weight_version)
        return versions

    def fail_next_load(self):
        self.failing = True

    def tear_next_load(self):
        self.tearing = True

    def request(self) -> int:
        """What a rollout rank's generation does first (``RolloutWorker.generate``); the version it runs."""
        self.apply_staged_weights()
        return self.weight_version

    def load_weights(self, named_tensors, version, changed_only=False):
        if getattr(self, "failing", False):
            self.failing = False
            next(iter(named_tensors))
            raise ValueError("bad shape")
        own, sent = self.model.state_dict(), set()
        if getattr(self, "tearing", False):  # copies one tensor, then fails
            self.tearing = False
            name, tensor = next(iter(named_tensors))
            own[name].copy_(tensor)
            raise OSError("disk full")
        for name, tensor in named_tensors:
            own[name].copy_(tensor)
            sent.add(name)
        self.last_sent = (sorted(sent), changed_only)

    def sent(self):
        return self.last_sent

    def state(self):
        return {k: v.clone() for k, v in self.model.state_dict().items()}

    def version(self):
        return self.weight_version


def test_buckets_split_by_dtype_and_size_and_roundtrip():
    named = [("a", torch.randn(1000)), ("b", torch.randn(10, dtype=torch.float64)),
             ("c", torch.randn(3000)), ("d", torch.arange(5))]
    buckets = list(make_buckets(named, bucket_bytes=8000))
    for flat, metas in buckets:
        assert flat.dtype == torch.uint8
        assert len({m.dtype for m in metas}) == 1
    assert sum(len(m) for _, m in buckets) == 4
    restored = dict(kv for flat, metas in buckets for kv in split_bucket(flat, metas))
    for name, tensor in named:
        assert torch.equal(restored[name], tensor) and restored[name].dtype == tensor.dtype


def test_a_bucket_of_one_tensor_is_a_view_unless_copied():
    big = torch.randn(1000)
    before = big.clone()
    (view, _), = make_buckets([("w", big)], bucket_bytes=64)
    (copy, _), = make_buckets([("w", big)], bucket_bytes=64, copy=True)
    big.add_(1.0)  # a trainer's next step
    assert torch.equal(view.view(torch.float32), big)
    assert torch.equal(copy.view(torch.float32), before)


@pytest.mark.parametrize("method", ["object_store", "collective"])
def test_sync_is_bit_exact_and_versioned(ray_cluster, method):
    trainer = WorkerGroup.launch(Trainer, "actor", num_ranks=1)
    rollout = WorkerGroup.launch(Rollout, "rollout", num_ranks=2)
    try:
        group = WeightSyncGroup(trainer, rollout) if method == "collective" else None
        assert rollout.version().wait() == [-1, -1]
        for version in (1, 2):
            trainer.train_a_bit().wait()
            stats = sync_weights(trainer, rollout, version=version, method=method,
                                 bucket_bytes=16 * 1024, group=group)
            assert stats.buckets >= 2 and stats.bytes > 0
            expected = trainer.state().wait()[0]
            for received in rollout.state().wait():
                assert received.keys() == expected.keys()
                for name in expected:
                    assert received[name].dtype == expected[name].dtype
                    assert torch.equal(received[name], expected[name]), name
            assert rollout.version().wait() == [version, version]
        # A receiver whose load fails: its error reaches the driver at once (not the trainer's
        # broadcast timing out), and the ranks stay in step for the next sync.
        rollout.fail_next_load(ranks=[1]).wait()
        with pytest.raises(WorkerError, match="bad shape"):
            sync_weights(trainer, rollout, version=3, method=method, bucket_bytes=16 * 1024, group=group)
        sync_weights(trainer, rollout, version=4, method=method, bucket_bytes=16 * 1024, group=group)
        assert rollout.version().wait() == [4, 4]
    finally:
        trainer.shutdown()
        rollout.shutdown()


def test_a_changed_only_sync_sends_what_the_source_says_changes(ray_cluster):
    """After a full sync, ``changed_only`` publishes the source's ``weights_for_sync(changed_only=True)``
    and tells the receivers so; their model is the trainer's all the same."""
    trainer = WorkerGroup.launch(Trainer, "actor", num_ranks=1)
    rollout = WorkerGroup.launch(Rollout, "rollout", num_ranks=2)
    try:
        trainer.train_a_bit().wait()
        full = sync_weights(trainer, rollout, version=1)
        trainer.train_the_head().wait()
        changed = sync_weights(trainer, rollout, version=2, changed_only=True)
        assert 0 < changed.bytes < full.bytes
        assert rollout.sent().wait() == [(["2.bias", "2.weight"], True)] * 2
        expected = trainer.state().wait()[0]
        for received in rollout.state().wait():
            assert all(torch.equal(received[name], expected[name]) for name in expected)
        assert rollout.version().wait() == [2, 2]
    finally:
        trainer.shutdown()
        rollout.shutdown()


def test_changed_only_needs_a_queued_object_store_or_cuda_ipc_sync():
    for method, interrupt in (("collective", False), ("object_store", True)):
        with pytest.raises(ValueError, match="changed_only=True"):
            start_weight_sync(None, None, version=1, method=method, interrupt=interrupt, changed_only=True)


def test_collective_needs_group(ray_cluster):
    with pytest.raises(ValueError, match="needs group"):
        sync_weights(None, None, version=1, method="collective")


def test_a_started_sync_frees_the_trainer_and_lands_between_requests(ray_cluster):
    """The asynchronous runners' contract: the trainer is free once it has published; each rollout
    rank loads the new version after the requests queued before the sync, and before later ones."""
    trainer = WorkerGroup.launch(Trainer, "actor", num_ranks=1)
    rollout = WorkerGroup.launch(Rollout, "rollout", num_ranks=1)
    try:
        sync_weights(trainer, rollout, version=1)
        before = rollout.generate(3.0)  # queued ahead of the sync
        trainer.train_a_bit().wait()
        pending = start_weight_sync(trainer, rollout, version=2)
        after = rollout.generate(0.0)  # queued behind it
        published = trainer.state().wait()[0]
        trainer.train_a_bit().wait()  # the trainer steps on at once: the published copy must not move
        assert not pending.done()  # the rank is still busy with the earlier request
        assert before.wait() == [1] and after.wait() == [2]
        assert pending.wait().version == 2
        received = rollout.state().wait()[0]
        for name, tensor in published.items():
            assert torch.equal(received[name], tensor), name
    finally:
        trainer.shutdown()
        rollout.shutdown()


def test_staged_weights_arrive_beside_a_running_request_and_load_between_its_steps(ray_cluster):
    """Partial rollouts: ``interrupt=True`` stages the weights while the rank is busy (the sync is
    done before the request is); the request loads them at its next step; the newest staged
    version wins; a later received (queued) version is never undone by an older staged one."""
    trainer = WorkerGroup.launch(Trainer, "actor", num_ranks=1)
    rollout = WorkerGroup.launch(Rollout, "rollout", num_ranks=1)
    try:
        sync_weights(trainer, rollout, version=1)
        running = rollout.generate_partially(6.0)
        trainer.train_a_bit().wait()
        start_weight_sync(trainer, rollout, version=2, interrupt=True).wait(timeout=30)
        trainer.train_a_bit().wait()
        published = trainer.state().wait()[0]
        start_weight_sync(trainer, rollout, version=3, interrupt=True).wait(timeout=30)
        assert not running.done()  # staged beside the request, not queued behind it
        assert running.wait(timeout=60) == [[1, 3, 3]]
        received = rollout.state().wait()[0]
        assert all(torch.equal(received[name], tensor) for name, tensor in published.items())

        trainer.train_a_bit().wait()
        start_weight_sync(trainer, rollout, version=4, interrupt=True).wait(timeout=30)
        sync_weights(trainer, rollout, version=5)  # queued: loads 5 and drops the staged 4
        assert rollout.generate_partially(0.0).wait() == [[5, 5, 5]]
        start_weight_sync(trainer, rollout, version=7, interrupt=True).wait(timeout=30)
        sync_weights(trainer, rollout, version=6)  # an older queued version keeps the newer staged one
        assert rollout.generate_partially(0.0).wait() == [[6, 7, 7]]
    finally:
        trainer.shutdown()
        rollout.shutdown()


def test_interrupt_needs_a_path_that_can_stage():
    with pytest.raises(ValueError, match="interrupt=True"):
        start_weight_sync(None, None, version=1, method="collective", interrupt=True)


def test_a_load_that_fails_partway_stops_the_ranks_requests_until_a_sync_repairs_it(ray_cluster):
    """A rank whose load failed after copying a tensor holds two versions mixed under the old
    stamp: the requests queued behind the sync raise, naming the failed version, instead of
    generating on them; a later full sync makes the rank whole again."""
    trainer = WorkerGroup.launch(Trainer, "actor", num_ranks=1)
    rollout = WorkerGroup.launch(Rollout, "rollout", num_ranks=2)
    try:
        sync_weights(trainer, rollout, version=1)
        rollout.tear_next_load(ranks=[1]).wait()
        trainer.train_a_bit().wait()
        pending = start_weight_sync(trainer, rollout, version=2, bucket_bytes=16 * 1024)
        behind = [rollout.request(ranks=[rank]) for rank in (0, 1)]
        with pytest.raises(WorkerError, match="disk full"):
            pending.wait(timeout=60)
        assert behind[0].wait(timeout=60) == [2]
        with pytest.raises(WorkerError, match="loading weights version 2 failed partway"):
            behind[1].wait(timeout=60)
        sync_weights(trainer, rollout, version=3)
        assert rollout.request().wait(timeout=60) == [3, 3]
    finally:
        trainer.shutdown()
        rollout.shutdown()


class RolloutWithoutBackend(Rollout):
    def _infinirl_join_sync_group(self, *args):
        if self.rank == 1:  # as a build without the group's backend fails, before it reaches the store
            raise ImportError("this torch build has no such process group backend")
        return super()._infinirl_join_sync_group(*args)


def test_a_receiver_failing_to_join_the_sync_group_is_reported_at_once(ray_cluster):
    """Not as the trainer's store timing out for want of it, after ``timeout_s``."""
    import time

    trainer = WorkerGroup.launch(Trainer, "actor", num_ranks=1)
    rollout = WorkerGroup.launch(RolloutWithoutBackend, "rollout", num_ranks=2)
    try:
        start = time.monotonic()
        with pytest.raises(WorkerError, match=r"(?s)rollout\[rank 1\].*ImportError: this torch build"):
            WeightSyncGroup(trainer, rollout, timeout_s=30)
        assert time.monotonic() - start < 15
    finally:
        trainer.shutdown()
        rollout.shutdown()


class BigTrainer(Trainer):
    def weights_for_sync(self, changed_only: bool = False):
        # One bucket larger than a socket's buffers: the broadcast waits for every receiver to read it
        return [("big", torch.ones(8 << 20))]


class DyingRollout(Rollout):
    def load_weights(self, named_tensors, version, changed_only=False):
        import os

        if self.rank == 0:
            os._exit(3)
        for _ in named_tensors:
            pass


def test_a_receiver_that_dies_in_a_collective_sync_is_reported_at_once(ray_cluster, deliberate_deaths):
    """While another receiver is still busy (so the trainer's broadcast still waits), the dead
    one's failure is raised as it happens: not once the others finished, and not the trainer's
    broadcast error it causes (a closed connection) in its place."""
    import time

    trainer = WorkerGroup.launch(BigTrainer, "actor", num_ranks=1)
    rollout = WorkerGroup.launch(DyingRollout, "rollout", num_ranks=2)
    try:
        deliberate_deaths(rollout.pids()[0])
        group = WeightSyncGroup(trainer, rollout, timeout_s=60)
        busy = rollout.generate(30.0, ranks=[1])
        start = time.monotonic()
        pending = start_weight_sync(trainer, rollout, version=1, method="collective", group=group)
        with pytest.raises(WorkerError, match=r"rollout\[rank 0\]._infinirl_receive_broadcast\(\) died"):
            pending.wait(timeout=60)
        assert time.monotonic() - start < 15 and not busy.done()
    finally:
        trainer.shutdown()
        rollout.shutdown()
