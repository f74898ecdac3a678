"""Score rows that share a prompt as one packed sequence: each prompt once, no padding.

In GRPO-style training every prompt is sampled ``n`` times (8 is typical) and each of the ``n``
rows repeats the whole prompt: a plain forward computes, and backpropagates through, the same
prompt ``n`` times. Rows are also right-padded to the longest response of the micro-batch. With
short answers to long prompts, repeated prompts and padding are most of the tokens computed.

So the rows of a micro-batch that share a prompt become one packed row::

    [prompt | response 1 | response 2 | ... | response n]

with a 4-D attention mask in which each response sees the prompt and, causally, itself only; each
token keeps its original position id. Every token therefore attends to exactly the keys it had in
its own row, at the same positions, so log-probs, entropies and gradients are the same numbers (to
float rounding). The first token of each response is scored by the logits at the prompt's last
token, every other token by the logits just before it. Prompt columns read 0 in the result, as
when the engine skips prompt scoring.

The model sees one ordinary call (HF models take a prepared 4-D mask as-is), so every rank makes
the same FSDP collectives whatever its data. Models whose layers need their own masks (sliding
window attention) must not use this: :func:`supports_packed_masks` says which.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from infinirl.engines.logprobs import token_logprobs


@dataclass
class PackedBatch:
    """One micro-batch packed by prompt; every tensor is on the original batch's device."""

    input_ids: torch.Tensor  # [G, N]
    position_ids: torch.Tensor  # [G, N]
    attention_mask: torch.Tensor  # [G, 1, N, N] additive (0 = attend)
    predictor: torch.Tensor  # [S] flat index (g * N + i) of the logits that score each token below
    target: torch.Tensor  # [S] the scored token ids
    row: torch.Tensor  # [S] original row of each scored token
    column: torch.Tensor  # [S] original column of each scored token

    @property
    def first_predictor_column(self) -> int:
        """Earliest packed column any scored token reads logits from (the LM head runs from here)."""
        width = self.input_ids.shape[1]
        return int((self.predictor % width).min()) if self.predictor.numel() else width - 1


def pack_by_prompt(
    input_ids: torch.Tensor,
    attention_mask: torch.Tensor,
    position_ids: torch.Tensor | None,
    response_mask: torch.Tensor | None,
    mask_dtype: torch.dtype = torch.float32,
    max_packed_tokens: int = 2048,
) -> PackedBatch:
    """Pack ``[B, L]`` rows (aligned layout, :mod:`infinirl.data.batch`) by shared prompt.

    A row's prompt is its columns before its first response token (at least column 0, which is
    never scored; all of it for a row without response tokens); the rest up to its last attended
    column is its suffix, scored where attended.
    Rows share a prompt when prompt ids, mask and positions are all equal. Without a
    ``response_mask`` every row's suffix starts at column 1. Missing ``position_ids`` mean
    ``0..L-1``, as HF assumes. A packed row grows to at most ``max_packed_tokens`` (or one
    prompt plus one suffix, if longer): the mask is dense, so attention costs the square of a
    packed row's length, and past a point a second copy of the prompt is cheaper.
    """
    batch, width = input_ids.shape
    device = input_ids.device
    if position_ids is None:
        position_ids = torch.arange(width, device=device).expand(batch, width)
    ids, attn, pos = input_ids.cpu(), attention_mask.cpu().to(torch.bool), position_ids.cpu()
    positions = torch.arange(width)
    ends = torch.where(attn.any(dim=1), (positions * attn).argmax(dim=1) + 1, torch.ones(batch, dtype=torch.long))
    starts = torch.ones(batch, dtype=torch.long)
    if response_mask is not None:  # a row without response tokens is all prompt: nothing to score
        responds = response_mask.cpu().to(torch.bool)
        starts = torch.where(responds.any(dim=1), responds.to(torch.int8).argmax(dim=1), ends).clamp(min=1)
    starts = torch.minimum(starts, ends)

    groups: dict[bytes, list[int]] = {}
    for b in range(batch):
        s = int(starts[b])
        key = b"|".join(t[b, :s].numpy().tobytes() for t in (ids, attn, pos))
        groups.setdefault(key, []).append(b)

    packed_ids, packed_pos, packed_valid, packed_segment = [], [], [], []
    predictor, target, row, column = [], [], [], []
    for members in _split_long(groups.values(), starts, ends, max_packed_tokens):
        lead, s = members[0], int(starts[members[0]])
        seq_ids, seq_pos, seq_valid = [ids[lead, :s]], [pos[lead, :s]], [attn[lead, :s]]
        seq_seg = [torch.zeros(s, dtype=torch.long)]
        length = s
        for k, b in enumerate(members, start=1):
            e = int(ends[b])
            if e <= s:
                continue
            seq_ids.append(ids[b, s:e])
            seq_pos.append(pos[b, s:e])
            seq_valid.append(attn[b, s:e])
            seq_seg.append(torch.full((e - s,), k, dtype=torch.long))
            scored = attn[b, s:e].nonzero().squeeze(1)
            packed_at = length + scored
            prev = packed_at - 1
            prev[scored == 0] = s - 1  # first response token: scored by the prompt's last logits
            predictor.append((len(packed_ids), prev))  # flat index once the packed width is known
            target.append(ids[b, s + scored])
            row.append(torch.full_like(scored, b))
            column.append(s + scored)
            length += e - s
        packed_ids.append(torch.cat(seq_ids))
        packed_pos.append(torch.cat(seq_pos))
        packed_valid.append(torch.cat(seq_valid))
        packed_segment.append(torch.cat(seq_seg))

    n = max(len(t) for t in packed_ids)
    groups_count = len(packed_ids)
    pad = lambda t, value: torch.nn.functional.pad(t, (0, n - len(t)), value=value)  # noqa: E731
    input_packed = torch.stack([pad(t, 0) for t in packed_ids])
    pos_packed = torch.stack([pad(t, 0) for t in packed_pos])
    valid = torch.stack([pad(t.to(torch.long), 0) for t in packed_valid]).to(torch.bool)
    segment = torch.stack([pad(t, -1) for t in packed_segment])

    causal = torch.ones(n, n, dtype=torch.bool).tril()
    same_or_prompt = (segment.unsqueeze(2) == segment.unsqueeze(1)) | (segment.unsqueeze(1) == 0)
    allowed = causal & same_or_prompt & valid.unsqueeze(1)
    allowed |= torch.eye(n, dtype=torch.bool)  # no all-masked query row (pads attend to themselves)
    additive = torch.zeros(groups_count, 1, n, n, dtype=mask_dtype)
    additive.masked_fill_(~allowed.unsqueeze(1), torch.finfo(mask_dtype).min)

    flat_predictor = [prev + g * n for g, prev in predictor]
    empty = torch.zeros(0, dtype=torch.long)
    cat = lambda parts: torch.cat(parts) if parts else empty  # noqa: E731
    return PackedBatch(
        input_ids=input_packed.to(device),
        position_ids=pos_packed.to(device),
        attention_mask=additive.to(device),
        predictor=cat(flat_predictor).to(device),
        target=cat(target).to(device),
        row=cat(row).to(device),
        column=cat(column).to(device),
    )


