"""BM25 against a slow float64 reference, the search tool's answers and bounds, and its config."""

import asyncio
import math
import random
from collections import Counter

import numpy as np
import pytest

from infinirl.agents.search import CORPORA, BM25Index, SearchTool, corpus_index, tokenize
from infinirl.agents.tool_env import ToolEnv
from infinirl.agents.tools import TOOLS, call_tool, make_tool
from infinirl.cli import main
from infinirl.tasks.fictional_kb import KBConfig, build_kb

TOY = [
    "The cat sat on the mat.",
    "A dog and a cat: the dog barked, the cat ran.",
    "",
    "Dogs dogs dogs everywhere, dog!",
    "Mat makers make mats; the MAT is red.",
    "Nothing in common here",
]


def reference_scores(documents, query, k1=1.5, b=0.75):
    """BM25 written out term by term with math.log, one document at a time."""
    docs = [tokenize(d) for d in documents]
    n = len(docs)
    average = sum(len(d) for d in docs) / n or 1.0
    scores = []
    for doc in docs:
        total = 0.0
        for term in tokenize(query):
            holding = sum(term in other for other in docs)
            tf = doc.count(term)
            if tf == 0:
                continue
            idf = math.log(1 + (n - holding + 0.5) / (holding + 0.5))
            total += idf * tf * (k1 + 1) / (tf + k1 * (1 - b + b * len(doc) / average))
        scores.append(total)
    return scores


@pytest.mark.parametrize(("k1", "b"), [(1.5, 0.75), (0.9, 0.4), (0.0, 1.0), (2.0, 0.0)])
def test_bm25_matches_the_reference_formula(k1, b):
    index = BM25Index(TOY, k1=k1, b=b)
    rng = random.Random(0)
    vocabulary = sorted({t for d in TOY for t in tokenize(d)}) + ["absent", "words"]
    queries = ["cat", "the dog", "dog dog", "mat red", "nothing", "absent", ""]
    queries += [" ".join(rng.choices(vocabulary, k=rng.randint(1, 6))) for _ in range(40)]
    for query in queries:
        np.testing.assert_allclose(index.scores(query), reference_scores(TOY, query, k1, b), rtol=1e-12, atol=0)


def test_search_ranks_by_score_then_document_order_and_drops_zero_scores():
    index = BM25Index(["alpha beta", "beta alpha", "gamma", "alpha"])
    hits = index.search("alpha beta", k=10)
    assert [i for i, _ in hits] == [0, 1, 3]  # 0 and 1 tie: document order
    assert hits[0][1] == hits[1][1] > hits[2][1] > 0
    assert index.search("alpha beta", k=1) == hits[:1]
    assert index.search("zeta", k=3) == []
    scores = index.scores("gamma alpha")
    order = [i for i, _ in index.search("gamma alpha", k=4)]
    assert order == sorted(np.flatnonzero(scores > 0), key=lambda i: (-scores[i], i))
    with pytest.raises(ValueError, match="k=0"):
        index.search("alpha", k=0)


def test_bm25_rejects_bad_input():
    with pytest.raises(ValueError, match="at least one document"):
        BM25Index([])
    with pytest.raises(ValueError, match="k1"):
        BM25Index(["a"], b=1.5)


def test_the_search_tool_is_registered_and_finds_a_persons_passage():
    assert "search" in TOOLS
    kb = build_kb(KBConfig())
    tool = make_tool("search", k=2)
    for person in list(kb.people.values())[:40]:
        first = tool.lookup(person.name).splitlines()[0]
        assert first.startswith(f"{person.name} is ") and person.city in first
    result = asyncio.run(call_tool(tool, {"query": "Who founded " + next(iter(kb.companies)) + "?"}))
    assert result.ok and next(iter(kb.companies.values())).founder in result.text


