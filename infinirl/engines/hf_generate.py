"""Inference engine on plain transformers: batched, KV-cached, with a hand-written decode loop.

Why our own loop rather than ``model.generate``:

- the returned log-probs come from the very logits we sample from (no second forward pass, no
  guessing which logits processors ``output_scores`` already applied);
- finished rows leave the batch (and the KV cache) at once, so a batch whose samples mostly stop
  early stops paying for them;
- each distinct prompt is prefilled once and its KV cache copied to its ``n`` samples: GRPO groups
  share a prompt, so prefill cost drops ``n``-fold;
- prefill computes logits for the last position only (the LM head is a large share of a small
  model's FLOPs, and the prompt positions' logits are never used here);
- the KV cache is preallocated (no per-token ``torch.cat`` of the whole cache) and sampling uses
  an inverse CDF instead of ``torch.multinomial``: together ~35% of a CPU decode step.

CPU note: on a machine shared with other busy processes, run with ``OMP_WAIT_POLICY=PASSIVE``
(set before torch is imported). Under contention OpenMP's default spin-waiting made generation
~6x slower for SmolLM2-135M and ~100x for a tiny test model in our measurements.

Prompts are left-padded so every row's next token sits in the last column; position ids are
derived from the attention mask so padding never shifts a sequence's positions. The result is
therefore the same as generating each prompt alone, up to float rounding.
"""

from __future__ import annotations

import inspect
import numbers
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import torch
from transformers import DynamicCache
from transformers.cache_utils import DynamicLayer

from infinirl.engines.base import GenerationResult, InferenceEngine, SamplingParams

NUCLEUS_SEARCH_WIDTH = 64
"""Top-p looks for the nucleus among this many most likely tokens first: a full-vocabulary sort
costs ~100 ms per step at batch 64 on CPU, while the nucleus usually holds a handful of tokens.
Rows whose nucleus is wider fall back to the full sort, so the result is exact either way."""


def excluded_tokens(probs: torch.Tensor, top_k: int, top_p: float) -> torch.Tensor | None:
    """Mask of tokens that top-k, then top-p, exclude from sampling; None if both are off.

    ``probs [R, V]`` is the tempered, normalised distribution. As in HF and vLLM, top-p runs on
    the distribution renormalised over the top-k survivors.
    """
    vocab = probs.shape[-1]
    drop = None
    if 0 < top_k < vocab:
        kth_largest = torch.topk(probs, top_k, dim=-1).values[..., -1:]
        drop = probs < kth_largest  # ties with the k-th token are kept, as in HF
    if top_p < 1.0:
        if drop is not None:
            probs = probs.masked_fill(drop, 0.0)
            probs = probs / probs.sum(-1, keepdim=True)
        nucleus_drop = _outside_nucleus(probs, top_p)
        drop = nucleus_drop if drop is None else drop | nucleus_drop
    return drop


def _outside_nucleus(probs: torch.Tensor, top_p: float) -> torch.Tensor:
    """Tokens after the smallest most-likely prefix whose mass reaches ``top_p``."""

    def drop_from_sorted(sorted_probs, sorted_ids):
        mass_before = torch.cumsum(sorted_probs, dim=-1) - sorted_probs
        # A token is dropped once the more likely ones already reach top_p; the first never is.
        keep_sorted = mass_before < top_p
        keep = torch.zeros_like(probs[: len(sorted_ids)], dtype=torch.bool)
        return ~keep.scatter(-1, sorted_ids, keep_sorted)

    width = min(NUCLEUS_SEARCH_WIDTH, probs.shape[-1])
    top_probs, top_ids = torch.topk(probs, width, dim=-1)
    drop = drop_from_sorted(top_probs, top_ids)
    wide_rows = (top_probs.sum(-1) < top_p).nonzero().squeeze(-1)
    if wide_rows.numel():
        sorted_probs, sorted_ids = torch.sort(probs[wide_rows], dim=-1, descending=True)
        drop[wide_rows] = drop_from_sorted(sorted_probs, sorted_ids)
    return drop


