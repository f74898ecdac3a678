"""docs/results.md's own rule: every entry names the command that measured it (a `Command:` line,
or the command written into its text), or says "Command: not recorded" where it cannot be
established; a number without it cannot be reproduced or checked."""

import re
from pathlib import Path

RESULTS = Path(__file__).resolve().parents[2] / "docs" / "results.md"

# "Command" (given, a scratch script, or not recorded), or a command quoted in the entry's text.
_PROVENANCE = re.compile(r"Command|`(?:time |[A-Z_]+=\S+ )?(?:python|infinirl|pytest|bash) ")


def entries_without_a_command(text: str) -> list[str]:
    """The `###` entries (with their `####` parts) that name no command; `##` sections group entries."""
    lines = text.splitlines()
    starts = [i for i, line in enumerate(lines) if re.match(r"#{2,3} ", line)] + [len(lines)]
    return [lines[a] for a, b in zip(starts, starts[1:])
            if lines[a].startswith("### ") and not _PROVENANCE.search("\n".join(lines[a + 1:b]))]


def test_an_entry_without_a_command_is_found():
    text = ("## Section\n\nIntro.\n\n### Measured\n\nCommand: `infinirl train x`.\n\n"
            "### Timed by hand\n\nHost: `cpu-vm`. 6.5 ms.\n\n### Inline\n\n`python benchmarks/b.py`: 1.2x\n")
    assert entries_without_a_command(text) == ["### Timed by hand"]


def test_every_results_entry_names_its_command_or_says_it_was_not_recorded():
    assert entries_without_a_command(RESULTS.read_text(encoding="utf-8")) == []
