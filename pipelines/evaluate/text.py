"""Caption metrics: BLEU-4, ROUGE-L and CIDEr by pycocoevalcap's scorers, x100, on PTB tokens.

The official tokenization is pycocoevalcap's own ``PTBTokenizer`` (Stanford CoreNLP 3.4.1, shipped in the wheel, run
with ``java``). Without Java, ``fallback_tokenize`` stands in (one warning names it) and the metrics are labelled
``approximate``: it reproduces PTB's output on our answers' forms (signed numbers, brackets as ``-lrb-`` etc., SGML
tags like ``<box>``, ``m/s``, abbreviations like ``i.e.``, clitics ``n't``/``'s``), but it is not PTB's lexer.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import shutil
import tempfile
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from enum import StrEnum
from functools import cache

import numpy as np
from pycocoevalcap.bleu import bleu_scorer
from pycocoevalcap.cider import cider_scorer
from pycocoevalcap.rouge.rouge import Rouge
from pycocoevalcap.tokenizer.ptbtokenizer import PUNCTUATIONS, PTBTokenizer


class Tokenizer(StrEnum):
    ptb = "ptb"
    """pycocoevalcap's PTBTokenizer (Java): the official tokenization."""
    fallback = "fallback"
    """``fallback_tokenize``: a regex stand-in for PTB when Java is missing."""


OFFICIAL = "official"
APPROXIMATE = "approximate"
PTB_PROTOCOL = "pycocoevalcap PTBTokenizer (Stanford CoreNLP 3.4.1 via java)"
FALLBACK_PROTOCOL = "gdwm's regex fallback tokenizer (pipelines.evaluate.text.fallback_tokenize), not the PTBTokenizer"

_BRACKETS = {"(": "-lrb-", ")": "-rrb-", "[": "-lsb-", "]": "-rsb-", "{": "-lcb-", "}": "-rcb-"}
# PTB's lexer on lowercased text, the forms our answers use: order matters (first alternative that matches wins).
_TOKEN = re.compile(
    r"</?[a-z_!?][^<>\s]*>"  # SGML tags: <cam_front>, <box>, </box>
    r"|(?:[a-z]\.){2,}(?!\w)"  # abbreviations: i.e., e.g., u.s.
    r"|(?<![\w.])-?\d+(?:[.,]\d+)+"  # decimals with their sign: -12.5, 1,000, 0,0 ("4.2m" -> 4.2 m, as PTB)
    r"|\w+(?=n't\b)|n't\b|'(?:s|re|ve|ll|d|m)\b"  # clitics: isn't -> is n't, car's -> car 's
    r"|(?<![\w.])-?\d\w*(?:[-/:]\w+)*"  # signed integers and what PTB keeps with them: -3, 5m, 2nd, 5-3, 10:30
    r"|[^\W\d_]\w*(?:[.?][^\W\d_]\w*)+"  # letters joined by "." or "?": now.e, doing?gauss (untrained answers)
    r"|\w+(?:[-/]\w+)*"  # words with inner hyphens and slashes: left-turn, m/s, and/or
    r"|\.\d+"  # a decimal without its leading digit: size.2 -> size .2
    r"|[^\w\s]"
)
_DROPPED = frozenset(PUNCTUATIONS) | {'"'}  # what pycocoevalcap drops after PTB (which turns " into `` and '')


def fallback_tokenize(text: str) -> str:
    """PTB-like tokens of ``text`` (lowercased, brackets as ``-lrb-``..., PTB's punctuation dropped), space-joined."""
    tokens = (_BRACKETS.get(t, t) for t in _TOKEN.findall(text.lower()))
    return " ".join(t for t in tokens if t not in _DROPPED)


def java_available() -> bool:
    return shutil.which("java") is not None


def default_tokenizer() -> Tokenizer:
    """``ptb`` where ``java`` is on the PATH, else ``fallback``."""
    return Tokenizer.ptb if java_available() else Tokenizer.fallback


def label(tokenizer: Tokenizer) -> str:
    """``official`` on PTB tokens, ``approximate`` on the fallback's."""
    return OFFICIAL if tokenizer is Tokenizer.ptb else APPROXIMATE


@cache
def warn_fallback() -> None:
    """Once per process: the text metrics use the fallback."""
    warnings.warn(
        f"java not found: BLEU, ROUGE-L and CIDEr use {FALLBACK_PROTOCOL}, and are labelled approximate "
        "(`make setup` installs a headless Java runtime where it can)",
        RuntimeWarning,
        stacklevel=3,
    )


