"""The embodied PPO update (``ppo_update``) is split-invariant: two data-parallel ranks, each
training on its share of every mini-batch and summing gradients, end with the weights one rank
gets alone. Also: normalising a batch once gives what normalising every mini-batch gives, and the
compiled update (``actor.compile``) trains like the eager one."""

import copy
import dataclasses
import math
import threading
import warnings

import pytest
import torch

pytest.importorskip("gymnasium")

from infinirl.components.embodied_actor import PPOSpec, ppo_update  # noqa: E402
from infinirl.components.embodied_rollout import PolicySpec  # noqa: E402
from infinirl.components.env_worker import probe_env_specs  # noqa: E402
from infinirl.runners.embodied_config import find_cxx_compiler  # noqa: E402

B = 48


def policy_and_batch():
    observation_spec, action_space = probe_env_specs("gym:Pendulum-v1", {})
    spec = PolicySpec(name="mlp_gaussian", options={"hidden": [16, 16]})
    gen = torch.Generator().manual_seed(1)
    obs = {"state": 3.0 + 2.0 * torch.randn(B, 3, generator=gen)}  # far from N(0, 1): normalising matters

    def build():
        torch.manual_seed(0)
        model = spec.build(observation_spec, action_space)
        model.update_obs_stats({"state": obs["state"][:20]})  # statistics the rollout would have used
        return model

    model = build()
    with torch.no_grad():
        step = model.act(obs)
    batch = {"obs": obs, "actions": step.actions, "logprobs": step.logprobs,
             "step_mask": torch.ones(B, 1, dtype=torch.bool), "values": step.values,
             "advantages": torch.randn(B, generator=gen), "returns": torch.randn(B, generator=gen)}
    return build, batch


PPO = PPOSpec(lr=1e-2, epochs=3, mini_batches=4, entropy_coef=0.01, value_clip=0.2, total_iterations=2)


def flat(model) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in model.parameters()])


def test_two_ranks_end_with_the_weights_of_one():
    build, batch = policy_and_batch()
    single = build()
    single_metrics = ppo_update(single, torch.optim.Adam(single.parameters(), lr=PPO.lr), batch, 0, PPO)

    models, _ = run_two_ranks(build, batch, PPO)
    torch.testing.assert_close(flat(models[0]), flat(single), rtol=0, atol=1e-6)
    torch.testing.assert_close(flat(models[1]), flat(single), rtol=0, atol=1e-6)
    assert not torch.equal(flat(single), flat(build()))  # the update moved the weights
    assert single_metrics["train/optimizer_steps"] == PPO.epochs * PPO.mini_batches
    for key in ("train/policy_loss", "train/value_loss", "train/entropy", "train/approx_kl", "train/grad_norm"):
        assert key in single_metrics and single_metrics[key] == single_metrics[key]  # present, not NaN


def test_a_batch_normalised_once_scores_like_raw_observations():
    build, batch = policy_and_batch()
    model = build()
    raw = model(batch["obs"], batch["actions"], None, True)
    once = model(model.normalize(batch["obs"]), batch["actions"], None, True, True)
    for a, b in zip(raw, once):
        assert torch.equal(a, b)


def grpo_like(batch):
    """Embodied GRPO's shape of batch: no critic, and an estimator mask that drops some decisions."""
    gen = torch.Generator().manual_seed(2)
    masked = dict(batch, advantage_mask=torch.rand(B, generator=gen) > 0.3)
    return masked, dataclasses.replace(PPO, critic=False, normalize_advantages=False)


@pytest.mark.skipif(find_cxx_compiler() is None,
                    reason="torch.compile on CPU needs a C++ compiler (g++/clang++), none on PATH")
