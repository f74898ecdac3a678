"""Runtime demo: the macro-flow shape of every InfiniRL job, on a task small enough to read whole.

Samplers (a component with a policy copy) draw inputs, label them with a hidden linear function and
score the current policy on them: a stand-in for rollout + reward. They stream micro-batches into a
channel. The learner (data-parallel over its ranks with gloo/NCCL all-reduce) trains on whatever
arrives, and its weights are synced back to the samplers with a version, so each sample records
how stale its policy was. Placement alone decides collocated vs disaggregated; this code doesn't.
"""

from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import dataclass, field
from typing import ClassVar

import torch

from infinirl.config import ConfigError, bounded, to_plain
from infinirl.runners import register_runner
from infinirl.runtime import (
    Channel,
    Cluster,
    ClusterConfig,
    Tracer,
    WeightSink,
    WeightSource,
    Worker,
    WorkerGroup,
    place,
    sync_weights,
)

logger = logging.getLogger(__name__)


@dataclass(kw_only=True)
class DemoConfig:
    """Every field documented: it is also the CLI reference (`key=value` overrides)."""

    RENAMED_KEYS: ClassVar[dict[str, str]] = {"steps": "iterations"}

    runner: str = "runtime_demo"
    iterations: int = bounded(20, ge=1)
    """Training iterations (each: sample, train, sync)."""
    dim: int = bounded(16, ge=1)
    """Input dimension of the hidden linear task."""
    samples_per_step: int = bounded(512, ge=1)
    """Samples produced per iteration over all sampler ranks."""
    micro_batch: int = bounded(64, ge=1)
    """Samples per channel item (the unit that streams from samplers to the learner)."""
    lr: float = bounded(0.05, gt=0)
    seed: int = 0
    output_dir: str = "runs/runtime_demo"
    """Where the metrics (JSONL) and the Chrome/Perfetto trace go."""
    placement: dict[str, str] = field(default_factory=lambda: {"sampler": "0", "learner": "1"})
    """Component -> device/CPU-slot spec (see infinirl.runtime.placement)."""
    cluster: ClusterConfig = field(default_factory=ClusterConfig)

    def validate(self) -> None:
        from infinirl.runners.run_config import validate_placement

        if self.runner != "runtime_demo":
            raise ConfigError(f"runner={self.runner!r}: this config is for the 'runtime_demo' runner")
        if set(self.placement) != {"sampler", "learner"}:
            raise ConfigError(
                f"placement must name exactly the components sampler and learner, got {sorted(self.placement)}"
            )
        validate_placement(self.placement, ("sampler", "learner"), "runtime_demo")


def _policy(dim: int) -> torch.nn.Module:
    return torch.nn.Linear(dim, 1)


class Sampler(Worker, WeightSink):
    def __init__(self, dim: int, seed: int):
        self.policy = _policy(dim)
        self.generator = torch.Generator().manual_seed(seed + 1000 * self.rank)
        hidden = torch.Generator().manual_seed(seed)
        self.true_w = torch.randn(dim, 1, generator=hidden)

    def load_weights(self, named_tensors, version):
        own = self.policy.state_dict()
        for name, tensor in named_tensors:
            own[name].copy_(tensor)

    def produce(self, out: Channel, n: int, micro_batch: int) -> float:
        """Stream ``n`` labelled samples in micro-batches; return the policy's loss on them."""
        losses = []
        for start in range(0, n, micro_batch):
            x = torch.randn(min(micro_batch, n - start), self.true_w.shape[0], generator=self.generator)
            y = x @ self.true_w
            with torch.no_grad():
                losses.append(torch.nn.functional.mse_loss(self.policy(x), y).item())
            out.put({"x": x, "y": y, "version": torch.tensor(self.weight_version)}, weight=len(x))
        return sum(losses) / len(losses)


class Learner(Worker, WeightSource):
    def __init__(self, dim: int, lr: float, seed: int):
        torch.manual_seed(seed)
        self.policy = _policy(dim)
        self.optimizer = torch.optim.SGD(self.policy.parameters(), lr=lr)
        self.version = 0
        self.init_process_group()

    def train(self, inbox: Channel, samples: int) -> dict:
        """Consume this rank's share of the step's samples, all-reduce gradients, step once."""
        import torch.distributed as dist

        share = samples // self.world_size
        batches = inbox.get_batch(target_weight=share)
        x = torch.cat([b["x"] for b in batches])
        y = torch.cat([b["y"] for b in batches])
        staleness = [self.version - int(b["version"]) for b in batches]
        self.optimizer.zero_grad()
        loss = torch.nn.functional.mse_loss(self.policy(x), y)
        loss.backward()
        for p in self.policy.parameters():
            dist.all_reduce(p.grad)
            p.grad /= self.world_size
        self.optimizer.step()
        self.version += 1
        return {"loss": loss.item(), "max_staleness": max(staleness), "samples": len(x)}

    def weights_for_sync(self):
        return self.policy.state_dict().items()


@register_runner("runtime_demo", DemoConfig, "placement + worker groups + channel + weight sync + tracing")
def run(cfg: DemoConfig) -> dict:
    os.makedirs(cfg.output_dir, exist_ok=True)
    with Cluster(cfg.cluster) as cluster:
        plan = place(cluster.inventory, cfg.placement, components=["sampler", "learner"])
        print(plan.describe(), flush=True)
        samplers = WorkerGroup.launch(Sampler, "sampler", placement=plan.ranks("sampler"), args=(cfg.dim, cfg.seed))
        learner = WorkerGroup.launch(Learner, "learner", placement=plan.ranks("learner"),
                                     args=(cfg.dim, cfg.lr, cfg.seed))
        channel = Channel.create(f"demo-{os.getpid()}", maxsize=4 * cfg.samples_per_step)
        tracer = Tracer()
        history = []
        per_sampler = cfg.samples_per_step // samplers.world_size
        from tqdm import tqdm

        for step in tqdm(range(cfg.iterations), desc="runtime_demo", unit="step"):
            t0 = time.perf_counter()
            produced = samplers.produce(channel, per_sampler, cfg.micro_batch)  # returns at once
            trained = learner.train(channel, per_sampler * samplers.world_size)  # streams as items land
            policy_loss = sum(produced.wait()) / samplers.world_size
            metrics = trained.wait()
            sync = sync_weights(learner, samplers, version=step + 1)
            history.append({
                "step": step,
                "rollout/policy_loss": policy_loss,
                "train/loss": sum(m["loss"] for m in metrics) / len(metrics),
                "rollout/max_staleness": max(m["max_staleness"] for m in metrics),
                "time/step_s": time.perf_counter() - t0,
                "time/weight_sync_s": sync.seconds,
            })
        tracer.collect(samplers, learner)
        trace = tracer.write_chrome_trace(os.path.join(cfg.output_dir, "trace.json"))
        busy = tracer.busy_ratio()
        with open(os.path.join(cfg.output_dir, "metrics.jsonl"), "w") as handle:
            for row in history:
                handle.write(json.dumps(row) + "\n")
        with open(os.path.join(cfg.output_dir, "config.json"), "w") as handle:
            json.dump(to_plain(cfg), handle, indent=2)
        summary = {
            "mode": plan.mode,
            "first_loss": history[0]["rollout/policy_loss"],
            "final_loss": history[-1]["rollout/policy_loss"],
            "busy_ratio": busy,
            "trace": trace,
        }
        print(json.dumps(summary, indent=2), flush=True)
        samplers.shutdown()
        learner.shutdown()
        return summary
