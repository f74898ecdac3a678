"""Stop strings: found in a growing response by decoding only its tail."""

from __future__ import annotations

from collections.abc import Sequence

__all__ = ["StopStringMatcher"]


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
