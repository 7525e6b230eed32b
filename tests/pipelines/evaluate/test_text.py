import contextlib
import io
import shutil
import warnings

import numpy as np
import pytest
from pycocoevalcap.bleu.bleu import Bleu
from pycocoevalcap.cider.cider import Cider
from pycocoevalcap.rouge.rouge import Rouge
from pycocoevalcap.tokenizer.ptbtokenizer import PTBTokenizer

from pipelines.evaluate import text
from pipelines.evaluate.text import Tokenizer, default_tokenizer, fallback_tokenize, text_scores, tokenize_all

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
# text -> what pycocoevalcap's PTBTokenizer (CoreNLP 3.4.1, -lowerCase) and its punctuation filter give: the
# fallback must give the same (test_fallback_equals_ptb checks these against java where it is installed)
PTB = {
    "x = -12.5, y = -3.0": "x = -12.5 y = -3.0",
    "x=-3": "x = -3",
    "(-1.5, 2)": "-lrb- -1.5 2 -rrb-",
    'It is a Red car, moving (fast); "ok"!': "it is a red car moving -lrb- fast -rrb- ok",
    "{a} [b] (c)": "-lcb- a -rcb- -lsb- b -rsb- -lrb- c -rrb-",
    "<CAM_FRONT> <box>(0,0),(10,10)</box>": "<cam_front> <box> -lrb- 0,0 -rrb- -lrb- 10,10 -rrb- </box>",
    "center: (10.00, 0.00, 0.50), size: (4.00, 2.00, 1.50)": (
        "center -lrb- 10.00 0.00 0.50 -rrb- size -lrb- 4.00 2.00 1.50 -rrb-"
    ),
    "[PT, [1.20, -0.35, 0.00], [2.41, -0.70, 0.01]]": (
        "-lsb- pt -lsb- 1.20 -0.35 0.00 -rsb- -lsb- 2.41 -0.70 0.01 -rsb- -rsb-"
    ),
    "speed 5 m/s, i.e. slow.": "speed 5 m/s i.e. slow",
    "e.g. the car's door": "e.g. the car 's door",
    "U.S. road": "u.s. road",
    "a left-turn isn't here.": "a left-turn is n't here",
    "I can't see; they're here, we'll go.": "i ca n't see they 're here we 'll go",
    "approximately 12.3 meters, 1,000 m": "approximately 12.3 meters 1,000 m",
    "The car is 4.2m ahead, 5m/s": "the car is 4.2 m ahead 5m/s",
    "the 2nd car, 3D box, 5-3 at 10:30": "the 2nd car 3d box 5-3 at 10:30",
    "a - b -- c ... d?": "a b c d",
    "it's 10% more, 5°C": "it 's 10 % more 5 ° c",
    "<gauss> what is it?": "<gauss> what is it",
    "Accelerate. Reason: the lane is clear; the ego vehicle drives 3.2 m/s now.": (
        "accelerate reason the lane is clear the ego vehicle drives 3.2 m/s now"
    ),
    # an untrained model's answers
    "its center and size.2, 1.": "its center and size .2 1",
    "is it doing?gauss>.e are": "is it doing?gauss > e are",
    "e ls now.e l, 0.": "e ls now.e l 0",
    " speed0.80, 0.00, 0.": "speed0 .80 0.00 0",
    "a.b.c": "a.b.c",
    "": "",
}
needs_java = pytest.mark.skipif(shutil.which("java") is None, reason="no java: pycocoevalcap's PTBTokenizer needs it")


@pytest.mark.parametrize(("raw", "tokens"), PTB.items())
def test_fallback_tokenization(raw, tokens):
    assert fallback_tokenize(raw) == tokens


@needs_java
def test_fallback_equals_ptb():
    assert tokenize_all(list(PTB), Tokenizer.ptb) == list(PTB.values())


@needs_java
def test_ptb_keeps_one_line_per_text():
    texts = ["a\rb", "c", "d\u2028e", "f", "g\x0bh", "i\x85j", "k"]  # each a line break to Java's reader
    assert tokenize_all(texts, Tokenizer.ptb) == ["a b", "c", "d e", "f", "g h", "i j", "k"]


@needs_java
def test_ptb_is_pycocoevalcaps_own_tokenizer():
    own = PTBTokenizer().tokenize({i: [{"caption": t}] for i, t in enumerate(REFS + PREDS)})
    assert tokenize_all(REFS + PREDS, Tokenizer.ptb) == [own[i][0] for i in range(len(REFS + PREDS))]
    assert default_tokenizer() is Tokenizer.ptb


