"""A generated knowledge base of fictional entities, its passages, and questions about it.

Facts a model cannot know from pre-training: countries, cities, companies and people with made-up
names and attributes, all a pure function of :class:`KBConfig` (its ``seed`` and sizes), so every
process (the driver, rollout workers running the ``search`` tool) rebuilds the same base. Each
entity is rendered as one short passage (the retrieval corpus, :func:`kb_documents`); questions
need one lookup ("In which city was X born?") or two ("In which country was X born?": X's passage
names the city, the city's passage names the country), and carry their gold answer.

Held-out split by *subject*: a seeded share of every entity kind is held out, and a question belongs
to the held-out set exactly when the entity it names is held out, so no training question names a
held-out entity (and no question text is shared). The intermediate entities of two-hop questions
(a city, a company) may appear in both splits: the corpus is one world.

Task source ``fictional_kb`` (``task.source: fictional_kb``; ``task.config``: ``kb`` (KBConfig
fields), ``kinds`` (question kinds, default all), ``heldout_fraction``), scored by the
``exact_match`` verifier (:mod:`infinirl.tasks.exact_match`).
"""

from __future__ import annotations

import random
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields
from functools import lru_cache
from typing import Any

from infinirl.config import ConfigError
from infinirl.tasks.config import TaskConfig
from infinirl.tasks.problem import Problem, normalize_question
from infinirl.tasks.sources import TASK_SOURCES, TaskSource

__all__ = [
    "QUESTION_KINDS",
    "Company",
    "Country",
    "KBConfig",
    "KnowledgeBase",
    "Person",
    "QuestionKind",
    "build_kb",
    "kb_documents",
    "kb_problems",
    "kb_split",
]

ONSETS = ("b", "br", "d", "dr", "f", "g", "gr", "k", "kr", "l", "m", "n", "p", "r", "s", "st", "t", "th", "v", "z")
VOWELS = ("a", "e", "i", "o", "u", "ae", "ei", "ou")
CODAS = ("", "", "", "n", "r", "l", "s", "th", "m", "nd", "rk")
COUNTRY_ENDINGS = ("ia", "land", "istan", "ora", "ary")
COMPANY_ENDINGS = ("Industries", "Labs", "Works", "Systems", "Trading", "Foods", "Motors", "Media")
INDUSTRIES = ("shipping", "software", "mining", "textile", "food", "aviation", "banking", "toy", "glass", "energy")
OCCUPATIONS = ("painter", "engineer", "farmer", "doctor", "teacher", "pilot", "chemist", "architect", "poet",
               "sailor", "lawyer", "baker", "composer", "astronomer", "carpenter")
FIRST_YEAR, LAST_YEAR = 1900, 1999  # birth years
LAST_FOUNDED = 2020  # companies are founded 20 to 60 years after their founder's birth, by this year


@dataclass(kw_only=True, frozen=True)
class KBConfig:
    """How big the generated world is; everything in it follows from these fields."""

    seed: int = 0
    countries: int = 8
    cities_per_country: int = 4
    companies: int = 40
    people: int = 160

    def __post_init__(self) -> None:
        for item in fields(self):
            value = getattr(self, item.name)
            if not isinstance(value, int) or isinstance(value, bool):
                raise ValueError(f"kb.{item.name}={value!r}: must be an integer")
            if item.name != "seed" and value < 1:
                raise ValueError(f"kb.{item.name}={value}: must be >= 1")
        if self.companies > self.people:
            raise ValueError(f"kb.companies={self.companies} > kb.people={self.people}: every company needs a "
                             "distinct founder; add people or remove companies")

    @classmethod
    def from_options(cls, options: Mapping[str, Any] | None) -> KBConfig:
        """From a config mapping; an unknown key is an error naming the known ones."""
        options = dict(options or {})
        known = {item.name for item in fields(cls)}
        unknown = sorted(set(options) - known)
        if unknown:
            raise ValueError(f"kb options {unknown} are unknown; known: {sorted(known)}")
        return cls(**options)


@dataclass(kw_only=True, frozen=True)
class Country:
    name: str
    capital: str
    currency: str


