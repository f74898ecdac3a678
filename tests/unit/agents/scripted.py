"""An engine that writes given turns, for agent-loop tests that need a turn's exact text or ids
(what a model would sample there, e.g. a token that runs past a stop string)."""

from infinirl.engines.base import GenerationResult


class ScriptedEngine:
    """Writes the given turns in order, one per generate call, for every prompt of the call: text
    (encoded) or token ids. A turn longer than the call's ``max_new_tokens`` is cut there, with
    finish reason ``length``, as an engine would. ``calls`` records each call's prompts and sampling."""

    def __init__(self, tokenizer, turns):
        self.tokenizer, self.turns, self.calls = tokenizer, list(turns), []

    def generate(self, prompts, sampling):
        self.calls.append(([list(p) for p in prompts], sampling))
        turn = self.turns.pop(0)
        ids = self.tokenizer.encode(turn, add_special_tokens=False) if isinstance(turn, str) else list(turn)
        finish = "length" if len(ids) > sampling.max_new_tokens else "stop"
        ids = ids[:sampling.max_new_tokens]
        return [GenerationResult(prompt_ids=list(p), response_ids=ids, response_logprobs=[-0.5] * len(ids),
                                 finish_reason=finish, weight_version=0) for p in prompts]
