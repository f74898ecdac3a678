"""The generated knowledge base: determinism across processes, questions that need the passages,
and a held-out split that shares no entity named in a question."""

import hashlib
import json
import os
import subprocess
import sys

import pytest

from infinirl.config import ConfigError
from infinirl.tasks.config import TaskConfig
from infinirl.tasks.datasets import EpochBatchIterator
from infinirl.tasks.fictional_kb import (
    QUESTION_KINDS,
    KBConfig,
    build_kb,
    kb_documents,
    kb_problems,
    kb_split,
)
from infinirl.tasks.problem import normalize_question
from infinirl.tasks.sources import TASK_SOURCES, eval_problems, training_problems, verifier_for

DIGEST = ("import hashlib, json; from infinirl.tasks.fictional_kb import kb_documents; "
          "print(hashlib.sha256(json.dumps(kb_documents(seed=5)).encode()).hexdigest())")


def task(**config):
    return TaskConfig(source="fictional_kb", name="fictional_kb", config=config, verifier="exact_match", eval_size=32)


def test_the_world_is_a_function_of_its_config_in_every_process():
    assert build_kb(KBConfig(seed=5)) == build_kb(KBConfig(seed=5))
    assert kb_documents(seed=5) != kb_documents(seed=6)
    here = hashlib.sha256(json.dumps(kb_documents(seed=5)).encode()).hexdigest()
    for hash_seed in ("1", "2"):  # str hashing differs between these processes; the world must not
        env = {**os.environ, "PYTHONHASHSEED": hash_seed}
        there = subprocess.run([sys.executable, "-c", DIGEST], env=env, capture_output=True, text=True, check=True)
        assert there.stdout.strip() == here


def test_sizes_and_unique_names():
    config = KBConfig(seed=1, countries=5, cities_per_country=3, companies=12, people=50)
    kb = build_kb(config)
    assert (len(kb.countries), len(kb.cities), len(kb.companies), len(kb.people)) == (5, 15, 12, 50)
    assert len(kb.passages()) == 5 + 15 + 12 + 50
    words = [w.lower() for w in [*kb.countries, *kb.cities, *kb.companies] for w in w.split()[:1]]
    assert len(words) == len(set(words))
    assert len({p.name.split()[1] for p in kb.people.values()}) == 50  # surnames identify people
    assert len({c.founder for c in kb.companies.values()}) == 12
    for country in kb.countries.values():
        assert kb.cities[country.capital] == country.name
    for company in kb.companies.values():
        assert 20 <= company.founded - kb.people[company.founder].born <= 60 and company.founded <= 2020


def test_bad_kb_options_name_the_key():
    with pytest.raises(ValueError, match=r"kb options \['size'\] are unknown"):
        KBConfig.from_options({"size": 3})
    with pytest.raises(ValueError, match="kb.people=0"):
        KBConfig(people=0)
    with pytest.raises(ValueError, match="kb.companies=9 > kb.people=3"):
        KBConfig(people=3, companies=9)
    with pytest.raises(ValueError, match="kb.seed"):
        KBConfig(seed=1.5)


def own_passage(kb, subject):
    return next(p for p in kb.passages() if p.startswith(f"{subject} is "))


def test_one_lookup_answers_one_hop_questions_and_two_hop_ones_need_two():
    kb = build_kb(KBConfig())
    problems = kb_problems(kb, list(QUESTION_KINDS), frozenset(), "train")
    assert {p.metadata["kind"] for p in problems} == set(QUESTION_KINDS)
    for problem in problems:
        subject, hops = problem.metadata["subject"], problem.metadata["hops"]
        assert subject in problem.prompt and problem.answer
        passage = own_passage(kb, subject)
        if hops == 1:
            assert problem.answer in passage, problem
        elif problem.answer != subject:  # a founder may work for their own company
            assert problem.answer not in passage, problem
            bridge = [e for e in [*kb.cities, *kb.companies, *kb.people] if e in passage and e != subject]
            assert any(problem.answer in own_passage(kb, e) for e in bridge), problem


def test_held_out_questions_name_entities_no_training_question_names():
    kb = build_kb(KBConfig())
    held = kb_split(kb, 0.25, seed=3)
    assert held == kb_split(kb, 0.25, seed=3) and held != kb_split(kb, 0.25, seed=4)
    assert len(held & set(kb.people)) == 40 and len(held & set(kb.countries)) == 2
    train = kb_problems(kb, list(QUESTION_KINDS), held, "train")
    test = kb_problems(kb, list(QUESTION_KINDS), held, "test")
    assert train and test
    assert all(p.metadata["subject"] in held for p in test)
    assert not any(p.metadata["subject"] in held for p in train)
    train_text = " ".join(p.prompt for p in train)
    assert not any(p.metadata["subject"] in train_text for p in test)
    assert not {normalize_question(p.prompt) for p in train} & {normalize_question(p.prompt) for p in test}
    with pytest.raises(ValueError, match="heldout_fraction=1.0"):
        kb_split(kb, 1.0, seed=0)
    with pytest.raises(ValueError, match="split='dev'"):
        kb_problems(kb, ["capital"], held, "dev")


def test_the_task_source_trains_and_evaluates_on_disjoint_problems():
    assert "fictional_kb" in TASK_SOURCES
    config = {"kb": {"seed": 2}, "kinds": ["birth_city", "birth_country"], "heldout_fraction": 0.2}
    stream, held_out = training_problems(task(**config), seed=0)
    assert isinstance(stream, EpochBatchIterator) and len(held_out) == 32
    assert {p.metadata["kind"] for p in held_out} <= {"birth_city", "birth_country"}
    assert held_out == eval_problems(task(**config), "test", None)
    assert eval_problems(task(**config), "test", 5) == held_out[:5]
    held_subjects = {p.metadata["subject"] for p in held_out}
    drawn = stream.next_batch(200)
    assert not {p.metadata["subject"] for p in drawn} & held_subjects
    assert all(p.verifier == "exact_match" for p in drawn + held_out)
    assert {p.uid for p in eval_problems(task(**config), "train", None)} == {p.uid for p in stream.items}
    assert verifier_for(task(**config), "test") == "exact_match"
    assert verifier_for(TaskConfig(source="fictional_kb"), "test") == "exact_match"  # not the reasoning_gym default


def test_bad_task_config_is_a_config_error_naming_the_key():
    with pytest.raises(ConfigError, match="task.config keys \\['hops'\\]"):
        training_problems(task(hops=2), seed=0)
    with pytest.raises(ConfigError, match="unknown question kinds \\['age'\\]"):
        training_problems(task(kinds=["age"]), seed=0)
    with pytest.raises(ConfigError, match="task.config.kb: kb.people=0"):
        training_problems(task(kb={"people": 0}), seed=0)
    with pytest.raises(ConfigError, match="task.eval_size=32 but .* holds out only"):
        training_problems(task(kinds=["capital"]), seed=0)
    with pytest.raises(ConfigError, match="split='dev'"):
        eval_problems(task(), "dev", None)
