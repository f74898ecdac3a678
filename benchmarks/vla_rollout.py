"""Benchmark: π0 action chunks per second, InfiniRL's VLA against LeRobot's, same checkpoint and batch.

Each side loads the same π0 checkpoint folder (LeRobot's published layout) and turns the same raw
observations (images at the checkpoint's resolution in [0, 1], state, instruction) and the same
initial noise into env-unit action chunks, ``--repeats`` times after ``--warmup`` untimed calls:

* ``ours``: ``infinirl.models.vla.load_vla(...).predict_action_chunk(obs, noise=noise)`` (processor,
  the prefix encoded once and its keys/values reused by every denoising step, unnormalisation);
* ``reference``: LeRobot 0.4.4's ``PI0Policy.from_pretrained`` with the folder's processor
  pipelines, ``postprocessor(policy.predict_action_chunk(preprocessor(batch), noise=noise))``.

Each runs in its own subprocess (neither sees the other's threads or memory) with the same torch
thread count (``--threads``, default: every core). The two start at once and take turns call by
call (benchmarks/_bench_turns.py: the waiting side is stopped), so a slow spell of a shared machine
lands on both alike and neither computes while the other does. Reported per side: the median
seconds per call and ``chunks_per_s`` = batch size / median. Both sides' actions for the shared noise are compared
(``max_abs_diff``), so the two did the same work: actions that differ, or a side that fails, are
listed in the last line's "failures" and the script exits 1.

LeRobot is not a dependency of the project (docs/vla.md, "The LeRobot decision"): it lives in its
own virtualenv (recipe in tests/fixtures/vla/make_fixtures.py), found through
``--reference-python`` or ``$INFINIRL_LEROBOT_PYTHON``. Without one, only our row is reported.

Checkpoints (``--size``): ``tiny`` is the test fixture (tests/fixtures/vla/pi0: Gemma widths 32/16,
32x32 images, 4 steps), too small to time anything but overhead; ``small`` (default) is a random
π0 of a few more, wider layers at 224x224 with π0's chunk of 50 and 10 denoising steps, written by
LeRobot itself through make_fixtures.py's code path (so in the published layout); without LeRobot
our own ``save_vla`` writes it for our row alone.

    python benchmarks/vla_rollout.py --reference-python /tmp/lerobot-venv/bin/python
    INFINIRL_LEROBOT_PYTHON=/tmp/lerobot-venv/bin/python python benchmarks/vla_rollout.py --size tiny
    python benchmarks/vla_rollout.py --batch-size 8 --repeats 20 --record docs/results.md

Last stdout line: {"benchmark": "vla_rollout", "ratios": {"vla_act_vs_reference": ours chunks/s /
reference chunks/s}, "targets": {"vla_act_vs_reference": 1.0}, "device": ..., "results": {...}}.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

from _bench_common import add_record_argument, conclude, concluded, device_description, failures_of, side_failed
from _bench_turns import Conductor, RowFailed, Turn

REPO = Path(__file__).resolve().parents[1]
FIXTURES = REPO / "tests" / "fixtures" / "vla"
TARGETS = {"vla_act_vs_reference": 1.0}

#: π0 checkpoints of other sizes in make_fixtures.py's terms: its module constants to replace.
#: Gemma keeps 8 heads (LeRobot's joint attention hard-codes them); widths keep π0's VLM:expert ratio of 2.
SIZES: dict[str, dict | None] = {
    "tiny": None,  # the committed fixture as it is
    "small": {
        "VLM": dict(width=256, depth=4, mlp_dim=1024, num_heads=8, num_kv_heads=1, head_dim=32),
        "EXPERT": dict(width=128, depth=4, mlp_dim=512, num_heads=8, num_kv_heads=1, head_dim=32),
        "VISION": dict(hidden_size=192, intermediate_size=768, num_hidden_layers=2, num_attention_heads=4,
                       patch_size=14),
        "IMAGE_SIZE": 224,
        "COMMON": dict(chunk_size=50, n_action_steps=50, max_state_dim=32, max_action_dim=32,
                       num_inference_steps=10),
    },
}
SEED = 0
#: relative to the actions' largest magnitude: float32 reassociation between the implementations
SAME_ACTIONS_RTOL = 1e-4


# --- pure helpers (unit-tested) ----------------------------------------------------------------

def timing_summary(seconds: Sequence[float], batch_size: int) -> dict:
    """Timed calls -> {median_s, chunks_per_s (batch size / median), min_s, max_s, repeats}."""
    if not seconds:
        raise ValueError("timing_summary needs at least one timed call")
    median = statistics.median(seconds)
    return {"median_s": round(median, 6), "chunks_per_s": round(batch_size / median, 4) if median > 0 else None,
            "min_s": round(min(seconds), 6), "max_s": round(max(seconds), 6), "repeats": len(seconds)}


def act_ratio(ours: Mapping | None, reference: Mapping | None) -> float | None:
    """Ours chunks/s / the reference's; None unless both rows have a rate."""
    mine = (ours or {}).get("chunks_per_s")
    theirs = (reference or {}).get("chunks_per_s")
    return round(mine / theirs, 3) if mine and theirs else None


