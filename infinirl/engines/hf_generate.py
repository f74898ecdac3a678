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
- the KV cache is preallocated (:mod:`~infinirl.engines.kv_cache`: no per-token ``torch.cat`` of
  the whole cache) and sampling uses an inverse CDF instead of ``torch.multinomial``
  (:mod:`~infinirl.engines.sampling`): both per-token costs would otherwise grow with the batch.

CPU note: on a machine shared with other busy processes, run with ``OMP_WAIT_POLICY=PASSIVE``
(set before torch is imported). Under contention OpenMP's default spin-waiting keeps idle threads
on the cores the busy processes need, and a decode loop of many small ops then slows by a large
factor, the more so the smaller the model.

Prompts are left-padded so every row's next token sits in the last column; position ids are
derived from the attention mask so padding never shifts a sequence's positions. The result is
therefore the same as generating each prompt alone, up to float rounding.

Partial rollouts: ``weight_refresh`` (set by the rollout worker) is asked between decode steps
whether new weights were just loaded. If so, the unfinished rows' KV caches (computed by the old
weights) are rebuilt by one prefill over prompt + tokens so far with the new weights, and decoding
goes on; every token keeps the log-prob and the version of the weights that sampled it.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import torch

from infinirl.engines.base import GenerationResult, InferenceEngine, SamplingParams
from infinirl.engines.generate_inputs import default_eos_ids, stop_token_ids, validate_prompts
from infinirl.engines.kv_cache import DecodeState, cache_keyword, new_kv_cache
from infinirl.engines.sampling import sample_next_tokens
from infinirl.engines.stop_strings import StopStringMatcher

__all__ = ["HFGenerateEngine"]