def _split_long(groups, starts: torch.Tensor, ends: torch.Tensor, max_tokens: int):
    """Each group's rows, cut into runs whose prompt plus suffixes fit ``max_tokens`` (>= 1 row each)."""
    for members in groups:
        prompt = int(starts[members[0]])
        run, length = [], prompt
        for b in members:
            suffix = max(0, int(ends[b]) - prompt)
            if run and length + suffix > max_tokens:
                yield run
                run, length = [], prompt
            run.append(b)
            length += suffix
        yield run


def packed_logprobs(
    model: torch.nn.Module,
    packed: PackedBatch,
    shape: tuple[int, int],
    temperature: float,
    chunk_tokens: int,
    with_entropy: bool,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Aligned ``[B, L]`` (``shape``) log-probs and entropies of every scored token: one model call."""
    groups, width = packed.input_ids.shape
    first = packed.first_predictor_column
    out = model(
        input_ids=packed.input_ids,
        attention_mask=packed.attention_mask,
        position_ids=packed.position_ids,
        use_cache=False,
        logits_to_keep=width - first,
    )
    logits = out.logits
    if logits.shape[1] == width and first > 0:  # a model that ignores logits_to_keep
        logits = logits[:, first:]
    kept = logits.shape[1]
    index = (packed.predictor // width) * kept + packed.predictor % width - (width - kept)
    rows = logits.reshape(groups * kept, -1).index_select(0, index)  # [S, V]: only scored tokens
    lp, ent = token_logprobs(rows, packed.target, temperature, chunk_tokens, with_entropy)
    base = lp.new_zeros(shape)
    if not packed.target.numel():  # nothing scored (a filler pass): stay on the graph for FSDP's backward
        base = base + logits.float().sum() * 0.0
    logprobs = base.index_put((packed.row, packed.column), lp)
    entropy = ent.new_zeros(shape).index_put((packed.row, packed.column), ent) if with_entropy else None
    return logprobs, entropy


def supports_packed_masks(config) -> bool:
    """False for models with sliding-window layers, whose attention builds its own windowed mask
    (a prepared 4-D mask would silently drop the window), and for attention kernels that take no
    dense mask (flash-attention, flex): only ``sdpa`` and ``eager`` apply it as given."""
    kernel = getattr(config, "_attn_implementation", None)
    if kernel not in (None, "sdpa", "eager"):
        return False
    layer_types = getattr(config, "layer_types", None) or []
    if any("sliding" in str(kind) for kind in layer_types):
        return False
    window = getattr(config, "sliding_window", None)
    return not (window and getattr(config, "use_sliding_window", True))