@contextlib.contextmanager
def _stderr_to(file) -> Iterator[None]:
    """The java child inherits fd 2, where PTB prints a line per call: keep it out of the terminal."""
    saved = os.dup(2)
    os.dup2(file.fileno(), 2)
    try:
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def ptb_tokenize(texts: Sequence[str]) -> list[str]:
    """pycocoevalcap's PTBTokenizer over ``texts`` in one java call."""
    if not texts:
        return []
    # one line per text: a \r, \v or \u2028 inside one would shift every later text's tokens onto the wrong text
    captions = {i: [{"caption": " ".join(t.splitlines())}] for i, t in enumerate(texts)}
    with tempfile.TemporaryFile() as err, _stderr_to(err):
        out = PTBTokenizer().tokenize(captions)
        err.seek(0)
        message = err.read().decode(errors="replace").strip()
    if len(out) != len(texts):
        raise RuntimeError(f"PTBTokenizer returned {len(out)} of {len(texts)} texts: {message[-500:]}")
    return [out[i][0] for i in range(len(texts))]


_CACHE: dict[tuple[Tokenizer, str], str] = {}
_CACHE_MAX = 200_000
"""Tokens by text: a bootstrap rescores resamples of the same answers, so java runs about once per table."""


def tokenize_all(texts: Sequence[str], tokenizer: Tokenizer | None = None) -> list[str]:
    """Tokens of every text, with ``tokenizer`` (default: ``default_tokenizer()``, warning once on the fallback)."""
    tok = Tokenizer(tokenizer) if tokenizer is not None else default_tokenizer()
    if tokenizer is None and tok is Tokenizer.fallback:
        warn_fallback()
    missing = list(dict.fromkeys(t for t in texts if (tok, t) not in _CACHE))
    if missing:
        if len(_CACHE) + len(missing) > _CACHE_MAX:
            _CACHE.clear()
        done = ptb_tokenize(missing) if tok is Tokenizer.ptb else [fallback_tokenize(t) for t in missing]
        _CACHE.update(zip(((tok, t) for t in missing), done, strict=True))
    return [_CACHE[tok, t] for t in texts]


def tokenize(text: str, tokenizer: Tokenizer | None = None) -> str:
    return tokenize_all([text], tokenizer)[0]


CIDER_N, CIDER_SIGMA = 4, 6.0
"""pycocoevalcap's ``Cider()`` defaults: n-grams up to 4, Gaussian length penalty sigma 6."""
_NGRAMS: dict[tuple[str, ...], int] = {}
"""Ids of the n-grams the cached pairs hold (CIDEr's document frequencies are counted over these ids)."""


@dataclass(frozen=True)
class _Pair:
    """One (reference, prediction) pair, cooked once: what pycocoevalcap's scorers derive from it per corpus."""

    bleu_ref: tuple
    """``bleu_scorer.cook_refs([ref])``."""
    bleu_test: dict
    """``bleu_scorer.cook_test(pred, bleu_ref)``."""
    rouge_l: float
    """``Rouge().calc_score([pred], [ref])``: ROUGE-L is a mean of per-pair scores."""
    test_ids: np.ndarray
    """CIDEr: the prediction's distinct n-grams (ids), their counts, orders (0..3) and ``min(count, ref count) x ref
    count`` (its term of the cosine's numerator, before the idf weights)."""
    test_counts: np.ndarray
    test_order: np.ndarray
    overlap: np.ndarray
    ref_ids: np.ndarray
    """CIDEr: the reference's distinct n-grams (ids), their counts and orders."""
    ref_counts: np.ndarray
    ref_order: np.ndarray
    penalty: float
    """CIDEr-D's length penalty exp(-delta^2 / 2 sigma^2), delta the difference in bigram counts (pycocoevalcap counts
    a sentence's length in bigrams)."""


_PAIRS: dict[tuple[str, str], _Pair] = {}


