"""Typed configuration of the SFT runner (behaviour cloning of a VLA; every field is a
``key=value`` CLI override).

Field limits are declared on the fields; :meth:`SFTConfig.check` holds the rules that involve
several fields. The dataset, the tasks and the model's sizes are checked by the runner in the
driver before training starts.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar, Literal

from infinirl.config import ConfigError, bounded
from infinirl.runners.run_config import EvalSchedule, RunConfig

__all__ = ["DataConfig", "DemoConfig", "ModelConfig", "OptimConfig", "RFTConfig", "SFTConfig", "SFTEvalConfig"]


@dataclass(kw_only=True)
class DemoConfig:
    """The MetaWorld demonstrations generated when ``data.path`` does not exist (`infinirl demos`)."""

    tasks: list[str] = field(default_factory=lambda: ["reach-v3", "push-v3", "drawer-close-v3"])
    """MetaWorld v3 task names (or a benchmark name such as MT10)."""
    episodes_per_task: int = bounded(20, ge=1)
    """Successful scripted-expert episodes kept per task."""
    image_size: int = bounded(64, ge=2)
    """Camera frames are image_size x image_size (even: H.264 video)."""
    camera: str = "corner"
    seed: int = bounded(0, ge=0)
    noise_std: float = bounded(0.1, ge=0)
    """Gaussian noise on the expert's actions: more varied states, so the clone sees recoveries."""
    instructions: Literal["env", "natural"] = "natural"
    """natural: one sentence per task (the Meta-World paper's); env: the env's own short name."""


@dataclass(kw_only=True)
class DataConfig:
    path: str = "data/metaworld_sft"
    """A LeRobotDataset v3.0 folder with one camera (video), observation.state and action; generated
    from `data.generate` when it does not exist."""
    generate: DemoConfig = field(default_factory=DemoConfig)
    camera_key: str | None = None
    """The dataset's video feature the model sees (None: its only one)."""
    min_std: float = bounded(1e-2, gt=0)
    """Floor of the state/action standard deviations used for normalisation: a dimension that hardly
    varies in the demonstrations would otherwise blow any other value far out of range."""
    augment_shift: int = bounded(4, ge=0)
    """Random image shift in pixels (pad by replication, random crop back; per sample): the
    augmentation that makes pixel-based cloning generalise from few demonstrations."""


@dataclass(kw_only=True)
class ModelConfig:
    family: Literal["pi0_smollm2"] = "pi0_smollm2"
    """The VLA family trained (π0's design on SmolLM2-135M's first layers)."""
    init: str | None = None
    """Start from this checkpoint folder of the family instead of a new model: its own sizes and chunk
    apply (the size keys below are a new model's); n_action_steps and the dataset must fit them."""
    smollm2: str | None = None
    """SmolLM2-135M folder (transformers layout); None: the embedded model."""
    language_layers: int = bounded(4, ge=1, le=30)
    """SmolLM2 decoder layers kept; the action expert has as many."""
    expert_width: int = bounded(288, ge=18)
    """Width of the action expert (a multiple of 18)."""
    expert_mlp_dim: int = bounded(768, ge=1)
    vision_channels: list[int] = bounded(default_factory=lambda: [32, 64, 128, 256], ge=8, each=True)
    """Channels of the conv stem's stride-2 stages (image tokens: (image_size / 2^stages)^2)."""
    chunk_size: int = bounded(8, ge=1)
    """Actions predicted per decision."""
    n_action_steps: int = bounded(4, ge=1)
    """Actions of each chunk executed before the next decision (evaluation and RL)."""
    num_inference_steps: int = bounded(10, ge=1)
    """Denoising steps when acting."""
    tokenizer_max_length: int = bounded(16, ge=1)
    train_language_model: bool = True
    """Fine-tune SmolLM2's layers (False: frozen; the gradients still reach the image encoder through them)."""
    train_embeddings: bool = False
    """Fine-tune SmolLM2's token embedding (49152 x 576: large, and the instructions use few tokens)."""


@dataclass(kw_only=True)
class OptimConfig:
    batch_size: int = bounded(32, ge=1)
    lr: float = bounded(3e-4, gt=0)
    lr_schedule: Literal["cosine", "constant"] = "cosine"
    """cosine: from lr down to lr * min_lr_ratio at the last iteration, after the warm-up."""
    warmup_steps: int = bounded(50, ge=0)
    """Linear warm-up from 0 over this many steps."""
    min_lr_ratio: float = bounded(0.1, ge=0, le=1)
    weight_decay: float = bounded(0.01, ge=0)
    betas: list[float] = bounded(default_factory=lambda: [0.9, 0.95], ge=0, lt=1, each=True)
    grad_clip: float = bounded(1.0, gt=0)
    """Clip the gradients' global norm to this."""