def action_agreement(max_abs_diff: float | None, scale: float | None, rtol: float = SAME_ACTIONS_RTOL) -> dict:
    """{max_abs_diff, actions_scale, same_actions}: the two agree within ``rtol`` of max(scale, 1)."""
    if max_abs_diff is None:
        return {"max_abs_diff": None, "actions_scale": scale, "same_actions": None}
    return {"max_abs_diff": max_abs_diff, "actions_scale": scale,
            "same_actions": bool(max_abs_diff <= rtol * max(scale or 0.0, 1.0))}


def final_line(results: Mapping[str, Mapping], device: str, settings: Mapping) -> dict:
    """The benchmark's last stdout line."""
    return {"benchmark": "vla_rollout",
            "ratios": {"vla_act_vs_reference": act_ratio(results.get("ours"), results.get("reference"))},
            "targets": dict(TARGETS), "device": device, "settings": dict(settings), "results": dict(results)}


def run_failures(results: Mapping[str, Mapping]) -> list[str]:
    """What makes the run void: a side that failed, or actions that differ (not the same work)."""
    failures = failures_of({side: results.get(side) or {} for side in ("ours", "reference")})
    if (results.get("actions") or {}).get("same_actions") is False:
        failures.append(f"same work: the two sides' actions differ ({dict(results['actions'])})")
    return failures


def resolve_reference_python(flag: str | None, environ: Mapping[str, str]) -> tuple[str | None, str]:
    """The reference interpreter (``--reference-python``, else ``$INFINIRL_LEROBOT_PYTHON``) and why
    there is none: a missing file is named, so a typo is not mistaken for "LeRobot not installed"."""
    python = flag or environ.get("INFINIRL_LEROBOT_PYTHON")
    if not python:
        return None, ("no LeRobot interpreter given (--reference-python or $INFINIRL_LEROBOT_PYTHON): "
                      "reporting our row only")
    if not Path(python).is_file():
        source = "--reference-python" if flag else "$INFINIRL_LEROBOT_PYTHON"
        return None, f"{source}={python} does not exist: reporting our row only"
    return python, ""


# --- the checkpoint and the shared inputs -------------------------------------------------------

def make_checkpoint_with_lerobot(size: str, out: Path) -> None:
    """(Reference venv) make_fixtures.py's π0 at ``SIZES[size]``, plus its tokenizer and architecture.json."""
    sys.path.insert(0, str(FIXTURES))
    import make_fixtures  # noqa: PLC0415 - the reference venv's LeRobot, through the fixtures' own script

    spec = SIZES[size]
    for name in ("VLM", "EXPERT", "VISION", "IMAGE_SIZE"):
        setattr(make_fixtures, name, spec[name])
    image = spec["IMAGE_SIZE"]
    make_fixtures.COMMON = {**make_fixtures.COMMON, **spec["COMMON"], "image_resolution": (image, image)}
    tokenizer = make_fixtures.build_tokenizer()
    make_fixtures.make("pi0", out, tokenizer, seed=SEED)
    tokenizer.save_pretrained(out / "tokenizer")
    sizes = {"vlm": spec["VLM"], "expert": spec["EXPERT"], "vision": spec["VISION"],
             "vocab_size": make_fixtures.vocab_size(tokenizer)}
    (out / "architecture.json").write_text(json.dumps(sizes, indent=2) + "\n")