def _ngram_arrays(counts: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ids = np.array([_NGRAMS.setdefault(g, len(_NGRAMS)) for g in counts], dtype=np.int64)
    return ids, np.array(list(counts.values()), dtype=float), np.array([len(g) - 1 for g in counts], dtype=np.int64)


def _pair(ref: str, pred: str) -> _Pair:
    """The cooked pair of two tokenized texts (pycocoevalcap's own cooking functions on the same strings); cached."""
    key = (ref, pred)
    if (found := _PAIRS.get(key)) is None:
        if len(_PAIRS) >= _CACHE_MAX:
            _PAIRS.clear()  # the n-gram ids stay valid: _NGRAMS only grows, and its size follows the pairs'
        crefs = bleu_scorer.cook_refs([ref])
        test, refc = cider_scorer.cook_test(pred, CIDER_N), cider_scorer.cook_refs([ref], CIDER_N)[0]
        delta = sum(c for g, c in test.items() if len(g) == 2) - sum(c for g, c in refc.items() if len(g) == 2)
        overlap = np.array([min(c, refc.get(g, 0)) * refc.get(g, 0) for g, c in test.items()], dtype=float)
        found = _PAIRS[key] = _Pair(
            crefs,
            bleu_scorer.cook_test(pred, crefs),
            Rouge().calc_score([pred], [ref]),
            *_ngram_arrays(test),
            overlap,
            *_ngram_arrays(refc),
            math.exp(-(delta**2) / (2 * CIDER_SIGMA**2)),
        )
    return found


def _cider(pairs: Sequence[_Pair]) -> float:
    """CIDEr-D of one corpus, as ``pycocoevalcap.cider.Cider().compute_score`` computes it (one reference each):
    idf from the document frequencies over this corpus's references (a repeated pair counts twice), tf-idf cosine
    per n-gram order times the length penalty, averaged over orders, x10, averaged over pairs.

    Written here in numpy because pycocoevalcap rebuilds every tf-idf dictionary in Python on each call (30 ms for
    96 pairs) and a bootstrap calls it thousands of times; a test holds it to pycocoevalcap's value on resamples."""
    n = len(pairs)
    ref_ids = np.concatenate([p.ref_ids for p in pairs])
    vocab, df = np.unique(ref_ids, return_counts=True)
    ref_len = np.log(float(n))

    def idf2(ids: np.ndarray) -> np.ndarray:  # (ref_len - log(max(1, df)))^2; an n-gram in no reference has df 0
        at = np.minimum(np.searchsorted(vocab, ids), max(len(vocab) - 1, 0))
        d = np.where(vocab[at] == ids, df[at], 0) if len(vocab) else np.zeros(len(ids))
        return (ref_len - np.log(np.maximum(1.0, d))) ** 2

    def by_pair_order(parts: list[np.ndarray], orders: list[np.ndarray], values: np.ndarray) -> np.ndarray:
        slot = np.concatenate([i * CIDER_N + o for i, o in enumerate(orders)]) if parts else np.zeros(0, np.int64)
        return np.bincount(slot, weights=values, minlength=n * CIDER_N).reshape(n, CIDER_N)

    t_ids, r_ids = [p.test_ids for p in pairs], [p.ref_ids for p in pairs]
    t_w, r_w = idf2(np.concatenate(t_ids)), idf2(ref_ids)
    t_ord, r_ord = [p.test_order for p in pairs], [p.ref_order for p in pairs]
    norm_t = np.sqrt(by_pair_order(t_ids, t_ord, np.concatenate([p.test_counts for p in pairs]) ** 2 * t_w))
    norm_r = np.sqrt(by_pair_order(r_ids, r_ord, np.concatenate([p.ref_counts for p in pairs]) ** 2 * r_w))
    num = by_pair_order(t_ids, t_ord, np.concatenate([p.overlap for p in pairs]) * t_w)
    both = (norm_t != 0) & (norm_r != 0)
    val = np.where(both, num / np.where(both, norm_t * norm_r, 1.0), num)
    penalty = np.array([p.penalty for p in pairs])
    return float(np.mean(val.mean(axis=1) * penalty * 10.0))


def _corpus_scores(pairs: Sequence[_Pair]) -> dict[str, float]:
    """BLEU-4 and ROUGE-L by pycocoevalcap's own scorer objects on the cooked pairs (``compute_score`` minus the
    cooking), CIDEr by ``_cider``; x100."""
    bleu = bleu_scorer.BleuScorer(n=4)
    bleu.crefs, bleu.ctest = [p.bleu_ref for p in pairs], [p.bleu_test for p in pairs]
    scores, _ = bleu.compute_score(option="closest", verbose=0)
    rouge = np.mean(np.array([p.rouge_l for p in pairs]))
    return {"bleu": 100 * float(scores[3]), "rouge_l": 100 * float(rouge), "cider": 100 * _cider(pairs)}


def text_scores(
    references: Sequence[str], predictions: Sequence[str], tokenizer: Tokenizer | None = None
) -> dict[str, float] | None:
    """``bleu`` (BLEU-4), ``rouge_l`` and ``cider`` x100 of predictions against one reference each; None if empty.

    Tokens from ``tokenizer`` (default: PTB where Java is, else the fallback). CIDEr's document frequencies come
    from this set's references, so it depends on the set scored.
    """
    if len(references) != len(predictions):
        raise ValueError(f"text_scores: {len(references)} references but {len(predictions)} predictions")
    if not references:
        return None
    tokens = tokenize_all([t or "" for t in (*references, *predictions)], tokenizer)
    n = len(references)
    return _corpus_scores([_pair(tokens[i], tokens[n + i]) for i in range(n)])