@dataclass(kw_only=True)
class RFTConfig:
    """Rejection-sampling fine-tuning (expert iteration): every ``every`` optimizer steps the policy
    being trained acts in each task's MetaWorld env on new training layouts, its successful episodes
    are kept (written to ``<output_dir>/rft/round_<k>``, a LeRobotDataset) and join the data it
    clones from. RL with success as the reward, through the behaviour-cloning loss."""

    every: int = bounded(0, ge=0)
    """Optimizer steps between collection rounds; 0: off. With ``model.init`` the first round runs
    before the first step (the initial policy's successes); a new model's first round waits ``every``."""
    episodes_per_task: int = bounded(40, ge=1)
    """Episodes tried per task each round (the successful ones are kept)."""
    num_envs: int = bounded(8, ge=1)
    """Envs of a task acting together (one batched policy pass per action chunk)."""
    seed: int = bounded(0, ge=0)
    """Layouts and sampling noise of each round derive from it (never a held-out layout)."""


@dataclass(kw_only=True)
class SFTEvalConfig(EvalSchedule):
    every: int = bounded(100, ge=0)
    tasks: list[str] = field(default_factory=list)
    """MetaWorld tasks rolled out (empty: data.generate.tasks). Each must have its instruction in
    the dataset (its natural sentence or the env's name)."""
    episodes_per_task: int = bounded(5, ge=1)
    """Held-out episodes per task, seeds 2**31 + eval.seed + i (never a demonstration's)."""
    num_envs: int = bounded(5, ge=1)
    """Envs stepped together per task."""
    seed: int = bounded(0, ge=0)
    max_episode_steps: int | None = bounded(None, ge=1)
    """Cut episodes earlier than MetaWorld's 200 steps (None: MetaWorld's limit)."""
    target: float | None = None
    """The summary names the first evaluation whose success rate reached this."""


@dataclass(kw_only=True)
class SFTConfig(RunConfig):
    RUNNER: ClassVar[str] = "sft"
    RESUME_MAY_CHANGE: ClassVar[tuple[str, ...]] = ("num_threads", "device")

    output_dir: str = "runs/sft"
    iterations: int = bounded(500, ge=1)
    """Optimizer steps."""
    save_every: int = bounded(100, ge=0)
    keep_checkpoints: int = bounded(2, ge=0)
    num_threads: int = bounded(0, ge=0)
    """torch threads (0: torch's default)."""
    device: str = "cpu"
    """Where the model trains and acts: ``cpu``, ``cuda``, ``cuda:N``, or ``auto`` (the first GPU
    when there is one, else the CPU). Batches are drawn and augmented on the CPU and moved over."""
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    eval: SFTEvalConfig = field(default_factory=SFTEvalConfig)
    rft: RFTConfig = field(default_factory=RFTConfig)

    def data_files(self) -> dict[str, str]:
        # The demonstrations' frames and statistics, and the model a run starts from.
        return {"data.path": self.data.path, **({"model.init": self.model.init} if self.model.init else {})}

    def _refused_on_resume(self, key: str) -> bool:
        # The cosine schedule spans `iterations`: the checkpoint's steps ran on the old span, so a new
        # length would continue on a different curve than the one the run started on.
        if key == "iterations" and self.optim.lr_schedule == "cosine":
            return True
        # With RFT the evaluation tasks are also the tasks each round collects in, and a task's place
        # in that list seeds its layouts: a new list changes what is trained on, not only what is evaluated.
        return key == "eval.tasks" and self.rft.every > 0

    def resume_may_change(self, key: str) -> bool:
        return not self._refused_on_resume(key) and super().resume_may_change(key)

    def resume_refusal_hint(self, key: str) -> str:
        if key == "iterations" and self._refused_on_resume(key):
            return ("optim.lr_schedule=cosine decays over iterations; to make a run extendable, start it with "
                    "optim.lr_schedule=constant")
        if key == "eval.tasks" and self._refused_on_resume(key):
            return ("with rft.every > 0, eval.tasks also names the tasks the RFT rounds collect in and seeds their "
                    "layouts; to change them, start a new run from this one's policy (model.init=<a checkpoint's "
                    "policy folder>)")
        return super().resume_refusal_hint(key)

    def check(self) -> None:
        if self.auto_placement:
            raise ConfigError("placement=auto: sft trains in one process of the driver, with no components to place; "
                              "its device key chooses where (device=auto: the first GPU, else the CPU)")
        model = self.model
        # With model.init the loaded model's chunk governs (checked against it once loaded, in the runner).
        if model.init is None and model.n_action_steps > model.chunk_size:
            raise ConfigError(f"model.n_action_steps={model.n_action_steps} must be <= model.chunk_size="
                              f"{model.chunk_size} (the executed part of each predicted chunk)")
        if model.expert_width % 18:
            raise ConfigError(f"model.expert_width={model.expert_width} must be a multiple of 18 (SmolLM2's 9 "
                              "heads, and even for the flow-time embedding)")
        if self.optim.warmup_steps >= self.iterations and self.optim.warmup_steps > 0:
            raise ConfigError(f"optim.warmup_steps={self.optim.warmup_steps} must be below iterations="
                              f"{self.iterations}")
        if not (self.device in ("cpu", "cuda", "auto") or self.device.startswith("cuda:")
                and self.device[5:].isdigit()):
            raise ConfigError(f"device={self.device!r}: use cpu, cuda, cuda:N or auto")
        if len(self.optim.betas) != 2:
            raise ConfigError(f"optim.betas={self.optim.betas}: give two numbers (AdamW's beta1, beta2)")