@pytest.mark.parametrize("variant", ["ppo", "grpo"])
def test_the_compiled_update_trains_like_the_eager_one(variant):
    build, batch = policy_and_batch()
    ppo = PPO
    if variant == "grpo":
        batch, ppo = grpo_like(batch)
    from torch._dynamo.utils import counters

    results = {}
    for compiled in (False, True):
        model = build()
        spec = dataclasses.replace(ppo, compile=compiled)
        counters.clear()
        optimizer = torch.optim.Adam(model.parameters(), lr=spec.lr)
        eager_steps = []
        optimizer.register_step_post_hook(lambda *_, steps=eager_steps: steps.append(1))
        metrics = ppo_update(model, optimizer, batch, 0, spec)
        results[compiled] = flat(model), metrics
        # compiled: dynamo captured the whole step as one graph, with no graph break, and the eager
        # optimizer step never ran (Adam is inside the graph, on the optimizer's own state)
        assert bool(counters["stats"]["unique_graphs"]) == compiled and not counters["graph_break"]
        assert len(eager_steps) == (0 if compiled else spec.epochs * spec.mini_batches)
        assert float(optimizer.state[next(model.parameters())]["step"]) == spec.epochs * spec.mini_batches
    (eager, eager_metrics), (fused, fused_metrics) = results[False], results[True]
    assert not torch.equal(eager, flat(build()))  # the update moved the weights
    # Fused kernels round differently (float32): equal to float32 precision over 12 Adam steps.
    torch.testing.assert_close(fused, eager, rtol=0, atol=1e-5)
    # the eager step also splits the gradient norm into the critic's and the policy's
    parts = {"train/grad_norm_critic", "train/grad_norm_policy"}
    assert eager_metrics.keys() - parts == fused_metrics.keys()
    assert (parts <= eager_metrics.keys()) == (variant == "ppo")
    assert ("train/value_loss" in eager_metrics) == (variant == "ppo")
    for key, value in fused_metrics.items():
        assert value == pytest.approx(eager_metrics[key], rel=1e-4, abs=1e-6), key


