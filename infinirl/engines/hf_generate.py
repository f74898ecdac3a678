"""Inference engine on plain transformers: batched, KV-cached, with a hand-written decode loop.

Why our own loop rather than ``model.generate``:

- the returned log-probs come from the very logits we sample from (no second forward pass, no
  guessing which logits processors ``output_scores`` already applied);
- finished rows leave the batch (and the KV cache) at once, so a batch whose samples mostly stop
  early stops paying for them;
- each distinct prompt is prefilled once and its KV cache copied to its ``n`` samples: GRPO groups
  share a prompt, so prefill cost drops ``n``-fold;
- prefill computes logits for the last position only (the LM head is a large share of a small
  model's FLOPs, and the prompt positions' logits are never used here).

Prompts are left-padded so every row's next token sits in the last column; position ids are
derived from the attention mask so padding never shifts a sequence's positions. The result is
therefore the same as generating each prompt alone, up to float rounding.
"""

from __future__ import annotations

import numbers
from collections.abc import Iterable, Sequence

import torch
from transformers import DynamicCache

from infinirl.engines.base import GenerationResult, InferenceEngine, SamplingParams


def filter_top_k_top_p(scaled_logits: torch.Tensor, top_k: int, top_p: float) -> torch.Tensor:
    """Set logits outside the top-k / nucleus (top-p) set to ``-inf`` (applied in that order).

    ``scaled_logits`` are already divided by the temperature, as in HF and vLLM, so the nucleus is
    taken over the tempered distribution the sample is drawn from.
    """
    vocab = scaled_logits.shape[-1]
    if 0 < top_k < vocab:
        kth_largest = torch.topk(scaled_logits, top_k, dim=-1).values[..., -1:]
        scaled_logits = scaled_logits.masked_fill(scaled_logits < kth_largest, float("-inf"))
    if top_p < 1.0:
        sorted_logits, sorted_ids = torch.sort(scaled_logits, dim=-1, descending=True)
        sorted_probs = torch.softmax(sorted_logits, dim=-1)
        mass_before = torch.cumsum(sorted_probs, dim=-1) - sorted_probs
        # A token is dropped once the more likely tokens already cover top_p; the first never is.
        drop_sorted = mass_before >= top_p
        drop = torch.zeros_like(drop_sorted).scatter(-1, sorted_ids, drop_sorted)
        scaled_logits = scaled_logits.masked_fill(drop, float("-inf"))
    return scaled_logits


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
        filtered = filter_top_k_top_p(scaled, sampling.top_k, sampling.top_p)
        probs = logprobs.exp() if filtered is scaled else torch.softmax(filtered, dim=-1)
        tokens = torch.multinomial(probs, 1, generator=generator).squeeze(-1)
    return tokens, logprobs.gather(-1, tokens.unsqueeze(-1)).squeeze(-1)


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


def _as_id_list(value) -> list[int]:
    if value is None:
        return []
    if isinstance(value, int):
        return [value]
    return [int(v) for v in value]


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
            raise RuntimeError("HFGenerateEngine.generate: engine is offloaded; call reload() first")
        self._validate_prompts(prompt_token_ids, sampling)
        if not prompt_token_ids:
            return []
        stop_ids = set(sampling.stop_token_ids)
        if not sampling.ignore_eos:
            stop_ids.update(self.eos_token_ids)
        matcher = (
            StopStringMatcher(self.tokenizer, sampling.stop_strings) if sampling.stop_strings else None
        )
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
        device = self._home_device
        unique_prompts = list(dict.fromkeys(p for p, _ in requests))
        slot_of_prompt = {p: slot for slot, p in enumerate(unique_prompts)}
        row_to_slot = torch.tensor([slot_of_prompt[p] for p, _ in requests], device=device)

        # Prefill each distinct prompt once, then copy its cache to every sample of it.
        input_ids, attention_mask = self._left_pad([list(prompts[p]) for p in unique_prompts])
        position_ids = (attention_mask.cumsum(-1) - 1).clamp(min=0)
        cache = DynamicCache(config=self.model.config)
        out = self.model(
            input_ids=input_ids,
            attention_mask=attention_mask,
            position_ids=position_ids,
            past_key_values=cache,
            use_cache=True,
            logits_to_keep=1,
        )
        logits = out.logits[:, -1, :].float()[row_to_slot]
        if len(unique_prompts) != len(requests):
            cache.batch_select_indices(row_to_slot)
        attention_mask = attention_mask[row_to_slot]
        next_position = position_ids[row_to_slot, -1] + 1

        num_rows, max_new = len(requests), sampling.max_new_tokens
        token_buf = torch.zeros((num_rows, max_new), dtype=torch.long, device=device)
        logprob_buf = torch.zeros((num_rows, max_new), dtype=torch.float32, device=device)
        lengths = [max_new] * num_rows
        finish = ["length"] * num_rows
        stop_strings: dict[int, str] = {}
        stop_id_tensor = torch.tensor(sorted(stop_ids), dtype=torch.long, device=device)
        active = torch.arange(num_rows, device=device)  # request row of each batch row

        for step in range(max_new):
            tokens, token_logprobs = sample_next_tokens(logits, sampling, generator)
            token_buf[active, step] = tokens
            logprob_buf[active, step] = token_logprobs
            done = torch.isin(tokens, stop_id_tensor).tolist()
            active_rows = active.tolist()
            if matcher is not None:
                for i, row in enumerate(active_rows):
                    if not done[i]:
                        hit = matcher.match(token_buf[row, : step + 1].tolist())
                        if hit is not None:
                            done[i] = True
                            stop_strings[row] = hit
            for i, row in enumerate(active_rows):
                if done[i]:
                    lengths[row], finish[row] = step + 1, "stop"
            if step + 1 == max_new or all(done):
                break
            if any(done):
                keep = torch.tensor(
                    [i for i, d in enumerate(done) if not d], dtype=torch.long, device=device
                )
                cache.batch_select_indices(keep)
                active, tokens = active[keep], tokens[keep]
                attention_mask, next_position = attention_mask[keep], next_position[keep]
            attention_mask = torch.cat(
                [attention_mask, attention_mask.new_ones((attention_mask.shape[0], 1))], dim=-1
            )
            out = self.model(
                input_ids=tokens.unsqueeze(-1),
                attention_mask=attention_mask,
                position_ids=next_position.unsqueeze(-1),
                past_key_values=cache,
                use_cache=True,
            )
            logits = out.logits[:, -1, :].float()
            next_position = next_position + 1

        token_lists, logprob_lists = token_buf.tolist(), logprob_buf.tolist()
        results = []
        for row, (prompt_index, sample_index) in enumerate(requests):
            n_tokens = lengths[row]
            results.append(
                GenerationResult(
                    prompt_ids=list(prompts[prompt_index]),
                    response_ids=token_lists[row][:n_tokens],
                    response_logprobs=logprob_lists[row][:n_tokens],
                    finish_reason=finish[row],
                    weight_version=self._weight_version,
                    prompt_index=prompt_index,
                    sample_index=sample_index,
                    extra={"stop_string": stop_strings[row]} if row in stop_strings else {},
                )
            )
        return results

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