class _VersionLog:
    """Which weights version sampled each row's tokens: the version at the start, and the steps
    at which a row switched (partial rollouts; usually none)."""

    def __init__(self, version: int):
        self._start = version
        self._switches: dict[int, list[tuple[int, int]]] = {}

    def switch(self, rows: list[int], step: int, version: int) -> None:
        for row in rows:
            self._switches.setdefault(row, []).append((step, version))

    def first(self, row: int) -> int:
        return self._start

    def per_token(self, row: int, length: int) -> list[int] | None:
        switches = self._switches.get(row)
        if not switches:
            return None
        out, version = [], self._start
        pending = iter(switches)
        upcoming = next(pending, None)
        for step in range(length):
            while upcoming is not None and upcoming[0] == step:
                version = upcoming[1]
                upcoming = next(pending, None)
            out.append(version)
        return out


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
        generation_eos = getattr(getattr(model, "generation_config", None), "eos_token_id", None)
        self.eos_token_ids = default_eos_ids(eos_token_ids, generation_eos, tokenizer)
        self.pad_token_id = self._default_pad_id(tokenizer, self.eos_token_ids, pad_token_id)
        self._home_device = next(model.parameters()).device
        self._vocab_size = model.get_input_embeddings().weight.shape[0]
        self._max_positions = getattr(model.config, "max_position_embeddings", None)
        self._weight_version = 0
        self._holds_full_sync = False  # a full set of the trainer's weights loaded (changed-only syncs build on it)
        self._changed_only_names: frozenset[str] | None = None  # what the first changed-only sync sent
        self._torn: tuple[int, bool] | None = None  # (version, changed_only) of a load that failed after copying
        self.weight_refresh = None
        """Partial rollouts: called between decode steps; True when it has just loaded new weights."""
        self._offloaded = False
        self._cache_keyword = cache_keyword(model)

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
        if self._torn is not None:
            raise RuntimeError(f"HFGenerateEngine.generate: loading weights version {self._torn[0]} failed after "
                               f"copying some of them, so the model mixes them with version {self._weight_version}; "
                               f"load weights again before generating")
        self._validate_prompts(prompt_token_ids, sampling)
        if not prompt_token_ids:
            return []
        stop_ids = stop_token_ids(sampling, self.eos_token_ids)
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
        validate_prompts(prompts, sampling, self._vocab_size, self._max_positions,
                         "the model's max_position_embeddings")

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
    ) -> tuple[DecodeState, torch.Tensor]:
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
        state = DecodeState(
            cache=cache,
            attention_mask=attention_mask[row_to_slot],
            next_position=position_ids[row_to_slot, -1] + 1,
            active=torch.arange(len(requests), device=self._home_device),
        )
        return state, out.logits[:, -1, :].float()[row_to_slot]

    def _decode_step(self, state: DecodeState, tokens: torch.Tensor) -> torch.Tensor:
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
        stop_ids: list[int],
        matcher: StopStringMatcher | None,
    ) -> list[GenerationResult]:
        device, num_rows, max_new = self._home_device, len(requests), sampling.max_new_tokens
        self._refreshed()
        state, logits = self._prefill(prompts, requests, max_new)
        token_buf = torch.zeros((num_rows, max_new), dtype=torch.long, device=device)
        logprob_buf = torch.zeros((num_rows, max_new), dtype=torch.float32, device=device)
        versions = _VersionLog(self._weight_version)
        lengths, finish = [max_new] * num_rows, ["length"] * num_rows
        stop_strings: dict[int, str] = {}
        stop_id_tensor = torch.tensor(stop_ids, dtype=torch.long, device=device)

        for step in range(max_new):
            if step and self._refreshed():
                state, logits = self._prefill_continuations(prompts, requests, state, token_buf[:, :step],
                                                            max_new - step)
                versions.switch(state.active.tolist(), step, self._weight_version)
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
                weight_version=versions.first(row),
                prompt_index=prompt_index,
                sample_index=sample_index,
                extra={"stop_string": stop_strings[row]} if row in stop_strings else {},
                response_versions=versions.per_token(row, lengths[row]),
            )
            for row, (prompt_index, sample_index) in enumerate(requests)
        ]

    def _refreshed(self) -> bool:
        return self.weight_refresh is not None and bool(self.weight_refresh())

    def _prefill_continuations(self, prompts, requests, state: DecodeState, generated: torch.Tensor,
                               remaining: int) -> tuple[DecodeState, torch.Tensor]:
        """A fresh decode state for the unfinished rows: their prompts plus the ``generated`` ids so
        far, prefilled by the current weights; the logits of each row's next token."""
        rows = state.active.tolist()
        sequences = [list(prompts[requests[row][0]]) + generated[row].tolist() for row in rows]
        input_ids, attention_mask = self._left_pad(sequences)
        position_ids = (attention_mask.cumsum(-1) - 1).clamp(min=0)
        cache = new_kv_cache(self.model, input_ids.shape[1] + remaining)
        out = self.model(input_ids=input_ids, attention_mask=attention_mask, position_ids=position_ids,
                         use_cache=True, logits_to_keep=1, **{self._cache_keyword: cache})
        fresh = DecodeState(cache=cache, attention_mask=attention_mask, next_position=position_ids[:, -1] + 1,
                            active=state.active)
        return fresh, out.logits[:, -1, :].float()

    # ---------------------------------------------------------------------------- weight sync

    @property
    def context_length(self) -> int | None:
        return self._max_positions

    @property
    def weight_version(self) -> int:
        return self._weight_version

    def load_weights(
        self, named_tensors: Iterable[tuple[str, torch.Tensor]], version: int, changed_only: bool = False
    ) -> None:
        """Copy tensors into the model by state-dict name, then adopt ``version``.

        Every weight must be sent (a tied weight under either of its names is enough): a silently
        partial update would tag samples from a half-old model with the new version. The exception
        is ``changed_only``, the trainer's declaration that it sends only what training changes;
        it is accepted only after a full load from the trainer (the rest of the model is then
        exactly the trainer's). Tensors are copied as they stream in, so on an error after the first
        copy the model is torn (two versions mixed) and the version stays old: ``generate`` then
        refuses to run until a load succeeds (a full one, if the failed one was full). ``copy_`` is
        bit-exact when dtypes match and rounds like ``.to()`` otherwise.
        """
        if not isinstance(version, int):
            raise TypeError(f"load_weights: version must be an int, got {version!r}")
        if changed_only and not self._holds_full_sync:
            raise ValueError(f"load_weights(changed_only=True): this engine has not loaded a full set of the "
                             f"trainer's weights yet, so the weights left out may not be the trainer's; send "
                             f"every weight first. weight_version stays {self._weight_version}")
        targets = self.model.state_dict(keep_vars=True)
        unique_names = {id(t): name for name, t in targets.items()}
        loaded: set[int] = set()
        try:
            self._copy_named(named_tensors, targets, loaded)
            missing = [name for key, name in unique_names.items() if key not in loaded]
            if missing and not changed_only:
                raise ValueError(
                    f"load_weights: {len(missing)} weights were not sent (e.g. {missing[:3]}); "
                    f"send the full state dict. weight_version stays {self._weight_version}"
                )
            if changed_only:
                self._check_changed_only_names(frozenset(unique_names[key] for key in loaded))
        except BaseException:
            if loaded:  # a mix of two versions, stamped with neither: generate refuses it
                self._torn = (version, changed_only)
                # what a full load left old is not the trainer's: a changed-only load cannot repair it
                self._holds_full_sync = self._holds_full_sync and changed_only
            raise
        if self._torn is not None and (not changed_only or self._torn[1]):
            self._torn = None  # this load rewrote every weight the failed one may have touched
        self._holds_full_sync = True
        self._weight_version = version

    @staticmethod
    def _copy_named(named_tensors, targets: dict, loaded: set[int]) -> None:
        """Copy each tensor into the model's by name; ``loaded`` collects the targets copied."""
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

    def _check_changed_only_names(self, sent: frozenset[str]) -> None:
        """What training changes does not change between syncs: a changed-only sync that sends
        nothing, or other weights than the first one did, means the trainer's idea of it broke."""
        expected = self._changed_only_names if self._changed_only_names is not None else sent
        if not sent or sent != expected:
            raise ValueError(f"load_weights(changed_only=True): sent {len(sent)} weights, the first changed-only "
                             f"sync {len(expected)}; differing: {sorted(sent ^ expected)[:3]}. The version stays "
                             f"{self._weight_version} (the sent weights are loaded)")
        self._changed_only_names = sent

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