@pytest.mark.parametrize("tokenizer", [Tokenizer.fallback, pytest.param(Tokenizer.ptb, marks=needs_java)])
def test_a_minus_sign_costs_bleu(tokenizer):
    got = text_scores(["x = 12.5, y = 3.0"], ["x = -12.5, y = -3.0"], tokenizer)
    assert got["bleu"] < 50.0  # the stand-in that dropped "-" scored this 100
    assert text_scores(["x = -12.5, y = -3.0"], ["x = -12.5, y = -3.0"], tokenizer)["bleu"] == pytest.approx(100.0)


def test_without_java_the_fallback_warns_once(monkeypatch, tmp_path):
    monkeypatch.setenv("PATH", str(tmp_path))  # a PATH without java
    text.warn_fallback.cache_clear()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        first = text_scores(REFS, PREDS)
        text_scores(REFS, REFS)
    assert default_tokenizer() is Tokenizer.fallback
    assert [str(w.message) for w in caught] == [
        "java not found: BLEU, ROUGE-L and CIDEr use gdwm's regex fallback tokenizer "
        "(pipelines.evaluate.text.fallback_tokenize), not the PTBTokenizer, and are labelled approximate "
        "(`make setup` installs a headless Java runtime where it can)"
    ]
    assert first == text_scores(REFS, PREDS, Tokenizer.fallback)


@pytest.mark.parametrize("tokenizer", [Tokenizer.fallback, pytest.param(Tokenizer.ptb, marks=needs_java)])
def test_scores_are_pycocoevalcaps_x100(tokenizer):
    gts = {i: [t] for i, t in enumerate(tokenize_all(REFS, tokenizer))}
    res = {i: [t] for i, t in enumerate(tokenize_all(PREDS, tokenizer))}
    with contextlib.redirect_stdout(io.StringIO()):
        bleu, _ = Bleu(4).compute_score(gts, res)
    rouge, _ = Rouge().compute_score(gts, res)
    cider, _ = Cider().compute_score(gts, res)
    got = text_scores(REFS, PREDS, tokenizer)
    assert got == pytest.approx({"bleu": 100 * bleu[3], "rouge_l": 100 * rouge, "cider": 100 * cider}, abs=1e-9)
    assert 0 < got["bleu"] < 100 and 0 < got["rouge_l"] < 100


def test_cooked_once_scores_equal_pycocoevalcaps_on_resamples_with_repeats():
    # the bootstrap rescores resamples (with repeats) of the same pairs: the cached cooking must give exactly what
    # pycocoevalcap's own compute_score gives on each resample, CIDEr's document frequencies included
    refs = [*REFS, "stop. reason: a pedestrian is crossing.", "go straight at 5 m/s.", "x = -12.5, y = -3.0", "", "a"]
    preds = [*PREDS, "stop.", "go straight at 4 m/s.", "x = 12.5, y = 3.0", "a car", ""]
    rng, ciders = np.random.default_rng(0), []
    for _ in range(40):
        idx = rng.integers(0, len(refs), size=rng.integers(1, 2 * len(refs)))
        r, p = [refs[i] for i in idx], [preds[i] for i in idx]
        gts = {k: [t] for k, t in enumerate(tokenize_all(r, Tokenizer.fallback))}
        res = {k: [t] for k, t in enumerate(tokenize_all(p, Tokenizer.fallback))}
        bleu, _ = Bleu(4).compute_score(gts, res, verbose=0)
        want = {
            "bleu": 100 * float(bleu[3]),
            "rouge_l": 100 * float(Rouge().compute_score(gts, res)[0]),
            "cider": 100 * float(Cider().compute_score(gts, res)[0]),
        }
        got = text_scores(r, p, Tokenizer.fallback)
        assert got["bleu"] == want["bleu"] and got["rouge_l"] == want["rouge_l"]  # pycocoevalcap's own arithmetic
        assert got["cider"] == pytest.approx(want["cider"], rel=1e-12, abs=1e-12)  # numpy CIDEr: sums in another order
        ciders.append(want["cider"])
    assert sum(c > 0 for c in ciders) > 30  # the comparison saw real CIDEr values, not only zeros


def test_identical_text_scores_full_bleu_and_rouge():
    got = text_scores(REFS, REFS, Tokenizer.fallback)
    assert got["bleu"] == pytest.approx(100.0) and got["rouge_l"] == pytest.approx(100.0)


def test_empty_set_and_empty_strings():
    assert text_scores([], []) is None
    got = text_scores(["It is a red car."], [""], Tokenizer.fallback)
    assert got == pytest.approx({"bleu": 0.0, "rouge_l": 0.0, "cider": 0.0})
    with pytest.raises(ValueError, match="2 references but 1 predictions"):
        text_scores(["a", "b"], ["a"])