def test_tool_output_is_bounded_and_says_when_nothing_matches():
    rng = random.Random(1)
    words = [t for d in build_kb(KBConfig()).passages() for t in tokenize(d)]
    for max_chars, k in [(16, 5), (100, 3), (300, 2), (5000, 10)]:
        tool = SearchTool(k=k, max_chars=max_chars)
        for _ in range(30):
            text = tool.lookup(" ".join(rng.choices(words, k=rng.randint(1, 12))))
            assert len(text) <= max_chars
            assert len(text.splitlines()) <= k
    long_passages = SearchTool(k=3, max_chars=40).lookup("company founded")
    assert len(long_passages) == 40 and long_passages.endswith("...")
    assert SearchTool().lookup("qqqq zzzz") == SearchTool.NO_HITS
    assert SearchTool().lookup("") == SearchTool.NO_HITS


def test_the_index_is_rebuilt_from_options_and_shared_within_a_process():
    a = SearchTool(corpus_options={"seed": 3, "people": 20, "companies": 5})
    b = SearchTool(corpus_options={"companies": 5, "people": 20, "seed": 3})
    assert a.index is b.index
    assert a.index is not SearchTool(corpus_options={"seed": 4, "people": 20, "companies": 5}).index
    assert list(a.index.documents) == build_kb(KBConfig(seed=3, people=20, companies=5)).passages()
    assert corpus_index("fictional_kb", {"seed": 3, "people": 20, "companies": 5}) is a.index
    assert "fictional_kb" in CORPORA


def test_bad_tool_options_are_one_line_errors():
    with pytest.raises(ValueError, match="k=0"):
        SearchTool(k=0)
    with pytest.raises(ValueError, match="max_chars"):
        SearchTool(max_chars=3)
    with pytest.raises(ValueError, match=r"kb options \['peeple'\]"):
        SearchTool(corpus_options={"peeple": 3})
    with pytest.raises(KeyError, match="unknown search corpus 'wiki'"):
        SearchTool(corpus="wiki")


def test_the_tools_env_runs_tag_format_searches():
    kb = build_kb(KBConfig())
    person = next(iter(kb.people.values()))
    env = ToolEnv(tools=["search"], tool_options={"search": {"k": 1}})
    assert env.stop_strings == ("</search>",)
    step = env.step(f"<search>{person.name}</search>")
    assert not step.error and not step.done and person.city in step.observation
    assert step.observation.startswith("<result>\n") and len(step.observation.splitlines()) == 3
    assert env.step("<answer>x</answer>").done
    assert env.step("<search></search>").error


def test_the_config_validates_and_bad_kb_options_are_config_errors(capsys):
    assert main(["validate", "grpo_search_agent"]) == 0
    assert main(["validate", "grpo_search_agent", "task.config.kb.people=0"]) == 2
    assert "kb.people=0" in capsys.readouterr().err


def test_the_config_prompts_fit_and_every_passage_fits_the_observation_budget():
    from infinirl.config import compose
    from infinirl.models.hf_causal_lm import resolve_model_source
    from infinirl.tasks.config import TaskConfig
    from infinirl.tasks.prompts import encode_prompt
    from infinirl.tasks.sources import eval_problems

    transformers = pytest.importorskip("transformers")
    raw = compose("grpo_search_agent")
    tokenizer = transformers.AutoTokenizer.from_pretrained(resolve_model_source(raw["model"]["path"]))
    task = TaskConfig(**raw["task"])
    problems = eval_problems(task, "test", None) + eval_problems(task, "train", None)
    longest = max(len(encode_prompt(p, tokenizer, task.system_prompt, few_shot=task.few_shot)) for p in problems)
    assert longest <= raw["rollout"]["max_prompt_length"]
    options = raw["rollout"]["agent"]["env_options"]["tool_options"]["search"]
    assert options["corpus_options"] == raw["task"]["config"]["kb"]
    tool = SearchTool(**options)
    budget = raw["rollout"]["agent"]["max_observation_tokens"]
    counts = Counter(p.metadata["kind"] for p in problems)
    assert set(counts) == set(raw["task"]["config"]["kinds"])
    for problem in problems[::7]:
        observation = f"<result>\n{tool.lookup(problem.prompt)}\n</result>\n"
        assert len(tokenizer.encode(observation, add_special_tokens=False)) <= budget