@dataclass(kw_only=True, frozen=True)
class Company:
    name: str
    industry: str
    founder: str
    founded: int
    city: str


@dataclass(kw_only=True, frozen=True)
class Person:
    name: str
    occupation: str
    city: str
    born: int
    employer: str


@dataclass(kw_only=True, frozen=True)
class KnowledgeBase:
    """The generated world: entities by name, in generation order."""

    countries: dict[str, Country]
    cities: dict[str, str]  # city -> its country
    companies: dict[str, Company]
    people: dict[str, Person]

    def passages(self) -> list[str]:
        """One passage per entity: countries, cities, companies, people, each in generation order."""
        texts = [f"{c.name} is a country. Its capital is {c.capital} and its currency is the {c.currency}."
                 for c in self.countries.values()]
        texts += [f"{city} is a city in {country}." for city, country in self.cities.items()]
        texts += [f"{c.name} is {article(c.industry)} {c.industry} company founded by {c.founder} in {c.founded}. "
                  f"Its headquarters are in {c.city}." for c in self.companies.values()]
        texts += [f"{p.name} is {article(p.occupation)} {p.occupation} who was born in {p.city} in {p.born}. "
                  f"{p.name} works for {p.employer}." for p in self.people.values()]
        return texts


def article(word: str) -> str:
    return "an" if word[0] in "aeiou" else "a"


class NameMaker:
    """Pronounceable made-up words, never the same word twice in one world."""

    def __init__(self, rng: random.Random):
        self.rng, self.used = rng, set()

    def word(self, syllables: tuple[int, int] = (2, 3)) -> str:
        for _ in range(10_000):
            count = self.rng.randint(*syllables)
            text = "".join(self.rng.choice(ONSETS) + self.rng.choice(VOWELS) for _ in range(count))
            text = (text + self.rng.choice(CODAS)).capitalize()
            if text.lower() not in self.used:
                self.used.add(text.lower())
                return text
        raise RuntimeError("name space exhausted; make the knowledge base smaller")


