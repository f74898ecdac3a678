"""SFT: behaviour cloning of a VLA on demonstrations (flow matching), evaluated in MetaWorld.

Read top to bottom: the dataset (a LeRobotDataset v3.0 folder; MetaWorld scripted-expert demos are
generated into it first when it does not exist) is read into memory once; the VLA is built
(``pi0_smollm2``: SmolLM2's first layers, a conv stem, a narrow action expert) with the dataset's
state/action statistics and the instruction of each evaluation task; every iteration draws a
batch of frames, each with the chunk of actions that follows it in its episode (rows past the
episode's end are padding, left out of the loss), shifts the images a few pixels at random, and
takes one AdamW step on the flow-matching loss (gradients clipped, cosine or constant learning
rate after a linear warm-up). Every ``eval.every`` iterations the policy acts deterministically
(π0's ODE sampler, ``n_action_steps`` actions of each chunk executed) in each evaluation task's
MetaWorld env from the rendered camera, on held-out seeds, and its success rate is logged. With
``rft.every`` the policy's own solved episodes on new layouts join the frames every so many steps
(rejection-sampling fine-tuning: :mod:`infinirl.runners.sft_rft`).

It runs in the driver process (one small model, no components to place), on ``device`` (the CPU,
or a GPU). Checkpoints hold the
model as a loadable VLA folder (``policy/``), the optimizer state, and the loop's RNG state, so a
resumed run continues bit for bit; the final model is also written to ``<output_dir>/policy/``,
which the ``pi0_smollm2`` policy loads for RL.
"""

from __future__ import annotations

import hashlib
import math
import os
import time
from pathlib import Path

import numpy as np
import torch

from infinirl.config import ConfigError
from infinirl.data.demo_frames import CAMERA_PREFIX, DemoFrames
from infinirl.runners import register_runner
from infinirl.runners.curves import Panel
from infinirl.runners.loop import LoopSpec, ProgressField, RunLoop
from infinirl.runners.run_support import run_start_time
from infinirl.runners.sft_config import SFTConfig
from infinirl.runners.sim_config import eval_seeds
from infinirl.utils import torch_save_atomic
from infinirl.utils.memory import peak_memory_bytes

__all__ = ["SFTFlow", "evaluation_tasks", "learning_rate", "load_optimizer_state", "preflight", "read_demos",
           "rollout_episodes", "run", "task_instructions"]

POLICY_DIR = "policy"
OPTIMIZER_FILE = "optimizer.pt"


def preflight(cfg: SFTConfig) -> list[str]:
    """The evaluation tasks (benchmark names resolved), ``model.init``'s files (its config and the
    headers of its tensor files: no weights are loaded) and, when ``data.path`` exists, the
    dataset's metadata against them; when it does not, what generating it needs. In the driver before
    anything is generated or trained (``infinirl validate`` runs it too); the evaluation tasks."""
    from infinirl.data.demos import metaworld_features

    tasks = evaluation_tasks(cfg)
    init = _read_init(cfg)
    if Path(cfg.data.path).exists():
        reader = open_dataset(cfg)
        if not reader.num_episodes:
            raise ConfigError(f"data.path={cfg.data.path}: the dataset has no episodes; record demonstrations into it")
        camera = DemoFrames.camera_of(reader, cfg.data.camera_key)
        _check_stats(reader)
        task_instructions(tasks, reader.tasks)
        shapes = {key: int(reader.features[key]["shape"][0]) for key in ("observation.state", "action")}
    else:
        _check_generation(cfg, tasks)
        gen = cfg.data.generate
        features = metaworld_features(gen.camera, gen.image_size)
        camera = f"{CAMERA_PREFIX}{gen.camera}"
        shapes = {key: int(features[key]["shape"][0]) for key in ("observation.state", "action")}
    if init is not None:
        _check_init_fits(init, cfg, shapes["observation.state"], shapes["action"], camera)
    return tasks


@register_runner("sft", SFTConfig, "behaviour cloning (flow matching) of a VLA on a LeRobotDataset of "
                                   "demonstrations, with held-out success in MetaWorld", preflight=preflight)