def make_checkpoint_ours(size: str, out: Path) -> None:
    """(Our interpreter) the same sizes, randomly initialised and written by ``save_vla`` (ours only)."""
    import torch

    from infinirl.models.vla import VLAArchitecture, VLAConfig, save_vla
    from infinirl.models.vla.smollm2_vla import build_vla

    spec = SIZES[size]
    fixture = json.loads((FIXTURES / "pi0" / "config.json").read_text())
    architecture = VLAArchitecture.from_dict({"vlm": spec["VLM"], "expert": spec["EXPERT"], "vision": spec["VISION"],
                                              "vocab_size": json.loads((FIXTURES / "architecture.json").read_text())
                                              ["vocab_size"]})
    cameras = tuple(k for k, f in fixture["input_features"].items() if f["type"] == "VISUAL")
    state_dim = fixture["input_features"]["observation.state"]["shape"][0]
    action_dim = fixture["output_features"]["action"]["shape"][0]
    image = spec["IMAGE_SIZE"]
    config = VLAConfig(family="pi0", architecture=architecture, camera_keys=cameras, state_dim=state_dim,
                       action_dim=action_dim, image_resolution=(image, image),
                       tokenizer_max_length=fixture["tokenizer_max_length"], **spec["COMMON"])
    torch.manual_seed(SEED)
    stats = {key: {"mean": torch.zeros(dim), "std": torch.ones(dim)}
             for key, dim in (("observation.state", state_dim), ("action", action_dim))}
    save_vla(build_vla(config, stats, FIXTURES / "tokenizer"), out)
    (out / "architecture.json").write_text(json.dumps(architecture.to_dict(), indent=2) + "\n")


def make_inputs(checkpoint: Path, batch_size: int, path: Path) -> None:
    """The raw batch both sides act on: all cameras but the last (LeRobot's missing-camera path), square
    images at the checkpoint's resolution in [0, 1] (so both resize alike), state, noise; tasks beside it."""
    import torch
    from safetensors.torch import save_file

    config = json.loads((checkpoint / "config.json").read_text())
    generator = torch.Generator().manual_seed(SEED)
    cameras = [k for k, f in config["input_features"].items() if f["type"] == "VISUAL"]
    resolution = config["image_resolution"][0]
    tensors = {key: torch.rand(batch_size, 3, resolution, resolution, generator=generator)
               for key in cameras[:max(1, len(cameras) - 1)]}
    state_dim = config["input_features"]["observation.state"]["shape"][0]
    tensors["observation.state"] = torch.randn(batch_size, state_dim, generator=generator)
    tensors["noise"] = torch.randn(batch_size, config["chunk_size"], config["max_action_dim"], generator=generator)
    save_file(tensors, str(path))
    tasks = json.loads((FIXTURES / "pi0" / "inputs.json").read_text())["tasks"]
    path.with_suffix(".json").write_text(json.dumps([tasks[i % len(tasks)] for i in range(batch_size)]))


def read_inputs(path: Path) -> tuple[dict, object]:
    from safetensors.torch import load_file

    tensors = load_file(str(path))
    noise = tensors.pop("noise")
    tensors["task"] = json.loads(path.with_suffix(".json").read_text())
    return tensors, noise


# --- one side, in its own process ---------------------------------------------------------------

def time_calls(act, warmup: int, repeats: int, turn: Turn | None = None) -> tuple[list[float], object]:
    """Seconds of each timed call, and the last call's actions; with a ``turn``, every call (warm-up
    too) in a turn of its own, so the other side's calls never run at the same time."""
    seconds, actions = [], None
    for i in range(warmup + repeats):
        with turn or contextlib.nullcontext():
            start = time.perf_counter()
            actions = act()
            elapsed = time.perf_counter() - start
        if i >= warmup:
            seconds.append(elapsed)
    return seconds, actions


def ours_act(checkpoint: Path, inputs: Path):
    from infinirl.models.vla import VLAArchitecture, load_vla

    vla = load_vla(checkpoint, family="pi0", architecture=VLAArchitecture.from_json(checkpoint / "architecture.json"),
                   tokenizer=checkpoint / "tokenizer")
    observation, noise = read_inputs(inputs)
    return lambda: vla.predict_action_chunk(observation, noise=noise)


