"""Caption metrics: BLEU-4, ROUGE-L and CIDEr by pycocoevalcap's scorers, x100, on PTB tokens.

The official tokenization is pycocoevalcap's own ``PTBTokenizer`` (Stanford CoreNLP 3.4.1, shipped in the wheel, run
with ``java``). Without Java, ``fallback_tokenize`` stands in (one warning names it) and the metrics are labelled
``approximate``: it reproduces PTB's output on our answers' forms (signed numbers, brackets as ``-lrb-`` etc., SGML
tags like ``<box>``, ``m/s``, abbreviations like ``i.e.``, clitics ``n't``/``'s``), but it is not PTB's lexer.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import shutil
import tempfile
import warnings
from collections.abc import Iterator, Sequence
from enum import StrEnum
from functools import cache

from pycocoevalcap.bleu.bleu import Bleu
from pycocoevalcap.cider.cider import Cider
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
    gts = {i: [tokens[i]] for i in range(n)}
    res = {i: [tokens[n + i]] for i in range(n)}
    with contextlib.redirect_stdout(io.StringIO()):  # Bleu prints its length statistics
        bleu, _ = Bleu(4).compute_score(gts, res, verbose=0)
    rouge, _ = Rouge().compute_score(gts, res)
    cider, _ = Cider().compute_score(gts, res)
    return {"bleu": 100 * float(bleu[3]), "rouge_l": 100 * float(rouge), "cider": 100 * float(cider)}