def run(cfg: SFTConfig) -> dict:
    if cfg.num_threads:
        torch.set_num_threads(cfg.num_threads)
    compute_device(cfg.device)  # a GPU that is not there fails here, before the dataset is read
    tasks = preflight(cfg)  # before demonstrations are generated
    # The demonstrations are generated once the run is found resumable and before it records its
    # inputs: their digest is recorded with the first checkpoint and compared on resume.
    with RunLoop(cfg, run_start_time(), prepare=lambda: generate_dataset(cfg)) as loop:
        reader = open_dataset(cfg)
        flow = SFTFlow(cfg, read_demos(reader, cfg.data.camera_key), task_instructions(tasks, reader.tasks))
        try:
            return loop.run(flow)
        finally:
            flow.close()


def compute_device(device: str) -> torch.device:
    """``device`` resolved (``auto``: the first GPU if any); a GPU this machine lacks is a ConfigError."""
    if device == "auto":
        return torch.device("cuda:0" if torch.cuda.is_available() else "cpu")
    resolved = torch.device(device)
    if resolved.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        index = resolved.index or 0
        if index >= count:
            raise ConfigError(f"device={device!r}: this machine has {count} CUDA device(s); use device=cpu or auto")
    return resolved


# ---------------------------------------------------------------------------------------------
# Data


def evaluation_tasks(cfg: SFTConfig) -> list[str]:
    """The MetaWorld tasks evaluated (and collected in by the RFT rounds): ``eval.tasks``, else
    ``data.generate.tasks``, with benchmark names (MT10) resolved to their tasks."""
    from infinirl.data.demos import resolve_metaworld_tasks

    key, names = ("eval.tasks", cfg.eval.tasks) if cfg.eval.tasks else ("data.generate.tasks", cfg.data.generate.tasks)
    if not names:
        raise ConfigError("eval.tasks is empty and so is data.generate.tasks: name the MetaWorld tasks to evaluate")
    try:
        return list(resolve_metaworld_tasks(",".join(names)))
    except ValueError as exc:
        raise ConfigError(f"{key}: {exc}") from None


def demo_spec(cfg: SFTConfig):
    """The :class:`~infinirl.data.demos.DemoSpec` that generates ``data.path`` from ``data.generate``."""
    from infinirl.data.demos import DemoSpec, resolve_metaworld_tasks

    gen = cfg.data.generate
    try:
        return DemoSpec(tasks=resolve_metaworld_tasks(",".join(gen.tasks)), episodes_per_task=gen.episodes_per_task,
                        out=str(cfg.data.path), image_size=gen.image_size, camera=gen.camera, seed=gen.seed,
                        noise_std=gen.noise_std, instructions=gen.instructions)
    except ValueError as exc:
        raise ConfigError(f"data.generate: {exc}") from None


def _check_generation(cfg: SFTConfig, tasks: list[str]) -> None:
    """What generating ``data.path`` needs: its settings, the ffmpeg binary that encodes its videos,
    and every evaluation task among the generated ones."""
    from infinirl.data.lerobot_dataset import LeRobotDatasetError, check_ffmpeg

    spec = demo_spec(cfg)
    try:
        check_ffmpeg()
    except LeRobotDatasetError as exc:
        raise ConfigError(f"data.path={cfg.data.path} does not exist and generating it needs ffmpeg: {exc}") from None
    missing = [task for task in tasks if task not in spec.tasks]
    if missing:
        raise ConfigError(f"eval.tasks: {missing[0]!r} is not among data.generate.tasks ({', '.join(spec.tasks)}), "
                          "so the generated demonstrations would not cover it; evaluate tasks the demonstrations "
                          "cover")


def generate_dataset(cfg: SFTConfig) -> None:
    """MetaWorld scripted-expert demonstrations into ``data.path`` from ``data.generate``, when it
    does not exist."""
    from infinirl.data.demos import collect_demos

    path = Path(cfg.data.path)
    if path.exists():
        return
    spec = demo_spec(cfg)
    print(f"data.path={path} does not exist: generating MetaWorld demonstrations", flush=True)
    print("\n".join(collect_demos("metaworld", spec).lines()), flush=True)


def open_dataset(cfg: SFTConfig):
    """The dataset at ``data.path`` (its metadata and numeric columns; videos are decoded later)."""
    from infinirl.data.lerobot_dataset import LeRobotDatasetError, LeRobotDatasetReader

    try:
        return LeRobotDatasetReader(cfg.data.path)
    except LeRobotDatasetError as exc:
        raise ConfigError(f"data.path: {exc}") from None


