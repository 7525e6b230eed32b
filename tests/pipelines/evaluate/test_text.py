import contextlib
import io

import pytest
from pycocoevalcap.bleu.bleu import Bleu
from pycocoevalcap.cider.cider import Cider
from pycocoevalcap.rouge.rouge import Rouge

from pipelines.evaluate.text import text_scores, tokenize

REFS = [
    "It is a red car, moving in the same direction as the ego vehicle.",
    "It is a pedestrian in blue, standing.",
    "Turn left. Reason: the road bends to the left; the heading changes by 12 degrees.",
    "The object is approximately 12.3 meters away from the ego vehicle.",
]
PREDS = [
    "It is a red car, parked.",
    "It is a pedestrian in blue, walking across the road.",
    "Turn left. Reason: the road bends to the left.",
    "The object is approximately 14.0 meters away.",
]


def test_tokenize_lowercases_and_drops_punctuation():
    assert tokenize('It is a Red car, moving (fast); "ok"!') == "it is a red car moving fast ok"
    assert tokenize("approximately 12.3 meters, 1,000 m") == "approximately 12.3 meters 1,000 m"
    assert tokenize("a left-turn isn't here.") == "a left-turn isn't here"
    assert tokenize("") == ""


def test_scores_are_pycocoevalcaps_x100():
    gts = {i: [tokenize(r)] for i, r in enumerate(REFS)}
    res = {i: [tokenize(p)] for i, p in enumerate(PREDS)}
    with contextlib.redirect_stdout(io.StringIO()):
        bleu, _ = Bleu(4).compute_score(gts, res)
    rouge, _ = Rouge().compute_score(gts, res)
    cider, _ = Cider().compute_score(gts, res)
    got = text_scores(REFS, PREDS)
    assert got == pytest.approx({"bleu": 100 * bleu[3], "rouge_l": 100 * rouge, "cider": 100 * cider}, abs=1e-9)
    assert 0 < got["bleu"] < 100 and 0 < got["rouge_l"] < 100


def test_identical_text_scores_full_bleu_and_rouge():
    got = text_scores(REFS, REFS)
    assert got["bleu"] == pytest.approx(100.0) and got["rouge_l"] == pytest.approx(100.0)


def test_empty_set_and_empty_strings():
    assert text_scores([], []) is None
    assert text_scores(["It is a red car."], [""]) == pytest.approx({"bleu": 0.0, "rouge_l": 0.0, "cider": 0.0})
    with pytest.raises(ValueError, match="2 references but 1 predictions"):
        text_scores(["a", "b"], ["a"])
