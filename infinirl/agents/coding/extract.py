"""Which code of a model's text is its answer.

The rule (:func:`extract_code`):

1. Fenced blocks: every block opened by a line starting with three backticks and a language tag
   that is empty, ``python``, ``py`` or ``python3`` (other tags, e.g. ``text`` or ``bash``, are not
   code to run), closed by a line starting with three backticks or by the end of the text (an
   answer cut at its token budget). With an ``entry_point``, the last block defining
   ``def <entry_point>(`` is the code; otherwise the last block.
2. No such block: the whole text.
3. Completion: when the code does not define ``entry_point`` and the problem has a stub (signature
   and docstring), the code is taken as the function's body and appended to the stub (indented by
   four spaces when its first line is not indented), as HumanEval's completion format reads it.
4. When the code does define ``entry_point``, whatever the stub declares before that function
   (imports, helper functions) is put in front of it, so an answer that uses ``List`` or a helper
   the stub gave need not repeat them; the answer's own definitions come later and win in the code
   (its ``from __future__`` imports move to the top). The tests never call the answer's versions of
   the stub's helpers: the harness defines the stub's own in the tests' process.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

__all__ = ["CODE_LANGUAGES", "ExtractedCode", "code_blocks", "defines", "extract_code", "stub_preamble"]

CODE_LANGUAGES = frozenset({"", "python", "py", "python3"})
_FENCE = re.compile(r"^[ \t]*```", re.M)
_OPEN = re.compile(r"```[ \t]*([A-Za-z0-9_+.-]*)[^\n]*\n")
_FUTURE = re.compile(r"^from[ \t]+__future__[ \t]+import[^\n]*\n?", re.M)


@dataclass(kw_only=True, frozen=True)
class ExtractedCode:
    code: str
    """The program to run (with the stub's preamble or the stub itself in front, see the rule)."""
    fenced: bool
    """It came from a fenced block (else from the whole text)."""
    completed_stub: bool
    """The text was a function body appended to the problem's stub."""


def code_blocks(text: str) -> list[tuple[str, str, bool]]:
    """``(language, body, closed)`` of each fenced block, in order; the last may be unclosed."""
    blocks = []
    position = 0
    while True:
        opening = _FENCE.search(text, position)
        if opening is None:
            return blocks
        header = _OPEN.match(text, opening.end() - 3)
        if header is None:  # a fence with nothing after it on the text's last line
            return blocks
        closing = _FENCE.search(text, header.end())
        if closing is None:
            blocks.append((header.group(1).lower(), text[header.end():], False))
            return blocks
        body = text[header.end():closing.start()]
        blocks.append((header.group(1).lower(), body, True))
        line_end = text.find("\n", closing.end())
        position = len(text) if line_end < 0 else line_end + 1


def defines(code: str, name: str) -> bool:
    """Whether ``code`` has a line ``def <name>(`` (at any indentation: a method counts too)."""
    return re.search(rf"^[ \t]*(?:async[ \t]+)?def[ \t]+{re.escape(name)}[ \t]*\(", code, re.M) is not None


def stub_preamble(stub: str, entry_point: str) -> str:
    """What ``stub`` declares before ``def <entry_point>(`` (imports, helpers); "" if it has no such line."""
    match = re.search(rf"^(?:async[ \t]+)?def[ \t]+{re.escape(entry_point)}[ \t]*\(", stub, re.M)
    return stub[:match.start()] if match else ""


def extract_code(text: str, entry_point: str | None = None, stub: str | None = None) -> ExtractedCode | None:
    """The code of ``text`` by the module's rule; None when there is none (blank text)."""
    blocks = [body for language, body, _ in code_blocks(text) if language in CODE_LANGUAGES]
    if blocks:
        defining = [b for b in blocks if entry_point and defines(b, entry_point)]
        code, fenced = (defining or blocks)[-1], True
    else:
        code, fenced = text, False
    if not code.strip():
        return None
    if not entry_point or not stub:
        return ExtractedCode(code=code, fenced=fenced, completed_stub=False)
    if defines(code, entry_point):
        preamble = stub_preamble(stub, entry_point)
        if preamble.strip():  # __future__ imports must stay first
            futures = "".join(line if line.endswith("\n") else line + "\n" for line in _FUTURE.findall(code))
            code = futures + preamble + _FUTURE.sub("", code)
        return ExtractedCode(code=code, fenced=fenced, completed_stub=False)
    body = code.strip("\n")
    if not body[:1].isspace():
        body = "\n".join("    " + line if line.strip() else line for line in body.splitlines())
    return ExtractedCode(code=f"{stub.rstrip()}\n{body}\n", fenced=fenced, completed_stub=True)