def _check_stats(reader) -> None:
    """The state and action statistics the model normalises with: there, and of the features' shapes."""
    from infinirl.data.lerobot_dataset import LeRobotDatasetError

    try:
        stats = reader.stats
    except LeRobotDatasetError as exc:
        raise ConfigError(f"data.path: {exc}") from None
    for key in ("observation.state", "action"):
        if key not in reader.features or key not in stats:
            raise ConfigError(f"data.path: the dataset at {reader.root} has no {key!r} (with statistics in "
                              "meta/stats.json); SFT needs states and actions")
        shape = tuple(reader.features[key]["shape"])
        for name in ("mean", "std"):
            value = stats[key].get(name)
            if value is None or tuple(np.shape(value)) != shape:
                found = "none" if value is None else f"shape {tuple(np.shape(value))}"
                raise ConfigError(f"data.path: {reader.root}/meta/stats.json gives {key}.{name} {found}, but the "
                                  f"feature's shape is {shape}; the statistics are corrupt: re-create the dataset")


def read_demos(reader, camera_key: str | None) -> DemoFrames:
    """Every frame of ``reader`` in memory; a video that does not decode is a ConfigError naming it."""
    from infinirl.data.lerobot_dataset import LeRobotDatasetError

    try:
        return DemoFrames.read(reader, camera_key)
    except LeRobotDatasetError as exc:
        raise ConfigError(f"data.path: {exc}") from None


def task_instructions(tasks: list[str], dataset_tasks: list[str]) -> dict[str, tuple[str, str]]:
    """Each evaluation task -> (the env's instruction, the dataset's wording of it): the dataset
    must hold the task's natural sentence or the env's own name for it."""
    from infinirl.data.demos import METAWORLD_INSTRUCTIONS
    from infinirl.envs.metaworld_env import task_instruction

    if not tasks:
        raise ConfigError("eval.tasks is empty and so is data.generate.tasks: name the MetaWorld tasks to evaluate")
    found = {}
    for task in tasks:
        env_text = task_instruction(task)
        wordings = [w for w in (METAWORLD_INSTRUCTIONS.get(task), env_text) if w in dataset_tasks]
        if not wordings:
            raise ConfigError(f"eval.tasks: {task!r} has no instruction in the dataset (its tasks: {dataset_tasks}); "
                              "evaluate tasks the demonstrations cover")
        found[task] = (env_text, wordings[0])
    return found


def _read_init(cfg: SFTConfig):
    """``model.init``'s :class:`~infinirl.models.vla.config.VLAConfig`, after checking that its
    tensor files' headers read (a truncated or corrupt file fails here, before anything is
    generated); None without ``model.init``."""
    from safetensors import SafetensorError, safe_open

    from infinirl.models.vla.config import read_vla_config

    init = cfg.model.init
    if not init:
        return None
    if not Path(init).is_dir():
        raise ConfigError(f"model.init={init}: no such folder; `infinirl train sft_vla_metaworld` writes one to "
                          "runs/sft_vla_metaworld/policy")
    try:
        config = read_vla_config(init, family=cfg.model.family)
    except (ValueError, FileNotFoundError) as exc:  # json's errors are ValueErrors
        raise ConfigError(f"model.init: {exc}") from None
    if not (Path(init) / "model.safetensors").is_file():
        raise ConfigError(f"model.init={init} has no model.safetensors: copy the whole policy folder")
    for path in sorted(Path(init).glob("*.safetensors")):  # the weights and the processors' statistics
        try:
            with safe_open(str(path), "pt"):
                pass
        except SafetensorError as exc:
            raise ConfigError(f"model.init: {path} is not a readable safetensors file ({exc}); copy it again, or "
                              "train a new model (model.init=null)") from None
    return config


# ---------------------------------------------------------------------------------------------
# Training


def learning_rate(step: int, cfg: SFTConfig) -> float:
    """The learning rate of optimizer step ``step`` (0-based): linear warm-up, then constant or cosine."""
    optim = cfg.optim
    if step < optim.warmup_steps:
        return optim.lr * (step + 1) / optim.warmup_steps
    if optim.lr_schedule == "constant":
        return optim.lr
    span = max(cfg.iterations - optim.warmup_steps - 1, 1)
    progress = min((step - optim.warmup_steps) / span, 1.0)
    floor = optim.lr * optim.min_lr_ratio
    return floor + (optim.lr - floor) * 0.5 * (1 + math.cos(math.pi * progress))


