"""Every link to a heading of the docs resolves: the README's and docs/*.md's markdown links
(`[text](file.md#anchor)`, `[text](#anchor)`) and the shipped configs' pointers
(`docs/file.md#anchor` in a YAML comment). A heading renamed without its links leaves readers on
the top of a long page (docs/results.md is thousands of lines), so a dead anchor fails here."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
CONFIGS = ROOT / "infinirl" / "configs"

_FENCE = re.compile(r"^\s*(```|~~~)")
_HEADING = re.compile(r"^ {0,3}(#{1,6})\s+(.*?)\s*#*\s*$")
_HTML_ANCHOR = re.compile(r"""<a\s+(?:name|id)\s*=\s*["']([^"']+)["']""")
_MD_LINK = re.compile(r"\]\(\s*([^)\s]*)\s*(?:\"[^\"]*\")?\)")
_CONFIG_LINK = re.compile(r"(docs/[\w./-]+\.md)#([\w-]+)")


def github_slug(heading: str) -> str:
    """GitHub's anchor for a heading's text (github-slugger): the rendered text, lower-cased, with
    every character that is not a letter, digit, underscore, hyphen or space removed, then each
    space a hyphen (runs of hyphens are kept)."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link renders as its text
    text = re.sub(r"<[^>]+>", "", text)  # inline HTML renders as nothing here
    text = text.replace("`", "").replace("*", "")
    text = text.lower()
    text = "".join(ch for ch in text if ch.isalnum() or ch in "_- ")
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """The anchors of a markdown file: its headings' slugs (a repeated one gets -1, -2, ... as on
    GitHub) and explicit `<a name=...>` / `<a id=...>` anchors; headings in code blocks do not count."""
    seen: dict[str, int] = {}
    found: set[str] = set()
    fenced = False
    for line in path.read_text(encoding="utf-8").splitlines():
        if _FENCE.match(line):
            fenced = not fenced
            continue
        if fenced:
            continue
        found.update(_HTML_ANCHOR.findall(line))
        match = _HEADING.match(line)
        if not match:
            continue
        slug = github_slug(match.group(2))
        count = seen.get(slug, 0)
        seen[slug] = count + 1
        found.add(slug if count == 0 else f"{slug}-{count}")
    return found


def markdown_links(path: Path) -> list[tuple[int, Path, str]]:
    """(line, target file, anchor) of every link with an anchor to a markdown file in the repository."""
    links = []
    fenced = False
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if _FENCE.match(line):
            fenced = not fenced
            continue
        if fenced:
            continue
        for target in _MD_LINK.findall(line):
            if "#" not in target or "://" in target:
                continue
            file_part, anchor = target.split("#", 1)
            if file_part and not file_part.endswith(".md"):
                continue
            links.append((number, (path.parent / file_part).resolve() if file_part else path, anchor))
    return links


def config_links(path: Path) -> list[tuple[int, Path, str]]:
    links = []
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        for file_part, anchor in _CONFIG_LINK.findall(line):
            links.append((number, ROOT / file_part, anchor))
    return links


def _dead(links_by_source: dict[Path, list[tuple[int, Path, str]]], root: Path = ROOT) -> list[str]:
    cache: dict[Path, set[str]] = {}
    dead = []
    for source, links in links_by_source.items():
        for number, target, anchor in links:
            where = f"{source.relative_to(root)}:{number}"
            if not target.is_file():
                dead.append(f"{where}: {target} does not exist")
                continue
            if target not in cache:
                cache[target] = anchors(target)
            if anchor not in cache[target]:
                dead.append(f"{where}: no heading of {target.relative_to(root)} has the anchor #{anchor}")
    return dead


@pytest.mark.parametrize(("heading", "slug"), [
    ("PPO in LIBERO", "ppo-in-libero"),
    ("Cost model (`scheduler/cost.py`)", "cost-model-schedulercostpy"),
    ("Threads (`actor.num_threads` / `rollout.num_threads`)", "threads-actornum_threads--rolloutnum_threads"),
    ("SFT then RL of the small VLA on three MetaWorld tasks", "sft-then-rl-of-the-small-vla-on-three-metaworld-tasks"),
    ("PPO on a π0 checkpoint", "ppo-on-a-π0-checkpoint"),
    ("See [runtime](runtime.md): 1.5x", "see-runtime-15x"),
])
def test_the_slug_follows_githubs_rules(heading, slug):
    assert github_slug(heading) == slug


def test_a_repeated_heading_gets_a_numbered_anchor_and_code_blocks_hold_none(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("# Results\n\n## Setup\n\n```\n## Not a heading\n```\n\n## Setup\n")
    assert anchors(page) == {"results", "setup", "setup-1"}


def test_a_dead_anchor_is_reported_with_its_file_and_line(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("# Title\n\nsee [there](#title) and [gone](#nowhere)\n")
    assert _dead({page: markdown_links(page)}, root=tmp_path) == [
        "page.md:3: no heading of page.md has the anchor #nowhere"]


def test_every_heading_link_in_the_docs_resolves():
    pages = [ROOT / "README.md", *sorted(DOCS.glob("*.md"))]
    assert _dead({page: markdown_links(page) for page in pages}) == []


def test_every_docs_link_in_the_shipped_configs_resolves():
    configs = sorted(CONFIGS.glob("*.yaml"))
    assert configs
    assert _dead({config: config_links(config) for config in configs}) == []