def sample_from_weights(weights: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
    """One index per row of non-negative, not necessarily normalised ``weights [R, V]``.

    Inverse-CDF sampling: a cumsum and a binary search cost ~2 ms at batch 64 x 49k vocab on CPU,
    where ``torch.multinomial`` costs ~60 ms (it draws an exponential per vocabulary entry).
    """
    cdf = torch.cumsum(weights, dim=-1)
    u = torch.rand(
        (weights.shape[0], 1), generator=generator, device=weights.device, dtype=cdf.dtype
    )
    tokens = torch.searchsorted(cdf, u * cdf[:, -1:], right=True).squeeze(-1)
    # u * total can round up to the total itself: step back to the last token with weight.
    overflow = tokens >= weights.shape[-1]
    if overflow.any():
        last_positive = weights.shape[-1] - 1 - (weights.flip(-1) > 0).int().argmax(-1)
        tokens = torch.where(overflow, last_positive, tokens)
    return tokens


def sample_next_tokens(
    logits: torch.Tensor, sampling: SamplingParams, generator: torch.Generator | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pick one token per row of float32 ``logits [R, V]``; return ``(tokens [R], logprobs [R])``.

    The log-prob is ``log softmax(logits / T)`` at the chosen token, over the full vocabulary
    (see ``infinirl.engines.base`` for why top-k/top-p are not renormalised into it).
    """
    temperature = sampling.logprob_temperature
    scaled = logits if temperature == 1.0 else logits / temperature
    logprobs = torch.log_softmax(scaled, dim=-1)
    if sampling.is_greedy:
        tokens = torch.argmax(logits, dim=-1)
    else:
        probs = logprobs.exp()
        drop = excluded_tokens(probs, sampling.top_k, sampling.top_p)
        if drop is not None:
            probs = probs.masked_fill(drop, 0.0)
        tokens = sample_from_weights(probs, generator)
    return tokens, logprobs.gather(-1, tokens.unsqueeze(-1)).squeeze(-1)


class PreallocatedKVLayer(DynamicLayer):
    """A KV-cache layer that writes into a buffer sized for the whole generation.

    transformers' ``DynamicLayer`` grows by ``torch.cat``, re-copying the entire cache every
    token: ~25% of a batch-64 decode step of SmolLM2-135M on CPU. We know the final length up
    front (longest prompt + max_new_tokens), so we allocate once and hand attention a view.
    """

    def __init__(self, capacity: int):
        super().__init__()
        self.capacity = capacity
        self.length = 0
        self._key_buffer: torch.Tensor | None = None
        self._value_buffer: torch.Tensor | None = None

    def lazy_initialization(self, key_states: torch.Tensor, value_states: torch.Tensor) -> None:
        self.dtype, self.device = key_states.dtype, key_states.device
        batch, heads, _, key_dim = key_states.shape
        self._key_buffer = key_states.new_empty((batch, heads, self.capacity, key_dim))
        self._value_buffer = value_states.new_empty(
            (batch, value_states.shape[1], self.capacity, value_states.shape[-1])
        )
        self.is_initialized = True

    def update(self, key_states, value_states, *args, **kwargs):
        if not self.is_initialized:
            self.lazy_initialization(key_states, value_states)
        end = self.length + key_states.shape[-2]
        if end > self.capacity:
            raise RuntimeError(
                f"PreallocatedKVLayer: {end} positions exceed the preallocated {self.capacity}"
            )
        self._key_buffer[:, :, self.length : end] = key_states
        self._value_buffer[:, :, self.length : end] = value_states
        self.length = end
        self._refresh_views()
        return self.keys, self.values

    def _refresh_views(self) -> None:
        self.keys = self._key_buffer[:, :, : self.length]
        self.values = self._value_buffer[:, :, : self.length]

    def get_seq_length(self) -> int:
        return self.length

    def batch_select_indices(self, indices: torch.Tensor) -> None:
        if self.is_initialized:
            self._key_buffer = self._key_buffer[indices]
            self._value_buffer = self._value_buffer[indices]
            self._refresh_views()

    def batch_repeat_interleave(self, repeats: int) -> None:
        if self.is_initialized:
            self._key_buffer = self._key_buffer.repeat_interleave(repeats, dim=0)
            self._value_buffer = self._value_buffer.repeat_interleave(repeats, dim=0)
            self._refresh_views()

    def crop(self, tokens_to_remove: int) -> None:
        if tokens_to_remove > 0:
            raise ValueError(f"crop({tokens_to_remove}): pass a negative number of tokens")
        self.length = max(0, self.length + tokens_to_remove)
        if self.is_initialized:
            self._refresh_views()

    def reset(self) -> None:
        self.length = 0
        self._key_buffer = self._value_buffer = None
        super().reset()


def new_kv_cache(model, capacity: int) -> DynamicCache:
    """A ``DynamicCache`` whose layers are preallocated to ``capacity`` positions, when every layer
    is a plain full-attention one; otherwise (sliding windows, hybrids) transformers' own layers."""
    cache = DynamicCache(config=model.config)
    if cache.layers and all(type(layer) is DynamicLayer for layer in cache.layers):
        cache.layers = [PreallocatedKVLayer(capacity) for _ in cache.layers]
    return cache


class StopStringMatcher:
    """Finds stop strings in a growing response by decoding only its tail.

    Checked after every token, so a match found now must involve the newest token (an older one
    would have stopped generation earlier); the tail only has to be long enough to hold the
    longest stop string. Byte-level tokens can decode to a fraction of a character, hence the
    4-tokens-per-character allowance.
    """

    def __init__(self, tokenizer, stop_strings: Sequence[str]):
        if tokenizer is None:
            raise ValueError(
                f"stop_strings={list(stop_strings)!r} need a tokenizer to decode responses; "
                "pass tokenizer= to HFGenerateEngine or use stop_token_ids instead"
            )
        self._tokenizer = tokenizer
        self._stop_strings = tuple(stop_strings)
        self._window = 4 * max(len(s) for s in stop_strings) + 4

    def match(self, response_ids: Sequence[int]) -> str | None:
        """The stop string present in the tail of ``response_ids``, or None."""
        text = self._tokenizer.decode(
            list(response_ids[-self._window :]),
            skip_special_tokens=False,
            clean_up_tokenization_spaces=False,
        )
        for stop in self._stop_strings:
            if stop in text:
                return stop
        return None


@dataclass
class _DecodeState:
    """What a micro-batch's decode loop carries between steps, one row per unfinished request."""

    cache: DynamicCache
    attention_mask: torch.Tensor  # [rows, positions so far]; 0 on left padding
    next_position: torch.Tensor  # [rows] position id of the token fed next
    active: torch.Tensor  # [rows] index of each row's request in the micro-batch

    def keep_rows(self, keep: torch.Tensor) -> None:
        """Drop finished rows, so later steps stop computing them."""
        self.cache.batch_select_indices(keep)
        self.attention_mask = self.attention_mask[keep]
        self.next_position = self.next_position[keep]
        self.active = self.active[keep]


def _as_id_list(value) -> list[int]:
    if value is None:
        return []
    if isinstance(value, int):
        return [value]
    return [int(v) for v in value]


def cache_keyword(model) -> str:
    """The name under which ``model``'s forward takes its KV cache.

    transformers 5.2x renamed it ``cache``; ``past_key_values`` still works there but warns on
    every forward call (dozens of warnings per rollout, from every rank) and is to be removed in
    5.40. Older releases (we support >= 4.56) know only ``past_key_values``."""
    forward = getattr(model, "_orig_mod", model).forward  # torch.compile's wrapper hides the signature
    return "cache" if "cache" in inspect.signature(forward).parameters else "past_key_values"


class HFGenerateEngine(InferenceEngine):
    """``InferenceEngine`` over a transformers causal LM (any device; tuned for CPU rollouts).

    Args:
        model: a ``PreTrainedModel`` causal LM. It is put in eval mode and used in place, so a
            trainer in the same process could share it (then ``load_weights`` is unnecessary).
        tokenizer: only needed for ``stop_strings`` and default EOS/pad ids; ids in, ids out.
        max_batch_size: most sequences decoded together (prompts x n). Bounds KV-cache memory;
            larger requests run as consecutive micro-batches.
        eos_token_ids: ids that end a response. Default: the model's generation config EOS ids
            plus the tokenizer's EOS id.
        pad_token_id: id used for left padding (masked out, so any valid id works). Default: the
            tokenizer's pad id, else the first EOS id, else 0.
    """

    def __init__(
        self,
        model,
        tokenizer=None,
        *,
        max_batch_size: int = 64,
        eos_token_ids: Sequence[int] | None = None,
        pad_token_id: int | None = None,
    ):
        if max_batch_size < 1:
            raise ValueError(f"HFGenerateEngine: max_batch_size={max_batch_size} must be >= 1")
        self.model = model.eval()
        self.tokenizer = tokenizer
        self.max_batch_size = max_batch_size
        self.eos_token_ids = self._default_eos_ids(model, tokenizer, eos_token_ids)
        self.pad_token_id = self._default_pad_id(tokenizer, self.eos_token_ids, pad_token_id)
        self._home_device = next(model.parameters()).device
        self._vocab_size = model.get_input_embeddings().weight.shape[0]
        self._max_positions = getattr(model.config, "max_position_embeddings", None)
        self._weight_version = 0
        self._offloaded = False
        self._cache_keyword = cache_keyword(model)

    @staticmethod
    def _default_eos_ids(model, tokenizer, explicit) -> tuple[int, ...]:
        if explicit is not None:
            return tuple(int(t) for t in explicit)
        ids = _as_id_list(getattr(getattr(model, "generation_config", None), "eos_token_id", None))
        if tokenizer is not None:
            ids += _as_id_list(tokenizer.eos_token_id)
        return tuple(dict.fromkeys(ids))

    @staticmethod
    def _default_pad_id(tokenizer, eos_ids, explicit) -> int:
        if explicit is not None:
            return int(explicit)
        if tokenizer is not None and tokenizer.pad_token_id is not None:
            return int(tokenizer.pad_token_id)
        return eos_ids[0] if eos_ids else 0

    # ----------------------------------------------------------------------------- generation

    def generate(
        self, prompt_token_ids: list[list[int]], sampling: SamplingParams
    ) -> list[GenerationResult]:
        if self._offloaded:
            raise RuntimeError("HFGenerateEngine.generate: engine is offloaded; call reload()")
        self._validate_prompts(prompt_token_ids, sampling)
        if not prompt_token_ids:
            return []
        stop_ids = set(sampling.stop_token_ids)
        if not sampling.ignore_eos:
            stop_ids.update(self.eos_token_ids)
        matcher = None
        if sampling.stop_strings:
            matcher = StopStringMatcher(self.tokenizer, sampling.stop_strings)
        generator = None
        if sampling.seed is not None and not sampling.is_greedy:
            generator = torch.Generator(device=self._home_device).manual_seed(sampling.seed)
        # Prompt-major request order; micro-batches are consecutive slices of it, so a GRPO group
        # usually shares one prefill.
        requests = [(p, s) for p in range(len(prompt_token_ids)) for s in range(sampling.n)]
        results: list[GenerationResult] = []
        for start in range(0, len(requests), self.max_batch_size):
            chunk = requests[start : start + self.max_batch_size]
            results.extend(
                self._generate_micro_batch(
                    prompt_token_ids, chunk, sampling, generator, stop_ids, matcher
                )
            )
        return results

    def _validate_prompts(self, prompts: list[list[int]], sampling: SamplingParams) -> None:
        for i, prompt in enumerate(prompts):
            if len(prompt) == 0:
                raise ValueError(f"generate: prompt {i} is empty; every prompt needs >= 1 token")
            if not all(isinstance(t, numbers.Integral) for t in prompt):
                raise TypeError(
                    f"generate: prompt {i} must be a list of token ids (ints), got elements like "
                    f"{next(t for t in prompt if not isinstance(t, numbers.Integral))!r}; "
                    "tokenize first (apply_chat_template(..., return_dict=False))"
                )
            low, high = min(prompt), max(prompt)
            if low < 0 or high >= self._vocab_size:
                raise ValueError(
                    f"generate: prompt {i} has token id {high if high >= self._vocab_size else low}"
                    f" outside the model's vocabulary [0, {self._vocab_size})"
                )
            needed = len(prompt) + sampling.max_new_tokens
            if self._max_positions is not None and needed > self._max_positions:
                raise ValueError(
                    f"generate: prompt {i} ({len(prompt)} tokens) + max_new_tokens="
                    f"{sampling.max_new_tokens} = {needed} exceeds the model's "
                    f"max_position_embeddings={self._max_positions}; shorten the prompt or "
                    "lower max_new_tokens"
                )

    def _left_pad(self, prompts: list[list[int]]) -> tuple[torch.Tensor, torch.Tensor]:
        width = max(len(p) for p in prompts)
        input_ids = torch.full((len(prompts), width), self.pad_token_id, dtype=torch.long)
        attention_mask = torch.zeros((len(prompts), width), dtype=torch.long)
        for row, prompt in enumerate(prompts):
            input_ids[row, width - len(prompt) :] = torch.as_tensor(prompt, dtype=torch.long)
            attention_mask[row, width - len(prompt) :] = 1
        return input_ids.to(self._home_device), attention_mask.to(self._home_device)

    def _prefill(
        self, prompts: list[list[int]], requests: list[tuple[int, int]], max_new_tokens: int
    ) -> tuple[_DecodeState, torch.Tensor]:
        """Run each distinct prompt once, then copy its KV cache to every sample of it.

        Returns the per-request decode state and the float32 logits of each request's first token.
        """
        unique_prompts = list(dict.fromkeys(p for p, _ in requests))
        slot_of_prompt = {p: slot for slot, p in enumerate(unique_prompts)}
        row_to_slot = torch.tensor(
            [slot_of_prompt[p] for p, _ in requests], device=self._home_device
        )
        input_ids, attention_mask = self._left_pad([list(prompts[p]) for p in unique_prompts])
        position_ids = (attention_mask.cumsum(-1) - 1).clamp(min=0)
        cache = new_kv_cache(self.model, input_ids.shape[1] + max_new_tokens)
        out = self.model(
            input_ids=input_ids,
            attention_mask=attention_mask,
            position_ids=position_ids,
            use_cache=True,
            logits_to_keep=1,
            **{self._cache_keyword: cache},
        )
        if len(unique_prompts) != len(requests):
            cache.batch_select_indices(row_to_slot)
        state = _DecodeState(
            cache=cache,
            attention_mask=attention_mask[row_to_slot],
            next_position=position_ids[row_to_slot, -1] + 1,
            active=torch.arange(len(requests), device=self._home_device),
        )
        return state, out.logits[:, -1, :].float()[row_to_slot]

    def _decode_step(self, state: _DecodeState, tokens: torch.Tensor) -> torch.Tensor:
        """Feed one token per active row; return the float32 logits of the next one."""
        state.attention_mask = torch.cat(
            [state.attention_mask, state.attention_mask.new_ones((len(tokens), 1))], dim=-1
        )
        out = self.model(
            input_ids=tokens.unsqueeze(-1),
            attention_mask=state.attention_mask,
            position_ids=state.next_position.unsqueeze(-1),
            use_cache=True,
            **{self._cache_keyword: state.cache},
        )
        state.next_position = state.next_position + 1
        return out.logits[:, -1, :].float()

    @torch.inference_mode()
    def _generate_micro_batch(
        self,
        prompts: list[list[int]],
        requests: list[tuple[int, int]],
        sampling: SamplingParams,
        generator: torch.Generator | None,
        stop_ids: set[int],
        matcher: StopStringMatcher | None,
    ) -> list[GenerationResult]:
        device, num_rows, max_new = self._home_device, len(requests), sampling.max_new_tokens
        state, logits = self._prefill(prompts, requests, max_new)
        token_buf = torch.zeros((num_rows, max_new), dtype=torch.long, device=device)
        logprob_buf = torch.zeros((num_rows, max_new), dtype=torch.float32, device=device)
        lengths, finish = [max_new] * num_rows, ["length"] * num_rows
        stop_strings: dict[int, str] = {}
        stop_id_tensor = torch.tensor(sorted(stop_ids), dtype=torch.long, device=device)

        for step in range(max_new):
            tokens, token_logprobs = sample_next_tokens(logits, sampling, generator)
            token_buf[state.active, step] = tokens
            logprob_buf[state.active, step] = token_logprobs
            done = torch.isin(tokens, stop_id_tensor).tolist()
            for i, row in enumerate(state.active.tolist()):
                if not done[i] and matcher is not None:
                    hit = matcher.match(token_buf[row, : step + 1].tolist())
                    if hit is not None:
                        done[i], stop_strings[row] = True, hit
                if done[i]:
                    lengths[row], finish[row] = step + 1, "stop"
            if step + 1 == max_new or all(done):
                break
            if any(done):
                keep = [i for i, finished in enumerate(done) if not finished]
                keep_index = torch.tensor(keep, dtype=torch.long, device=device)
                state.keep_rows(keep_index)
                tokens = tokens[keep_index]
            logits = self._decode_step(state, tokens)

        token_lists, logprob_lists = token_buf.tolist(), logprob_buf.tolist()
        return [
            GenerationResult(
                prompt_ids=list(prompts[prompt_index]),
                response_ids=token_lists[row][: lengths[row]],
                response_logprobs=logprob_lists[row][: lengths[row]],
                finish_reason=finish[row],
                weight_version=self._weight_version,
                prompt_index=prompt_index,
                sample_index=sample_index,
                extra={"stop_string": stop_strings[row]} if row in stop_strings else {},
            )
            for row, (prompt_index, sample_index) in enumerate(requests)
        ]

    # ---------------------------------------------------------------------------- weight sync

    @property
    def weight_version(self) -> int:
        return self._weight_version

    def load_weights(
        self, named_tensors: Iterable[tuple[str, torch.Tensor]], version: int
    ) -> None:
        """Copy tensors into the model by state-dict name, then adopt ``version``.

        Every weight must be sent (a tied weight under either of its names is enough): a silently
        partial update would tag samples from a half-old model with the new version. Tensors are
        copied as they stream in, so on an error the model may be partly updated, but the version
        stays old. ``copy_`` is bit-exact when dtypes match and rounds like ``.to()`` otherwise.
        """
        if not isinstance(version, int):
            raise TypeError(f"load_weights: version must be an int, got {version!r}")
        targets = self.model.state_dict(keep_vars=True)
        unique_names = {id(t): name for name, t in targets.items()}
        loaded: set[int] = set()
        with torch.no_grad():
            for name, tensor in named_tensors:
                target = targets.get(name)
                if target is None:
                    examples = ", ".join(list(targets)[:3])
                    raise KeyError(
                        f"load_weights: unknown weight name {name!r}; this model's names look "
                        f"like {examples}, ... (strip wrapper prefixes such as 'module.' first)"
                    )
                if tuple(target.shape) != tuple(tensor.shape):
                    raise ValueError(
                        f"load_weights: {name!r} has shape {tuple(tensor.shape)} but the model "
                        f"expects {tuple(target.shape)}"
                    )
                target.copy_(tensor)
                loaded.add(id(target))
        missing = [name for key, name in unique_names.items() if key not in loaded]
        if missing:
            raise ValueError(
                f"load_weights: {len(missing)} weights were not sent (e.g. {missing[:3]}); "
                f"send the full state dict. weight_version stays {self._weight_version}"
            )
        self._weight_version = version

    # ------------------------------------------------------------------------ offload / reload

    @property
    def is_offloaded(self) -> bool:
        return self._offloaded

    def offload(self) -> None:
        """Move weights to host memory. On a CPU-only engine there is nothing to free: only the
        state flag changes (the KV cache lives only inside ``generate`` calls anyway)."""
        if self._offloaded:
            return
        if self._home_device.type != "cpu":
            self.model.to("cpu")
            if self._home_device.type == "cuda":
                torch.cuda.empty_cache()
        self._offloaded = True

    def reload(self) -> None:
        if not self._offloaded:
            return
        if self._home_device.type != "cpu":
            self.model.to(self._home_device)
        self._offloaded = False
