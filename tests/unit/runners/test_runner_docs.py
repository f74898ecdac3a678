"""The README's promise about the shared keys and output (iterations, eval.every, save_every,
resume, checkpoints, curves) names the runners it holds for: exactly those whose config is a
RunConfig, driven by the shared run loop. A new runner outside it (like runtime_demo) must be
named as an exception there, not silently covered by the promise."""

import re
from pathlib import Path

from infinirl.runners import load_runners
from infinirl.runners.run_config import RunConfig

README = (Path(__file__).resolve().parents[3] / "README.md").read_text(encoding="utf-8")


def test_the_readme_names_exactly_the_runners_on_the_shared_run_loop():
    sentence = re.search(r"the (\w+) runners on the shared run loop \(([^)]*)\)", README)
    assert sentence, "README: the sentence naming the runners on the shared run loop is gone"
    named = set(re.findall(r"`(\w+)`", sentence.group(2)))
    runners = load_runners()
    specs = [runners.get(name) for name in runners.names()]
    on_the_loop = {spec.name for spec in specs if issubclass(spec.config_cls, RunConfig)}
    assert named == on_the_loop
    words = {4: "four", 5: "five", 6: "six", 7: "seven", 8: "eight"}
    assert sentence.group(1) == words.get(len(named))
    # the others are named as exceptions in the same paragraph
    paragraph = README[sentence.start():].split("\n\n", 1)[0]
    for outside in {spec.name for spec in specs} - on_the_loop:
        assert f"`{outside}`" in paragraph or f"`infinirl {outside}`" in paragraph, outside