def reference_act(checkpoint: Path, inputs: Path):
    sys.path.insert(0, str(FIXTURES))
    import lerobot.policies.pi0.modeling_pi0 as modeling_pi0
    import make_fixtures  # noqa: PLC0415 - its patch builds LeRobot's π0 at the checkpoint's sizes
    from lerobot.processor import PolicyProcessorPipeline
    from lerobot.processor.converters import (
        batch_to_transition,
        policy_action_to_transition,
        transition_to_batch,
        transition_to_policy_action,
    )
    from transformers import PreTrainedTokenizerFast

    sizes = json.loads((checkpoint / "architecture.json").read_text())
    make_fixtures.VLM, make_fixtures.EXPERT = sizes["vlm"], sizes["expert"]
    make_fixtures.VISION = {k: v for k, v in sizes["vision"].items() if k != "kind"}
    for spec in (make_fixtures.VLM, make_fixtures.EXPERT):
        spec.pop("kind", None)
    make_fixtures.patch_reference(modeling_pi0, sizes["vocab_size"])
    policy = modeling_pi0.PI0Policy.from_pretrained(str(checkpoint))
    policy.eval()
    tokenizer = PreTrainedTokenizerFast.from_pretrained(str(checkpoint / "tokenizer"))
    # what lerobot.policies.factory.make_pre_post_processors does for a pretrained path (that module
    # imports gymnasium, which LeRobot's pi extra does not install)
    preprocessor = PolicyProcessorPipeline.from_pretrained(
        str(checkpoint), config_filename="policy_preprocessor.json", to_transition=batch_to_transition,
        to_output=transition_to_batch, overrides={"tokenizer_processor": {"tokenizer": tokenizer}})
    postprocessor = PolicyProcessorPipeline.from_pretrained(
        str(checkpoint), config_filename="policy_postprocessor.json", to_transition=policy_action_to_transition,
        to_output=transition_to_policy_action)
    observation, noise = read_inputs(inputs)

    def act():
        batch = preprocessor(dict(observation))
        return postprocessor(policy.predict_action_chunk(batch, noise=noise.clone()))
    return act


SIDES = {"ours": ours_act, "reference": reference_act}


def run_side(side: str, checkpoint: Path, inputs: Path, actions_out: Path, threads: int, warmup: int,
             repeats: int) -> dict:
    import torch
    from safetensors.torch import save_file

    torch.set_num_threads(threads)
    turn = Turn.from_env()
    with torch.no_grad():
        act = SIDES[side](checkpoint, inputs)
        seconds, actions = time_calls(act, warmup, repeats, turn)
    if turn is not None:
        turn.take()  # the last turn: what follows the timed calls
    save_file({"actions": actions.detach().float().contiguous()}, str(actions_out))
    batch_size = int(actions.shape[0])
    return {**timing_summary(seconds, batch_size), "seconds": [round(s, 6) for s in seconds],
            "torch": torch.__version__, "threads": torch.get_num_threads(), "actions_shape": list(actions.shape)}


# --- the driver ---------------------------------------------------------------------------------

def child_env(python: str, threads: int) -> dict[str, str]:
    """Our interpreter also finds the repository's package; the reference's sees the repository only
    through this script's own folder and the fixtures (an empty PYTHONPATH adds nothing)."""
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    ours = python == sys.executable
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])) if ours else ""
    return env


def child(python: str, args: list[str], threads: int) -> subprocess.CompletedProcess:
    """This script under ``python``, alone."""
    return subprocess.run([python, __file__, *args], capture_output=True, text=True, env=child_env(python, threads))


def result_of(stdout: str) -> dict:
    lines = [line for line in stdout.splitlines() if line.startswith("RESULT ")]
    if not lines:
        return side_failed(f"no RESULT line in its output: {stdout.strip()[-1500:]}")
    return json.loads(lines[-1][len("RESULT "):])


def run_sides_in_turns(pythons: Mapping[str, str], work: Path, common: list[str], args) -> dict[str, dict]:
    """Both sides start at once and take turns call by call (``_bench_turns.Conductor``): the i-th
    call of each runs within one call of the other's, so a slow spell of a shared machine lands on
    both alike, and never while the other computes."""
    commands = {side: [python, __file__, "--only", side, "--actions-out", str(work / f"{side}_actions.safetensors"),
                       *common] for side, python in pythons.items()}
    row_env = {side: {"PYTHONPATH": child_env(python, args.threads)["PYTHONPATH"]} for side, python in pythons.items()}
    base = {**os.environ, "OMP_NUM_THREADS": str(args.threads), "MKL_NUM_THREADS": str(args.threads)}
    try:
        outputs = Conductor(commands, env=base, row_env=row_env).run(args.warmup + args.repeats)
    except RowFailed as error:  # the conductor stopped every side: the failing one named, the others stopped
        return {side: {**side_failed(str(error) if side == error.row else f"stopped: the {error.row} side failed"),
                       "python": python} for side, python in pythons.items()}
    return {side: {**result_of(outputs[side]), "python": pythons[side]} for side in pythons}


