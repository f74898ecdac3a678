"""Local retrieval for search agents: a BM25 index in numpy, corpora by name, the ``search`` tool.

BM25 (Okapi, with the always-positive idf of Lucene): a document ``d`` scores, for a query of terms
``q_1..q_n`` (a term written twice counts twice),

    sum_i idf(q_i) * tf(q_i, d) * (k1 + 1) / (tf(q_i, d) + k1 * (1 - b + b * |d| / avgdl))
    idf(t) = log(1 + (N - n_t + 0.5) / (n_t + 0.5))

with ``N`` documents, ``n_t`` of them holding ``t``, lengths in tokens (lowercased ``\\w+`` runs).
Each term's per-document weight is computed once at indexing; a query adds the weights of its terms.

The tool runs inside rollout workers, one instance per trajectory, so it never receives a corpus
from the driver: it rebuilds it from its options (``corpus`` by name in :data:`CORPORA`, and
``corpus_options``), which makes it identical in every process; the index is built once per process
and options, and shared.
"""

from __future__ import annotations

import json
import math
import re
import threading
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from infinirl.agents.tools import TOOLS, Tool
from infinirl.registry import Registry

__all__ = ["CORPORA", "BM25Index", "SearchTool", "corpus_index", "tokenize"]

TOKEN = re.compile(r"\w+")
CORPORA: Registry[Callable[..., Sequence[str]]] = Registry("search corpus", entry_point_group="infinirl.corpora")


def tokenize(text: str) -> list[str]:
    """Lowercased runs of word characters: the terms BM25 counts."""
    return TOKEN.findall(text.lower())


class BM25Index:
    """An exact BM25 index over ``documents`` (see the module docstring for the formula)."""

    def __init__(self, documents: Sequence[str], *, k1: float = 1.5, b: float = 0.75):
        if not documents:
            raise ValueError("BM25Index needs at least one document")
        if k1 < 0 or not 0.0 <= b <= 1.0:
            raise ValueError(f"BM25 k1={k1}, b={b}: need k1 >= 0 and 0 <= b <= 1")
        self.documents = tuple(documents)
        self.k1, self.b = float(k1), float(b)
        counts = [Counter(tokenize(document)) for document in self.documents]
        lengths = np.array([sum(c.values()) for c in counts], dtype=np.float64)
        average = lengths.mean() or 1.0  # every document empty: length normalisation is moot
        norm = self.k1 * (1.0 - self.b + self.b * lengths / average)
        postings: dict[str, tuple[list[int], list[int]]] = {}
        for index, count in enumerate(counts):
            for term, tf in count.items():
                docs, tfs = postings.setdefault(term, ([], []))
                docs.append(index)
                tfs.append(tf)
        n = len(self.documents)
        self.postings: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        for term, (docs, tfs) in postings.items():
            doc_ids, tf = np.array(docs, dtype=np.int64), np.array(tfs, dtype=np.float64)
            idf = math.log(1.0 + (n - len(docs) + 0.5) / (len(docs) + 0.5))
            self.postings[term] = (doc_ids, idf * tf * (self.k1 + 1.0) / (tf + norm[doc_ids]))

    def __len__(self) -> int:
        return len(self.documents)

    def scores(self, query: str) -> np.ndarray:
        """The BM25 score of every document for ``query`` (float64, one per document)."""
        scores = np.zeros(len(self.documents), dtype=np.float64)
        for term in tokenize(query):
            posting = self.postings.get(term)
            if posting is not None:
                scores[posting[0]] += posting[1]  # a term's documents are distinct: no index repeats
        return scores

    def search(self, query: str, k: int) -> list[tuple[int, float]]:
        """The ``k`` best documents ``(index, score)`` with a positive score, best first; equal
        scores in document order."""
        if k < 1:
            raise ValueError(f"k={k}: must be >= 1")
        scores = self.scores(query)
        hits = np.flatnonzero(scores > 0)
        order = hits[np.lexsort((hits, -scores[hits]))][:k]
        return [(int(i), float(scores[i])) for i in order]


@CORPORA.register("fictional_kb")
def fictional_kb_corpus(**options: Any) -> Sequence[str]:
    """The passages of :mod:`infinirl.tasks.fictional_kb` (options: its ``KBConfig`` fields)."""
    from infinirl.tasks.fictional_kb import kb_documents

    return kb_documents(**options)


INDEXES: dict[str, BM25Index] = {}
INDEX_LOCK = threading.Lock()


def corpus_index(corpus: str, options: Mapping[str, Any] | None = None, *, k1: float = 1.5,
                 b: float = 0.75) -> BM25Index:
    """The BM25 index of the registered corpus ``corpus`` built with ``options``, built once per process."""
    key = json.dumps([corpus, dict(options or {}), k1, b], sort_keys=True, default=str)
    with INDEX_LOCK:
        if key not in INDEXES:
            INDEXES[key] = BM25Index(list(CORPORA.get(corpus)(**dict(options or {}))), k1=k1, b=b)
        return INDEXES[key]


@TOOLS.register("search")
class SearchTool(Tool):
    """Answers a query with the ``k`` best passages of a corpus, one per line, at most ``max_chars``
    characters in all (a cut ends with ``...``)."""

    name = "search"
    description = "Search the knowledge base and return the passages that best match the query."
    parameters = {
        "type": "object",
        "properties": {"query": {"type": "string", "description": "what to look up, e.g. a name"}},
        "required": ["query"],
    }
    NO_HITS = "No passage matches the query."

    def __init__(self, *, corpus: str = "fictional_kb", corpus_options: Mapping[str, Any] | None = None, k: int = 3,
                 max_chars: int = 600, k1: float = 1.5, b: float = 0.75, timeout_s: float = 5.0) -> None:
        if k < 1:
            raise ValueError(f"search tool k={k}: must be >= 1")
        if max_chars < 16:
            raise ValueError(f"search tool max_chars={max_chars}: must be >= 16")
        self.index = corpus_index(corpus, corpus_options, k1=k1, b=b)
        self.k, self.max_chars, self.timeout_s = k, max_chars, timeout_s

    async def run(self, query: str) -> str:
        return self.lookup(query)

    def lookup(self, query: str) -> str:
        """The tool's answer to ``query`` (synchronously: the search is fast and holds no lock)."""
        passages = [self.index.documents[i] for i, _ in self.index.search(query, self.k)]
        return bounded_join(passages, self.max_chars) if passages else self.NO_HITS


def bounded_join(passages: Sequence[str], max_chars: int) -> str:
    """``passages`` one per line, cut to at most ``max_chars`` characters (a cut ends with ``...``)."""
    text = "\n".join(passages)
    return text if len(text) <= max_chars else text[: max_chars - 3] + "..."