def build_model(cfg: SFTConfig, demos: DemoFrames, instructions: dict[str, str]):
    """The VLA to train: a new ``pi0_smollm2`` (SmolLM2's first layers), or ``model.init``'s."""
    from safetensors import SafetensorError

    from infinirl.models.vla.config import ConvStemSpec
    from infinirl.models.vla.smollm2_vla import SmolVLASpec, build_pi0_smollm2
    from infinirl.models.vla.vla import load_vla

    model = cfg.model
    if model.init:
        try:
            vla = load_vla(model.init, family=model.family)
        except (ValueError, FileNotFoundError, SafetensorError) as exc:
            raise ConfigError(f"model.init: {exc}") from None
        _check_init_fits(vla.config, cfg, int(demos.state.shape[1]), int(demos.action.shape[1]), demos.camera_key)
        vla.config.instructions.update(instructions)
        return vla
    try:
        spec = SmolVLASpec(language_layers=model.language_layers, expert_width=model.expert_width,
                           expert_mlp_dim=model.expert_mlp_dim,
                           vision=ConvStemSpec(channels=tuple(model.vision_channels)), image_size=demos.image_size,
                           chunk_size=model.chunk_size, n_action_steps=model.n_action_steps,
                           num_inference_steps=model.num_inference_steps,
                           tokenizer_max_length=model.tokenizer_max_length)
        stats = demos.normalization_stats(cfg.data.min_std)
        return build_pi0_smollm2(spec, camera_keys=(demos.camera_key,), state_dim=int(demos.state.shape[1]),
                                 action_dim=int(demos.action.shape[1]), stats=stats, instructions=instructions,
                                 smollm2=model.smollm2, seed=cfg.seed)
    except ValueError as exc:
        raise ConfigError(f"model: {exc}") from None


def _check_init_fits(config, cfg: SFTConfig, state_dim: int, action_dim: int, camera_key: str) -> None:
    """``model.init``'s own sizes govern (the model.* sizes are those of a new model): the executed
    part of a chunk and the demonstrations (their state and action sizes, their camera) must fit
    them, or training fails deep in the first step."""
    init, steps = cfg.model.init, cfg.model.n_action_steps
    if steps > config.chunk_size:
        raise ConfigError(f"model.n_action_steps={steps} exceeds the chunk of model.init={init} ({config.chunk_size} "
                          f"actions per decision); set model.n_action_steps <= {config.chunk_size}")
    for key, dataset_dim, model_dim in (("observation.state", state_dim, config.state_dim),
                                        ("action", action_dim, config.action_dim)):
        if dataset_dim != model_dim:
            raise ConfigError(f"data.path: the dataset's {key} has {dataset_dim} dimensions but model.init={init} "
                              f"was trained on {model_dim}; clone from demonstrations of the same robot, or train a "
                              "new model (model.init=null)")
    if camera_key not in config.camera_keys:
        raise ConfigError(f"data.camera_key: the dataset's camera {camera_key!r} is not one model.init={init} "
                          f"reads ({', '.join(config.camera_keys)}); record the demonstrations with that camera")


def trainable_parameters(vla, cfg: SFTConfig) -> list[torch.nn.Parameter]:
    """Freeze what the config keeps fixed; the rest, in a stable order, for the optimizer."""
    vlm = vla.model.vlm
    for parameter in vlm.parameters():
        parameter.requires_grad_(cfg.model.train_language_model)
    vlm.embed_tokens.weight.requires_grad_(cfg.model.train_embeddings)
    return [p for p in vla.model.parameters() if p.requires_grad]


def load_optimizer_state(optimizer: torch.optim.Optimizer, path: str) -> None:
    """The optimizer state saved at ``path``, wherever it was saved from: ``device`` may change on
    resume (a GPU run continued on a CPU-only machine), and the optimizer moves each state tensor to
    its parameter's device as it loads."""
    optimizer.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))


