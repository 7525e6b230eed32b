"""Caption metrics: BLEU-4, ROUGE-L and CIDEr by pycocoevalcap's scorers, x100."""

from __future__ import annotations

import contextlib
import io
import re
from collections.abc import Sequence

from pycocoevalcap.bleu.bleu import Bleu
from pycocoevalcap.cider.cider import Cider
from pycocoevalcap.rouge.rouge import Rouge

_TOKEN = re.compile(r"\d+(?:[.,]\d+)+|\w+(?:[-']\w+)*|[^\w\s]")
# The tokens PTBTokenizer (pycocoevalcap.tokenizer) drops, brackets included (it writes them -LRB- etc.).
_PUNCTUATION = frozenset(".?!,:;-'`\"()[]{}")


def tokenize(text: str) -> str:
    """Lowercased, punctuation split off and dropped, tokens joined by single spaces.

    Stands in for pycocoevalcap's PTBTokenizer, which needs Java; on plain English it has the same effect, except that
    contractions stay whole ("don't", "car's") where PTB splits them ("do n't", "car 's").
    """
    return " ".join(t for t in _TOKEN.findall(text.lower()) if t not in _PUNCTUATION)


def text_scores(references: Sequence[str], predictions: Sequence[str]) -> dict[str, float] | None:
    """``bleu`` (BLEU-4), ``rouge_l`` and ``cider`` x100 of predictions against one reference each; None if empty.

    CIDEr's document frequencies come from this set's references, so it depends on the set scored.
    """
    if len(references) != len(predictions):
        raise ValueError(f"text_scores: {len(references)} references but {len(predictions)} predictions")
    if not references:
        return None
    gts = {i: [tokenize(r or "")] for i, r in enumerate(references)}
    res = {i: [tokenize(p or "")] for i, p in enumerate(predictions)}
    with contextlib.redirect_stdout(io.StringIO()):  # Bleu prints its length statistics
        bleu, _ = Bleu(4).compute_score(gts, res, verbose=0)
    rouge, _ = Rouge().compute_score(gts, res)
    cider, _ = Cider().compute_score(gts, res)
    return {"bleu": 100 * float(bleu[3]), "rouge_l": 100 * float(rouge), "cider": 100 * float(cider)}