def build_kb(config: KBConfig) -> KnowledgeBase:
    """The world of ``config``: the same in every process (``random.Random`` seeded by an int)."""
    rng = random.Random(config.seed)
    names = NameMaker(rng)
    countries: dict[str, Country] = {}
    cities: dict[str, str] = {}
    for _ in range(config.countries):
        country = names.word((2, 2)) + rng.choice(COUNTRY_ENDINGS)
        own = [names.word() for _ in range(config.cities_per_country)]
        cities.update((city, country) for city in own)
        countries[country] = Country(name=country, capital=rng.choice(own), currency=names.word((2, 2)).lower())
    city_names = list(cities)
    first_names = [names.word((1, 2)) for _ in range(max(8, config.people // 4))]
    people_names: list[str] = []
    while len(people_names) < config.people:
        name = f"{rng.choice(first_names)} {names.word()}"
        people_names.append(name)
    births = {name: rng.randint(FIRST_YEAR, LAST_YEAR) for name in people_names}
    founders = rng.sample(people_names, config.companies)
    companies: dict[str, Company] = {}
    for founder in founders:
        company = f"{names.word()} {rng.choice(COMPANY_ENDINGS)}"
        companies[company] = Company(name=company, industry=rng.choice(INDUSTRIES), founder=founder,
                                     founded=rng.randint(births[founder] + 20, min(births[founder] + 60, LAST_FOUNDED)),
                                     city=rng.choice(city_names))
    company_names = list(companies)
    people = {name: Person(name=name, occupation=rng.choice(OCCUPATIONS), city=rng.choice(city_names),
                           born=births[name], employer=rng.choice(company_names)) for name in people_names}
    return KnowledgeBase(countries=countries, cities=cities, companies=companies, people=people)


@lru_cache(maxsize=8)
def cached_kb(config: KBConfig) -> KnowledgeBase:
    return build_kb(config)


def kb_documents(**options: Any) -> list[str]:
    """The passages of the world ``KBConfig(**options)`` (the ``search`` tool's ``fictional_kb`` corpus)."""
    return cached_kb(KBConfig.from_options(options)).passages()


# --------------------------------------------------------------------------- questions
@dataclass(kw_only=True, frozen=True)
class QuestionKind:
    """One question template over entities of one kind (``subject``)."""

    subject: str  # "person", "company", "country" or "city"
    hops: int  # passages needed to answer
    template: str  # with {subject}
    answer: Callable[[KnowledgeBase, str], str]


def birth_country(kb: KnowledgeBase, person: str) -> str:
    return kb.cities[kb.people[person].city]


QUESTION_KINDS: dict[str, QuestionKind] = {
    "birth_city": QuestionKind(subject="person", hops=1, template="In which city was {subject} born?",
                               answer=lambda kb, s: kb.people[s].city),
    "birth_year": QuestionKind(subject="person", hops=1, template="In what year was {subject} born?",
                               answer=lambda kb, s: str(kb.people[s].born)),
    "employer": QuestionKind(subject="person", hops=1, template="Which company does {subject} work for?",
                             answer=lambda kb, s: kb.people[s].employer),
    "founder": QuestionKind(subject="company", hops=1, template="Who founded {subject}?",
                            answer=lambda kb, s: kb.companies[s].founder),
    "headquarters": QuestionKind(subject="company", hops=1, template="In which city is {subject} headquartered?",
                                 answer=lambda kb, s: kb.companies[s].city),
    "founding_year": QuestionKind(subject="company", hops=1, template="In what year was {subject} founded?",
                                  answer=lambda kb, s: str(kb.companies[s].founded)),
    "capital": QuestionKind(subject="country", hops=1, template="What is the capital of {subject}?",
                            answer=lambda kb, s: kb.countries[s].capital),
    "city_country": QuestionKind(subject="city", hops=1, template="In which country is {subject}?",
                                 answer=lambda kb, s: kb.cities[s]),
    "birth_country": QuestionKind(subject="person", hops=2, template="In which country was {subject} born?",
                                  answer=birth_country),
    "employer_founder": QuestionKind(subject="person", hops=2,
                                     template="Who founded the company that {subject} works for?",
                                     answer=lambda kb, s: kb.companies[kb.people[s].employer].founder),
    "founder_birth_year": QuestionKind(subject="company", hops=2,
                                       template="In what year was the founder of {subject} born?",
                                       answer=lambda kb, s: str(kb.people[kb.companies[s].founder].born)),
    "headquarters_country": QuestionKind(subject="company", hops=2,
                                         template="In which country is {subject} headquartered?",
                                         answer=lambda kb, s: kb.cities[kb.companies[s].city]),
}


def subjects(kb: KnowledgeBase, kind: str) -> list[str]:
    return list({"person": kb.people, "company": kb.companies, "country": kb.countries, "city": kb.cities}[kind])


def kb_split(kb: KnowledgeBase, heldout_fraction: float, seed: int) -> frozenset[str]:
    """The held-out entities: of every entity kind, a ``seed``-chosen ``heldout_fraction`` (at least one)."""
    if not 0.0 < heldout_fraction < 1.0:
        raise ValueError(f"heldout_fraction={heldout_fraction}: must be strictly between 0 and 1")
    rng = random.Random(seed)
    held: set[str] = set()
    for kind in ("person", "company", "country", "city"):
        names = subjects(kb, kind)
        held.update(rng.sample(names, max(1, round(heldout_fraction * len(names)))))
    return frozenset(held)


def kb_problems(kb: KnowledgeBase, kinds: Sequence[str], held_out: frozenset[str], split: str,
                verifier: str = "exact_match") -> list[Problem]:
    """The questions of ``kinds`` whose subject is (``split="test"``) or is not (``"train"``) held out,
    kind after kind, subjects in generation order, each naming ``verifier`` to be scored by."""
    if split not in ("train", "test"):
        raise ValueError(f"split={split!r}: the fictional_kb task has splits train and test (held out)")
    problems = []
    for kind_name in kinds:
        kind = QUESTION_KINDS[kind_name]
        for index, subject in enumerate(subjects(kb, kind.subject)):
            if (subject in held_out) != (split == "test"):
                continue
            question = kind.template.format(subject=subject)
            problems.append(Problem(uid=f"fictional_kb/{split}/{kind_name}/{index}", prompt=question,
                                    answer=kind.answer(kb, subject), verifier=verifier,
                                    metadata={"kind": kind_name, "hops": kind.hops, "subject": subject}))
    return problems


# --------------------------------------------------------------------------- the task source
@dataclass(kw_only=True, frozen=True)
class KBTask:
    """``task.config`` of the ``fictional_kb`` source."""

    kb: KBConfig
    kinds: tuple[str, ...]
    heldout_fraction: float

    @classmethod
    def from_task(cls, task: TaskConfig) -> KBTask:
        options = dict(task.config or {})
        unknown = sorted(set(options) - {"kb", "kinds", "heldout_fraction"})
        if unknown:
            raise ConfigError(f"task.config keys {unknown} are unknown to task.source=fictional_kb; "
                              "known: kb, kinds, heldout_fraction")
        kinds = tuple(options.get("kinds") or QUESTION_KINDS)
        bad = [k for k in kinds if k not in QUESTION_KINDS]
        if bad:
            raise ConfigError(f"task.config.kinds: unknown question kinds {bad}; known: {sorted(QUESTION_KINDS)}")
        try:
            kb = KBConfig.from_options(options.get("kb"))
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"task.config.kb: {exc}") from None
        return cls(kb=kb, kinds=kinds, heldout_fraction=float(options.get("heldout_fraction", 0.2)))

    def split(self, split: str, eval_seed: int, verifier: str = "exact_match") -> list[Problem]:
        kb = cached_kb(self.kb)
        return kb_problems(kb, self.kinds, kb_split(kb, self.heldout_fraction, eval_seed), split, verifier)


def held_out_problems(task: TaskConfig, limit: int | None = None) -> list[Problem]:
    """The first ``limit`` (default ``task.eval_size``) held-out questions in an ``eval_seed`` order."""
    problems = KBTask.from_task(task).split("test", task.eval_seed, kb_verifier(task, "test"))
    random.Random(task.eval_seed).shuffle(problems)
    size = task.eval_size if limit is None else limit
    if size > len(problems):
        raise ConfigError(f"task.eval_size={size} but the fictional_kb task holds out only {len(problems)} "
                          "questions; lower task.eval_size or raise task.config.heldout_fraction or the kb sizes")
    return problems[:size]


def kb_training(task: TaskConfig, seed: int):
    from infinirl.tasks.datasets import EpochBatchIterator

    held_out = held_out_problems(task)
    train = KBTask.from_task(task).split("train", task.eval_seed, kb_verifier(task, "train"))
    # Disjoint by construction (different subjects); asserted because a leak would be silent.
    overlap = {normalize_question(p.prompt) for p in train} & {normalize_question(p.prompt) for p in held_out}
    if overlap:
        raise RuntimeError(f"fictional_kb: {len(overlap)} held-out questions are also training questions")
    return EpochBatchIterator(train, seed=seed), held_out


def kb_evaluation(task: TaskConfig, split: str, limit: int | None, from_run: bool) -> list[Problem]:
    if split == "test":
        return held_out_problems(task, limit)
    if split == "train":
        problems = KBTask.from_task(task).split("train", task.eval_seed, kb_verifier(task, "train"))
        return problems[:limit] if limit else problems
    raise ConfigError(f"split={split!r}: the fictional_kb task has splits test (held out) and train")


def kb_verifier(task: TaskConfig, split: str) -> str:
    # reasoning_gym is the TaskConfig default and cannot score these answers.
    return "exact_match" if task.verifier == "reasoning_gym" else task.verifier


TASK_SOURCES.add("fictional_kb", TaskSource(training=kb_training, evaluation=kb_evaluation, verifier=kb_verifier,
                                            label=lambda task, split: f"fictional_kb-{split}",
                                            answer_format=lambda task: "tagged"))