def weights_digest(module: torch.nn.Module) -> str:
    digest = hashlib.sha256()
    for name, tensor in module.state_dict().items():
        digest.update(name.encode())
        digest.update(tensor.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()


# ---------------------------------------------------------------------------------------------
# Evaluation


def rollout_episodes(policy, env, seeds: list[int]) -> dict[str, list]:
    """One episode per seed (rounds of ``env.num_envs``), acting deterministically; the instruction
    travels with the observation."""
    from infinirl.models.policies.base import prepare_obs

    out: dict[str, list] = {"success": [], "return": [], "length": []}
    num_envs = env.num_envs
    for start in range(0, len(seeds), num_envs):
        batch = [int(s) for s in seeds[start:start + num_envs]]
        obs = env.reset(seeds=batch + [batch[-1]] * (num_envs - len(batch)))
        active = np.arange(num_envs) < len(batch)
        while active.any():
            step = policy.act(prepare_obs(obs), deterministic=True)
            result = env.step(step.actions.cpu().numpy(), env_mask=active, autoreset=False)
            for i in np.flatnonzero(result.done & active):
                out["success"].append(bool(result.info["episode_success"][i]))
                out["return"].append(float(result.info["episode_return"][i]))
                out["length"].append(int(result.info["episode_length"][i]))
            active &= ~result.done
            obs = result.obs
    return out


class SFTFlow:
    """The iteration logic (the loop drives it: see :mod:`infinirl.runners.loop`)."""

    def __init__(self, cfg: SFTConfig, demos: DemoFrames, tasks: dict[str, tuple[str, str]]):
        from infinirl.models.policies.base import build_policy
        from infinirl.runners.sft_rft import RejectionSampling

        self.cfg, self.demos, self.tasks = cfg, demos, tasks
        self.base_demos = demos
        self.rft = RejectionSampling(cfg, tasks, demos.camera_key, demos.image_size)
        self.device = compute_device(cfg.device)
        self.vla = build_model(cfg, demos, {env_text: wording for env_text, wording in tasks.values()})
        self.vla.to(self.device)  # before the optimizer exists: its state follows the parameters
        self.vla.train()
        self.parameters = trainable_parameters(self.vla, cfg)
        optim = cfg.optim
        self.optimizer = torch.optim.AdamW(self.parameters, lr=optim.lr, betas=tuple(optim.betas),
                                           weight_decay=optim.weight_decay)
        self.policy = build_policy(cfg.model.family, checkpoint=self.vla, action_dim=self.vla.config.action_dim,
                                   chunk=cfg.model.n_action_steps,
                                   cameras={"rgb": demos.camera_key}, state_key="proprio", value_head=False)
        self.envs: dict[str, object] = {}
        self.samples = 0
        self.spec = LoopSpec(
            name="sft", title=f"SFT {cfg.model.family} on {Path(cfg.data.path).name}", headline="eval/success_rate",
            target=cfg.eval.target,
            progress=(ProgressField(label="loss", key="train/loss", format=".4f"),
                      ProgressField(label="lr", key="train/lr", format=".1e"),
                      ProgressField(label="success", key="eval/success_rate", format=".2f")),
            panels=(Panel(title="flow-matching loss", y=("train/loss",), x="step", x_label="optimizer steps"),
                    Panel(title="held-out success rate", y=("eval/success_rate",), x="step",
                          x_label="optimizer steps"),
                    Panel(title="learning rate", y=("train/lr",), x="step", x_label="optimizer steps"),
                    *((Panel(title="success of the RFT rounds' episodes", y=("rft/success_rate",), x="step",
                             x_label="optimizer steps"),) if self.rft.enabled else ())))

    def start(self, iteration: int) -> None:
        """Nothing to sync: the model lives in this process."""

    def step(self, iteration: int) -> dict:
        rft_metrics = self._rft_round() if self.rft.due(iteration) else {}
        cfg, t0 = self.cfg, time.perf_counter()
        lr = learning_rate(iteration, cfg)
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        indices = torch.randint(len(self.demos), (cfg.optim.batch_size,))
        observation, actions, valid = self.demos.batch(indices, self.vla.config.chunk_size, cfg.data.augment_shift)
        loss = self.vla.loss(observation, actions, action_mask=valid)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(self.parameters, cfg.optim.grad_clip)
        self.optimizer.step()
        self.samples += len(indices)
        seconds = time.perf_counter() - t0
        return {"train/loss": float(loss.detach()), "train/grad_norm": float(grad_norm), "train/lr": lr,
                "train/peak_memory_bytes": peak_memory_bytes(self.device),
                "train/samples": self.samples, "train/frames": len(self.demos), "time/step_s": seconds,
                "time/samples_per_s": len(indices) / max(seconds, 1e-9), **rft_metrics}

    def _rft_round(self) -> dict:
        """Collect a rejection-sampling round with the current weights; its successes join the data."""
        path, metrics = self.rft.collect(self.policy, self.vla)
        if path is not None:
            self.demos = self.demos.extended(self._read_round(path))
        return metrics

    def _read_round(self, path: Path) -> DemoFrames:
        from infinirl.data.lerobot_dataset import LeRobotDatasetError, LeRobotDatasetReader

        try:
            return DemoFrames.read(LeRobotDatasetReader(path), self.demos.camera_key)
        except LeRobotDatasetError as exc:
            raise ConfigError(f"rft: the round {path} does not read ({exc}); restore it, or start the run again in a "
                              "new output_dir") from None

    # ------------------------------------------------------------------ evaluation
    def _env(self, task: str):
        from infinirl.envs.registry import make_env

        if task not in self.envs:
            cfg = self.cfg.eval
            self.envs[task] = make_env(f"metaworld:{task}", min(cfg.num_envs, cfg.episodes_per_task), seed=cfg.seed,
                                       num_workers=0, chunk_size=self.cfg.model.n_action_steps,
                                       max_episode_steps=cfg.max_episode_steps, obs_mode="state+rgb",
                                       camera=self.demos.camera_key[len(CAMERA_PREFIX):],
                                       image_size=self.demos.image_size, terminate_on_success=True)
        return self.envs[task]

    def evaluate(self) -> dict:
        cfg = self.cfg.eval
        seeds = eval_seeds(cfg.seed, cfg.episodes_per_task)
        metrics: dict[str, float] = {}
        episodes: dict[str, list] = {"success": [], "return": [], "length": []}
        self.vla.eval()
        try:
            with torch.random.fork_rng(), torch.no_grad():
                torch.manual_seed(cfg.seed)  # the same initial noise at every evaluation
                for task in self.tasks:
                    result = rollout_episodes(self.policy, self._env(task), seeds)
                    metrics[f"eval/success/{task}"] = float(np.mean(result["success"]))
                    for key, values in result.items():
                        episodes[key] += values
        finally:
            self.vla.train()
        return {"eval/success_rate": float(np.mean(episodes["success"])),
                "eval/return_mean": float(np.mean(episodes["return"])),
                "eval/episode_length_mean": float(np.mean(episodes["length"])), **metrics}

    # ------------------------------------------------------------------ checkpoints
    def save(self, folder: str) -> dict:
        from infinirl.models.vla.save import write_vla_files

        policy = Path(folder) / POLICY_DIR
        policy.mkdir()
        write_vla_files(self.vla, policy)  # inside the checkpoint's temporary folder: renamed whole
        torch_save_atomic(self.optimizer.state_dict(), os.path.join(folder, OPTIMIZER_FILE))
        return {"samples": self.samples, "rft_kept": list(self.rft.kept)}

    def load(self, folder: str, state: dict) -> None:
        from infinirl.models.vla.checkpoint import load_weights
        from infinirl.models.vla.vla import load_processor_stats

        load_weights(self.vla.model, Path(folder) / POLICY_DIR / "model.safetensors")
        # The statistics the checkpoint normalised with (the model was built with those of data.path
        # or model.init as they are now; the run's inputs check refuses those when they changed).
        load_processor_stats(self.vla, Path(folder) / POLICY_DIR)
        load_optimizer_state(self.optimizer, os.path.join(folder, OPTIMIZER_FILE))
        self.samples = int(state["samples"])
        self.rft.kept = [int(k) for k in state.get("rft_kept", [])]
        self.demos = self.base_demos
        for path in self.rft.saved_rounds():
            self.demos = self.demos.extended(self._read_round(path))

    # ------------------------------------------------------------------ the end
    def finish(self, output_dir: str) -> dict:
        from infinirl.models.vla.save import save_vla

        path = save_vla(self.vla, Path(output_dir) / POLICY_DIR)
        return {"policy": str(path), "samples": self.samples, "weights_sha256": weights_digest(self.vla.model)}

    def close(self) -> None:
        for env in self.envs.values():
            env.close()
        self.envs = {}
        self.rft.close()