def run_two_ranks(build, batch, ppo):
    """``ppo_update`` on two ranks (threads) summing gradients as gloo/NCCL ``all_reduce(SUM)``."""
    models = [build(), build()]
    optimizers = [torch.optim.Adam(m.parameters(), lr=ppo.lr) for m in models]
    barrier = threading.Barrier(2)
    grads: list = [None, None]
    results: list = [None, None]
    errors: list = []

    def all_reduce(rank):
        grads[rank] = [p.grad.clone() for p in models[rank].parameters()]
        barrier.wait()
        for p, mine, other in zip(models[rank].parameters(), grads[rank], grads[1 - rank]):
            p.grad.copy_(mine + other)
        barrier.wait()

    def train(rank):
        try:
            results[rank] = ppo_update(models[rank], optimizers[rank], batch, 0, ppo, rank, 2,
                                       lambda: all_reduce(rank))
        except BaseException as exc:  # surfaced below, not lost in the thread
            errors.append(exc)
            barrier.abort()

    threads = [threading.Thread(target=train, args=(r,)) for r in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(300)
    if errors:
        raise errors[0]
    assert results[0] is not None and results[1] is not None
    return models, results


@pytest.mark.slow  # default-suite budget: compiles two ranks; one compiled rank is checked in the default suite
@pytest.mark.skipif(find_cxx_compiler() is None,
                    reason="torch.compile on CPU needs a C++ compiler (g++/clang++), none on PATH")
def test_two_compiled_ranks_end_with_the_weights_of_one_eager_rank():
    """With two ranks the compiled step splits around the all-reduce (gradients, then clip + Adam)."""
    build, batch = policy_and_batch()
    single = build()
    ppo_update(single, torch.optim.Adam(single.parameters(), lr=PPO.lr), batch, 0, PPO)
    models, _ = run_two_ranks(build, batch, dataclasses.replace(PPO, compile=True))
    for model in models:
        torch.testing.assert_close(flat(model), flat(single), rtol=0, atol=1e-5)


@pytest.mark.parametrize("compiled", [False, pytest.param(True, marks=pytest.mark.slow)])  # compiled: budget
def test_an_fsdp2_model_trains_like_the_plain_one(compiled):
    """strategy=fsdp (FSDP2 ``fully_shard``, SUM reduction, one gloo rank here): the same weights as
    the plain model, eager and with actor.compile (which compiles only the loss under FSDP2), and
    no FSDP2 warning about returned views (``engines.sharding`` copies them)."""
    if compiled and find_cxx_compiler() is None:
        pytest.skip("torch.compile on CPU needs a C++ compiler (g++/clang++), none on PATH")
    from infinirl.engines.distributed import init_distributed
    from infinirl.engines.parallel import DATA_PARALLEL

    init_distributed()
    build, batch = policy_and_batch()
    plain = build()
    ppo_update(plain, torch.optim.Adam(plain.parameters(), lr=PPO.lr), batch, 0, PPO)
    sharded = DATA_PARALLEL.get("fsdp")().wrap(build())
    spec = dataclasses.replace(PPO, strategy="fsdp", compile=compiled)
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*returned a view tensor")
        metrics = ppo_update(sharded, torch.optim.Adam(sharded.parameters(), lr=PPO.lr), batch, 0, spec)
    weights = torch.cat([p.full_tensor().detach().reshape(-1) for p in sharded.parameters()])
    torch.testing.assert_close(weights, flat(plain), rtol=0, atol=1e-5)
    assert metrics["train/grad_norm"] == metrics["train/grad_norm"]


@pytest.mark.parametrize("anneal_iterations, expected_horizon", [(0, 150), (600, 600)])
def test_the_learning_rate_decays_over_the_configured_horizon(anneal_iterations, expected_horizon):
    """``actor.anneal_iterations`` sets the linear decay's horizon (0: ``iterations``), so a run
    stopped early (a shortened demo, a test) keeps the longer run's learning rates."""
    from infinirl.config import compose, to_dataclass
    from infinirl.runners.embodied import ppo_spec
    from infinirl.runners.embodied_config import EmbodiedConfig

    raw = compose("ppo_metaworld_push")
    raw["iterations"] = 150
    raw["actor"]["anneal_iterations"] = anneal_iterations
    spec = ppo_spec(to_dataclass(EmbodiedConfig, raw))
    assert spec.total_iterations == expected_horizon

    build, batch = policy_and_batch()
    model = build()
    optimizer = torch.optim.Adam(model.parameters(), lr=spec.lr)
    ppo = dataclasses.replace(PPO, lr=spec.lr, total_iterations=spec.total_iterations)
    for iteration in (0, 75, 149):
        ppo_update(model, optimizer, batch, iteration, ppo)
        assert optimizer.param_groups[0]["lr"] == pytest.approx(3e-4 * (1 - iteration / expected_horizon), rel=1e-12)


@pytest.mark.parametrize("horizon, message", [(-1, "actor.anneal_iterations=-1 must be >= 0"),
                                              (100, "actor.anneal_iterations=100 < iterations=150")])
def test_a_bad_anneal_horizon_is_refused_before_anything_starts(horizon, message):
    from infinirl.config import ConfigError, compose, to_dataclass
    from infinirl.runners.embodied_config import EmbodiedConfig

    raw = compose("ppo_metaworld_push")
    raw["iterations"] = 150
    raw["actor"]["anneal_iterations"] = horizon
    with pytest.raises(ConfigError, match=message):
        to_dataclass(EmbodiedConfig, raw).validate()


def test_value_lr_trains_the_critic_at_its_own_rate_and_anneals_each_group_from_its_own():
    """``actor.value_lr``: the critic's parameters (the policy's ``critic_modules``) in a group of
    their own; the linear decay scales each group's own base rate. Without it, one group as before."""
    from infinirl.components.embodied_policy import critic_lr_of
    from infinirl.engines.parallel import DATA_PARALLEL

    build, batch = policy_and_batch()
    model = build()
    optimizer = DATA_PARALLEL.get("ddp")(0, 1).build_optimizer(model, 1e-3, 1e-5, critic_lr_of(model, 1e-3, 1e-2))
    rates = {group["lr"]: {id(p) for p in group["params"]} for group in optimizer.param_groups}
    critic = {id(p) for name, p in model.named_parameters() if ".critic." in f".{name}."}
    assert set(rates) == {1e-3, 1e-2} and rates[1e-2] == critic and critic
    ppo = dataclasses.replace(PPO, lr=1e-3, value_lr=1e-2, total_iterations=4)
    ppo_update(model, optimizer, batch, 1, ppo)
    assert sorted(group["lr"] for group in optimizer.param_groups) == pytest.approx([1e-3 * 0.75, 1e-2 * 0.75])
    single = DATA_PARALLEL.get("ddp")(0, 1).build_optimizer(build(), 1e-3, 1e-5)
    assert len(single.param_groups) == 1 and "base_lr" not in single.param_groups[0]


@pytest.mark.parametrize("change, message", [
    ({"algorithm": {"name": "grpo", "group_size": 2}}, "trains no critic"),
    ({"actor": {"compile": True}}, "actor.compile"),
    ({"policy": {"kwargs": {"value_head": False}}}, "has no critic parameters"),
])
def test_value_lr_is_refused_where_no_critic_trains_at_its_rate(change, message):
    assert_refused_in_one_line({"actor": {"value_lr": 1e-3}}, change, message)


def assert_refused_in_one_line(setting: dict, change: dict, message: str) -> None:
    """``ppo_metaworld_reach`` with ``setting`` and then ``change`` applied (section -> key -> value,
    dicts merged) fails the driver's checks with a one-line ConfigError matching ``message``."""
    from infinirl.config import ConfigError, compose, to_dataclass
    from infinirl.runners.embodied import _check_env_and_policy
    from infinirl.runners.embodied_config import EmbodiedConfig

    raw = compose("ppo_metaworld_reach")
    for values_by_section in (setting, change):
        for section, values in values_by_section.items():
            for key, value in values.items():
                current = raw[section].get(key)
                raw[section][key] = {**current, **value} if isinstance(current, dict) else value
    with pytest.raises(ConfigError, match=message) as error:
        _check_env_and_policy(to_dataclass(EmbodiedConfig, raw))
    assert "\n" not in str(error.value)


def test_the_adaptive_rate_follows_rsl_rls_rule_within_its_bounds():
    """``desired_kl``: above 2x the target the rate shrinks by 1.5, below half of it it grows by 1.5,
    in between it stays; each group keeps its own base rate times the anneal factor times the scale."""
    from infinirl.algorithms.embodied_ppo import KL_SCALE_BOUNDS, _adapt_rates

    a, b = torch.nn.Parameter(torch.zeros(1)), torch.nn.Parameter(torch.zeros(1))
    optimizer = torch.optim.Adam([{"params": [a], "base_lr": 1e-3}, {"params": [b], "base_lr": 1e-2}], lr=1e-3)
    spec = dataclasses.replace(PPO, lr=1e-3, desired_kl=0.01)
    expected = 1.0
    for kl, change in ((0.03, 1 / 1.5), (0.02, 1.0), (0.005, 1.0), (0.004, 1.5), (0.001, 1.5), (0.5, 1 / 1.5)):
        _adapt_rates(optimizer, spec, 0.5, torch.tensor(kl, dtype=torch.float64), world_size=1)
        expected *= change
        rates = [g["lr"] for g in optimizer.param_groups]
        assert rates == pytest.approx([1e-3 * 0.5 * expected, 1e-2 * 0.5 * expected])
        assert all(g["kl_scale"] == pytest.approx(expected) for g in optimizer.param_groups)
    for _ in range(40):
        _adapt_rates(optimizer, spec, 1.0, torch.tensor(0.0), world_size=1)
    assert optimizer.param_groups[0]["kl_scale"] == KL_SCALE_BOUNDS[1]
    for _ in range(40):
        _adapt_rates(optimizer, spec, 1.0, torch.tensor(1.0), world_size=1)
    assert optimizer.param_groups[0]["kl_scale"] == KL_SCALE_BOUNDS[0]


def test_the_adaptive_rate_moves_with_the_kl_and_resumes_exactly():
    """A target far below the update's KL shrinks the rate, one far above grows it; the scale is in
    the optimizer's state dict, so an optimizer restored from it continues bit for bit."""
    build, batch = policy_and_batch()
    scales = {}
    for target in (1e-9, 1e3):
        model = build()
        optimizer = torch.optim.Adam(model.parameters(), lr=PPO.lr)
        spec = dataclasses.replace(PPO, desired_kl=target, total_iterations=4)
        scales[target] = ppo_update(model, optimizer, batch, 0, spec)["train/kl_scale"]
    assert scales[1e-9] < 1.0 < scales[1e3]

    spec = dataclasses.replace(PPO, desired_kl=1e-3, total_iterations=4)
    model = build()
    optimizer = torch.optim.Adam(model.parameters(), lr=PPO.lr)
    ppo_update(model, optimizer, batch, 0, spec)
    saved_model, saved_optimizer = copy.deepcopy(model.state_dict()), copy.deepcopy(optimizer.state_dict())
    ppo_update(model, optimizer, batch, 1, spec)
    resumed = build()
    resumed.load_state_dict(saved_model)
    resumed_optimizer = torch.optim.Adam(resumed.parameters(), lr=PPO.lr)
    resumed_optimizer.load_state_dict(saved_optimizer)
    ppo_update(resumed, resumed_optimizer, batch, 1, spec)
    assert torch.equal(flat(resumed), flat(model))
    assert resumed_optimizer.param_groups[0]["lr"] == optimizer.param_groups[0]["lr"]


@pytest.mark.parametrize("setting", [{"desired_kl": 0.01}, {"warmup_steps": 10}])
def test_per_step_rates_are_refused_with_the_compiled_step(setting):
    """``desired_kl`` and ``warmup_steps`` change the rate at every step; the fused step's is fixed."""
    from infinirl.config import ConfigError, compose, to_dataclass
    from infinirl.runners.embodied_config import EmbodiedConfig

    raw = compose("ppo_metaworld_reach")
    raw["actor"].update(setting, compile=True)
    with pytest.raises(ConfigError, match=f"actor.{next(iter(setting))}") as error:
        to_dataclass(EmbodiedConfig, raw).validate()
    assert "\n" not in str(error.value)


def test_the_gradient_norm_splits_into_the_critics_and_the_rest():
    """``train/grad_norm_critic`` and ``train/grad_norm_policy``: the norms (before clipping) of the
    critic parameters' gradient and of the rest's, which make up ``train/grad_norm``."""
    from infinirl.algorithms.embodied_ppo import critic_parameter_ids

    build, batch = policy_and_batch()
    model = build()
    one_step = dataclasses.replace(PPO, epochs=1, mini_batches=1)
    metrics = ppo_update(model, torch.optim.SGD(model.parameters(), lr=0.0), batch, 0, one_step)
    critic = critic_parameter_ids(model)
    norm = {part: float(torch.cat([p.grad.reshape(-1) for p in model.parameters()
                                   if p.grad is not None and (id(p) in critic) == (part == "critic")]).norm())
            for part in ("critic", "policy")}
    clip = min(1.0, one_step.max_grad_norm / metrics["train/grad_norm"])  # the grads left are the clipped ones
    assert metrics["train/grad_norm_critic"] * clip == pytest.approx(norm["critic"], rel=1e-5)
    assert metrics["train/grad_norm_policy"] * clip == pytest.approx(norm["policy"], rel=1e-5)
    assert math.hypot(metrics["train/grad_norm_critic"], metrics["train/grad_norm_policy"]) == pytest.approx(
        metrics["train/grad_norm"], rel=1e-5)


@pytest.mark.parametrize("value_lr", [None, 1e-2])
def test_critic_warmup_trains_the_critic_alone_and_then_the_policy(value_lr):
    """``critic_warmup=2``: iterations 0 and 1 leave every parameter outside the critic bit for bit
    (and its optimizer state empty), the critic learns as if it were the only trainable part; from
    iteration 2 on the whole policy trains."""
    from infinirl.algorithms.embodied_ppo import critic_parameter_ids
    from infinirl.components.embodied_policy import critic_lr_of
    from infinirl.engines.parallel import DATA_PARALLEL

    build, batch = policy_and_batch()
    ppo = dataclasses.replace(PPO, critic_warmup=2, total_iterations=4, value_lr=value_lr)
    lr_of = None if value_lr is None else critic_lr_of(build(), ppo.lr, value_lr)
    model = build()
    optimizer = DATA_PARALLEL.get("ddp")(0, 1).build_optimizer(model, ppo.lr, ppo.adam_eps, lr_of)
    critic = critic_parameter_ids(model)
    names = {id(p): name for name, p in model.named_parameters()}
    assert critic and all(".critic." in f".{names[i]}." for i in critic)
    before = {name: p.detach().clone() for name, p in model.named_parameters()}
    for iteration in (0, 1):
        metrics = ppo_update(model, optimizer, batch, iteration, ppo)
        assert metrics["train/value_loss"] == metrics["train/value_loss"]
    for name, p in model.named_parameters():
        changed = not torch.equal(p.detach(), before[name])
        assert changed == (id(p) in critic), name
        assert (id(p) in critic) == bool(optimizer.state.get(p)), name

    # the same critic steps as training the critic's parameters alone
    reference = build()
    ref_optimizer = DATA_PARALLEL.get("ddp")(0, 1).build_optimizer(reference, ppo.lr, ppo.adam_eps, lr_of)
    value_only = dataclasses.replace(ppo, critic_warmup=0)
    for p in reference.parameters():
        p.requires_grad_(id(p) in critic_parameter_ids(reference))
    for iteration in (0, 1):
        ppo_update(reference, ref_optimizer, batch, iteration, value_only)
    torch.testing.assert_close(flat(reference), flat(model), rtol=0, atol=1e-6)

    frozen_before = {name: p.detach().clone() for name, p in model.named_parameters() if id(p) not in critic}
    ppo_update(model, optimizer, batch, 2, ppo)
    assert any(not torch.equal(p.detach(), frozen_before[name])
               for name, p in model.named_parameters() if id(p) not in critic)


@pytest.mark.parametrize("change, message", [
    ({"algorithm": {"name": "grpo", "group_size": 2}}, "trains no critic"),
    ({"algorithm": {"critic_warmup": 400}}, "algorithm.critic_warmup=400 >= iterations"),
    ({"policy": {"kwargs": {"value_head": False}}}, "has no critic parameters"),
])
def test_critic_warmup_is_refused_where_it_cannot_warm_a_critic_up(change, message):
    assert_refused_in_one_line({"algorithm": {"critic_warmup": 3}}, change, message)


def rates_at_each_step(optimizer) -> list[list[float]]:
    """Every group's rate as each optimizer step takes it (a step pre-hook records them)."""
    seen: list[list[float]] = []
    optimizer.register_step_pre_hook(lambda opt, args, kwargs: seen.append([g["lr"] for g in opt.param_groups]))
    return seen


@pytest.mark.parametrize("value_lr", [None, 1e-1])
def test_the_warmup_ramps_the_policys_rate_over_its_first_steps_and_resumes_exactly(value_lr):
    """``warmup_steps=5``: the policy's k-th optimizer step (from 1) runs at k / 5 of the annealed
    rate, then at the rate; the count is Adam's, so a restored optimizer continues the ramp bit for
    bit; the critic's warm-up iterations take no ramp step; a value head with a group of its own
    (``value_lr``) is never ramped."""
    from infinirl.components.embodied_policy import critic_lr_of
    from infinirl.engines.parallel import DATA_PARALLEL

    build, batch = policy_and_batch()
    ppo = dataclasses.replace(PPO, epochs=1, mini_batches=3, total_iterations=4, warmup_steps=5, critic_warmup=1,
                              value_lr=value_lr)
    lr_of = None if value_lr is None else critic_lr_of(build(), ppo.lr, value_lr)

    def optimizer_of(model):
        return DATA_PARALLEL.get("ddp")(0, 1).build_optimizer(model, ppo.lr, ppo.adam_eps, lr_of)

    model = build()
    optimizer = optimizer_of(model)
    seen = rates_at_each_step(optimizer)
    for iteration in (0, 1):
        ppo_update(model, optimizer, batch, iteration, ppo)
    saved_model, saved_optimizer = copy.deepcopy(model.state_dict()), copy.deepcopy(optimizer.state_dict())
    ppo_update(model, optimizer, batch, 2, ppo)

    anneal = [1.0] * 3 + [0.75] * 3 + [0.5] * 3
    ramp = [1.0] * 3 + [1 / 5, 2 / 5, 3 / 5, 4 / 5, 1.0, 1.0]  # iteration 0 is the critic's warm-up
    policy_rates = [rates[0] for rates in seen]
    assert policy_rates == pytest.approx([ppo.lr * a * r for a, r in zip(anneal, ramp)], rel=1e-12)
    if value_lr is not None:
        assert [rates[1] for rates in seen] == pytest.approx([value_lr * a for a in anneal], rel=1e-12)

    resumed = build()
    resumed.load_state_dict(saved_model)
    resumed_optimizer = optimizer_of(resumed)
    resumed_optimizer.load_state_dict(saved_optimizer)
    resumed_seen = rates_at_each_step(resumed_optimizer)
    ppo_update(resumed, resumed_optimizer, batch, 2, ppo)
    assert resumed_seen == seen[-3:]
    assert torch.equal(flat(resumed), flat(model))


def test_the_warmup_makes_the_first_policy_step_small():
    """Adam's first step moves a weight by about the rate whatever the gradient; with the ramp the
    first update's weights move by a fraction of what they move without it."""
    build, batch = policy_and_batch()
    moves = {}
    for steps in (0, 12):
        model = build()
        before = flat(model)
        ppo_update(model, torch.optim.Adam(model.parameters(), lr=PPO.lr), batch, 0,
                   dataclasses.replace(PPO, epochs=1, mini_batches=1, warmup_steps=steps))
        moves[steps] = float((flat(model) - before).abs().max())
    assert moves[12] == pytest.approx(moves[0] / 12, rel=1e-3)


# --- decoupled PPO (asynchronous training) ------------------------------------------------------


def test_decoupled_ppo_two_ranks_end_with_the_weights_of_one():
    """The proximal log-probs are recomputed by every rank; the update stays split-invariant."""
    build, batch = policy_and_batch()
    gen = torch.Generator().manual_seed(5)
    stale = {**batch, "logprobs": batch["logprobs"] + 0.2 * torch.randn(batch["logprobs"].shape, generator=gen)}
    ppo = dataclasses.replace(PPO, is_cap=2.0, is_cap_mode="mask")
    single = build()
    metrics = ppo_update(single, torch.optim.Adam(single.parameters(), lr=ppo.lr), stale, 0, ppo)
    models, _ = run_two_ranks(build, stale, ppo)
    for model in models:
        torch.testing.assert_close(flat(model), flat(single), rtol=0, atol=1e-6)
    assert metrics["train/behaviour_logprob_abs_diff"] > 0.05 and metrics["train/is_capped_fraction"] < 1
    # rollout vs trainer: the stale rollout's log-probs against the trainer's (not ~0 against its own)
    assert metrics["train/logprob_mismatch"] > 0.05


def test_decoupled_ppo_on_on_policy_data_is_plain_ppo():
    """Behaviour == proximal (the batch came from the current weights): every weight is 1."""
    build, batch = policy_and_batch()
    plain, decoupled = build(), build()
    ppo_update(plain, torch.optim.Adam(plain.parameters(), lr=PPO.lr), batch, 0, PPO)
    metrics = ppo_update(decoupled, torch.optim.Adam(decoupled.parameters(), lr=PPO.lr), batch, 0,
                         dataclasses.replace(PPO, is_cap=2.0))
    torch.testing.assert_close(flat(decoupled), flat(plain), rtol=0, atol=1e-5)
    assert metrics["train/is_weight_mean"] == pytest.approx(1.0, abs=1e-5)


def test_an_anchor_loss_joins_every_policy_step_and_none_of_the_critics_warmup():
    """``anchor(step)`` is asked once per optimizer step, in order, from the first iteration the
    policy trains; its loss is added to that step's PPO loss (an anchor of zero gradient leaves the
    update bit for bit as without one; one with a gradient moves the weights elsewhere)."""
    from infinirl.algorithms import embodied_ppo
    from infinirl.components.embodied_actor import minibatch_order_generator
    from infinirl.engines.parallel import DATA_PARALLEL

    build, batch = policy_and_batch()
    ppo = dataclasses.replace(PPO, critic_warmup=1, total_iterations=3)
    steps = ppo.epochs * ppo.mini_batches

    def train(anchor_of):
        model = build()
        optimizer = DATA_PARALLEL.get("ddp")(0, 1).build_optimizer(model, ppo.lr, ppo.adam_eps)
        asked, metrics = [], []
        for iteration in range(3):
            def anchor(step, model=model, iteration=iteration):
                asked.append((iteration, step))
                return anchor_of(model), {"train/bc_loss": torch.tensor(float(step))}
            metrics.append(embodied_ppo.ppo_update(model, optimizer, batch, iteration, ppo,
                                                   generator=minibatch_order_generator(ppo.seed, iteration),
                                                   anchor=None if anchor_of is None else anchor))
        return model, asked, metrics

    plain, _, _ = train(None)
    zero, asked, metrics = train(lambda model: 0.0 * sum(p.sum() for p in model.parameters()))
    assert asked == [(i, s) for i in (1, 2) for s in range(steps)]
    assert "train/bc_loss" not in metrics[0] and metrics[1]["train/bc_loss"] == (steps - 1) / 2
    assert torch.equal(flat(plain), flat(zero))
    pulled, _, _ = train(lambda model: sum((p ** 2).sum() for p in model.parameters()))
    assert not torch.allclose(flat(plain), flat(pulled))