def prepare_checkpoint(size: str, work: Path, reference: str | None, threads: int) -> tuple[Path, str]:
    if SIZES[size] is None:
        folder = work / "pi0"
        import shutil

        shutil.copytree(FIXTURES / "pi0", folder)
        shutil.copytree(FIXTURES / "tokenizer", folder / "tokenizer")
        shutil.copy(FIXTURES / "architecture.json", folder / "architecture.json")
        return folder, "tests/fixtures/vla/pi0 (LeRobot)"
    folder = work / f"pi0_{size}"
    if reference:
        proc = child(reference, ["--make-checkpoint", str(folder), "--size", size], threads)
        if proc.returncode:
            raise RuntimeError(f"LeRobot ({reference}) could not write the {size} checkpoint: "
                               f"{proc.stderr.strip()[-1500:]}")
        return folder, f"{size}, written by LeRobot"
    make_checkpoint_ours(size, folder)
    return folder, f"{size}, written by save_vla"


def compare_actions(work: Path) -> dict:
    from safetensors.torch import load_file

    ours, theirs = (work / "ours_actions.safetensors", work / "reference_actions.safetensors")
    if not (ours.is_file() and theirs.is_file()):
        return action_agreement(None, None)
    a, b = load_file(str(ours))["actions"], load_file(str(theirs))["actions"]
    if a.shape != b.shape:
        return {**action_agreement(None, None), "same_actions": False,
                "shape_mismatch": [list(a.shape), list(b.shape)]}
    return action_agreement(float((a - b).abs().max()), float(b.abs().max()))


def drive(args) -> dict:
    reference, why = resolve_reference_python(args.reference_python, os.environ)
    if why:
        print(why, file=sys.stderr, flush=True)
    with tempfile.TemporaryDirectory(prefix="bench-vla-") as tmp:
        work = Path(tmp)
        checkpoint, made_by = prepare_checkpoint(args.size, work, reference, args.threads)
        inputs = work / "inputs.safetensors"
        make_inputs(checkpoint, args.batch_size, inputs)
        common = ["--checkpoint", str(checkpoint), "--inputs", str(inputs), "--threads", str(args.threads),
                  "--warmup", str(args.warmup), "--repeats", str(args.repeats)]
        pythons = {"ours": sys.executable, **({"reference": reference} if reference else {})}
        results = run_sides_in_turns(pythons, work, common, args)
        results.setdefault("reference", {"skipped": why})
        for side in ("ours", "reference"):
            print(f"[{side}] {json.dumps(results[side])[:400]}", file=sys.stderr, flush=True)
        results["actions"] = compare_actions(work)
        config = json.loads((checkpoint / "config.json").read_text())
    settings = {"size": args.size, "checkpoint": made_by, "batch_size": args.batch_size,
                "image_size": config["image_resolution"][0], "chunk_size": config["chunk_size"],
                "num_inference_steps": config["num_inference_steps"], "threads": args.threads,
                "warmup": args.warmup, "repeats": args.repeats}
    return final_line(results, device_description(), settings)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference-python", default=None,
                        help="interpreter of a venv with LeRobot 0.4.4 (default: $INFINIRL_LEROBOT_PYTHON)")
    parser.add_argument("--size", choices=sorted(SIZES), default="small")
    parser.add_argument("--batch-size", type=int, default=4)
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1,
                        help="torch threads of each side (on a host whose cores other jobs keep busy, 1: a "
                             "parallel region waits for its slowest thread, and a descheduled one stalls it)")
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--only", choices=sorted(SIDES), help=argparse.SUPPRESS)
    parser.add_argument("--make-checkpoint", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--checkpoint", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--inputs", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--actions-out", type=Path, help=argparse.SUPPRESS)
    add_record_argument(parser)
    args = parser.parse_args()
    if min(args.batch_size, args.threads, args.repeats) < 1 or args.warmup < 0:
        parser.error("--batch-size, --threads and --repeats must be >= 1, --warmup >= 0")
    if args.make_checkpoint:
        make_checkpoint_with_lerobot(args.size, args.make_checkpoint)
        return 0
    if args.only:
        result = run_side(args.only, args.checkpoint, args.inputs, args.actions_out, args.threads, args.warmup,
                          args.repeats)
        print("RESULT " + json.dumps(result), flush=True)
        return 0
    final = drive(args)
    return conclude(final, run_failures(final["results"]),
                    record=(args.record, "π0 action chunks per second against LeRobot"))


if __name__ == "__main__":
    sys.exit(concluded("vla_rollout", main))
