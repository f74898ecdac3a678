"""Runtime on a real GPU: discovery, placement env, NCCL group, CUDA IPC channel and weight sync."""

import pytest
import torch

from infinirl.runtime import (
    Channel,
    WeightSink,
    WeightSource,
    Worker,
    WorkerGroup,
    device_turn,
    place,
    start_weight_sync,
    sync_weights,
)
from infinirl.runtime.transport import pack
from tests.conftest import ship_by_value

ship_by_value(__name__)
pytestmark = pytest.mark.gpu


class GpuWorker(Worker, WeightSource, WeightSink):
    def __init__(self, seed: int):
        torch.manual_seed(seed)
        self.model = torch.nn.Linear(256, 256).to(self.device)
        self.model.half()

    def env(self):
        import os

        return {"cuda_visible": os.environ.get("CUDA_VISIBLE_DEVICES"), "device": self.device,
                "count": torch.cuda.device_count()}

    def nccl_allreduce(self):
        import torch.distributed as dist

        self.init_process_group()
        t = torch.ones(4, device="cuda") * (self.rank + 1)
        dist.all_reduce(t)
        return dist.get_backend(), t.sum().item()

    def put_cuda(self, ch: Channel):
        t = torch.arange(1 << 20, device="cuda", dtype=torch.float32)
        envelope = pack(t)  # in a Worker: an offer the consumer takes by IPC (same GPU) or NCCL
        assert envelope.path == "p2p" and envelope.body.ipc is not None
        from infinirl.runtime import p2p

        p2p.release(envelope.body.item)
        ch.put({"t": t})
        torch.cuda.synchronize()
        return float(t.sum().item())

    def get_cuda(self, ch: Channel):
        item = ch.get(timeout=120)
        return item["t"].device.type, float(item["t"].sum().item())

    def busy(self, seconds: float):
        """A generation stand-in: the weight version it ran with, after ``seconds``."""
        import time

        time.sleep(seconds)
        return self.weight_version

    def load_staged(self):
        return self.apply_staged_weights(), self.weight_version

    def step_in_place(self):
        with torch.no_grad():
            for p in self.model.parameters():
                p.add_(1.0)

    def weights_for_sync(self):
        return self.model.state_dict().items()

    def load_weights(self, named_tensors, version):
        own = self.model.state_dict()
        for name, tensor in named_tensors:
            own[name].copy_(tensor)

    def state(self):
        return {k: v.cpu() for k, v in self.model.state_dict().items()}

    def turn(self):
        with device_turn(self):
            return True


def test_gpu_inventory_and_placement_env(ray_cluster):
    inv = ray_cluster.refresh()
    assert inv.accelerator_kind == "cuda" and inv.num_accelerators == torch.cuda.device_count()
    assert inv.nodes[0].accelerators[0].memory_bytes > 10 * 2**30
    plan = place(inv, {"trainer": "0", "rollout": "0"})
    assert plan.mode == "collocated"
    group = WorkerGroup.launch(GpuWorker, "trainer", placement=plan.ranks("trainer"), args=(0,))
    try:
        env = group.env().wait()[0]
        assert env == {"cuda_visible": "0", "device": "cuda", "count": 1}
        backend, total = group.nccl_allreduce().wait(timeout=120)[0]
        assert backend == "nccl" and total == 4.0
        assert group.turn().wait(timeout=60) == [True]
    finally:
        group.shutdown()


def test_cuda_ipc_channel_and_weight_sync_on_one_gpu(ray_cluster):
    plan = place(ray_cluster.inventory, {"trainer": "0", "rollout": "0"})
    trainer = WorkerGroup.launch(GpuWorker, "trainer", placement=plan.ranks("trainer"), args=(1,))
    rollout = WorkerGroup.launch(GpuWorker, "rollout", placement=plan.ranks("rollout"), args=(2,))
    try:
        ch = Channel.create("gpu-ipc")
        got = rollout.get_cuda(ch)
        sent = trainer.put_cuda(ch).wait(timeout=120)[0]
        assert got.wait(timeout=120)[0] == ("cuda", sent)
        stats = sync_weights(trainer, rollout, version=7)
        assert stats.method == "cuda_ipc"
        expected, received = trainer.state().wait()[0], rollout.state().wait()[0]
        assert all(torch.equal(expected[k], received[k]) for k in expected)
    finally:
        trainer.shutdown()
        rollout.shutdown()


def test_a_started_cuda_ipc_sync_frees_the_trainer_before_the_rollout_loads(ray_cluster):
    """Asynchronous training on one GPU: the trainer publishes private GPU copies and steps on at
    once (overwriting its weights in place) while the rollout rank is still busy; the rank then
    loads the published weights, not the stepped ones."""
    plan = place(ray_cluster.inventory, {"trainer": "0", "rollout": "0"})
    trainer = WorkerGroup.launch(GpuWorker, "trainer", placement=plan.ranks("trainer"), args=(1,))
    rollout = WorkerGroup.launch(GpuWorker, "rollout", placement=plan.ranks("rollout"), args=(2,))
    try:
        sync_weights(trainer, rollout, version=1)
        before = rollout.busy(3.0)
        published = trainer.state().wait()[0]
        # small buckets: the weight matrix alone in one (the bucket that could alias the weights)
        pending = start_weight_sync(trainer, rollout, version=2, bucket_bytes=1024)
        assert pending.method == "cuda_ipc"
        after = rollout.busy(0.0)
        trainer.step_in_place().wait(timeout=60)  # the trainer is free while the rank is busy
        assert not pending.done()
        assert before.wait(timeout=60) == [1] and after.wait(timeout=60) == [2]
        assert pending.wait(timeout=60).version == 2
        received, stepped = rollout.state().wait()[0], trainer.state().wait()[0]
        for name, tensor in published.items():
            assert torch.equal(received[name], tensor), name
            assert not torch.equal(stepped[name], tensor), name
    finally:
        trainer.shutdown()
        rollout.shutdown()


def test_cuda_ipc_weights_staged_beside_a_busy_rank_load_at_its_next_step(ray_cluster):
    """Partial rollouts on one GPU: the weights are staged (CUDA IPC handles rebuilt on the rank's
    event loop) while it is busy, then loaded by the rank itself."""
    plan = place(ray_cluster.inventory, {"trainer": "0", "rollout": "0"})
    trainer = WorkerGroup.launch(GpuWorker, "trainer", placement=plan.ranks("trainer"), args=(1,))
    rollout = WorkerGroup.launch(GpuWorker, "rollout", placement=plan.ranks("rollout"), args=(2,))
    try:
        sync_weights(trainer, rollout, version=1)
        busy = rollout.busy(3.0)
        trainer.step_in_place().wait(timeout=60)
        published = trainer.state().wait()[0]
        start_weight_sync(trainer, rollout, version=2, interrupt=True).wait(timeout=60)
        assert not busy.done()
        trainer.step_in_place().wait(timeout=60)  # the staged copies are private: this must not leak in
        assert busy.wait(timeout=60) == [1]
        assert rollout.load_staged().wait(timeout=60) == [(True, 2)]
        received = rollout.state().wait()[0]
        assert all(torch.equal(received[name], tensor) for name, tensor in published.items())
    finally:
        trainer.shutdown()
        rollout.shutdown()
