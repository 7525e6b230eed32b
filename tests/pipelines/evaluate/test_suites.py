import re
import shutil
from decimal import Decimal

import pyarrow as pa
import pytest
from omegaconf import OmegaConf

from gdwm.compare.rounding import fmt
from gdwm.config import load_config
from pipelines.data.synth.planning import DIRECTION_DECISIONS, SPEED_DECISIONS
from pipelines.evaluate.config import NUINSTRUCT_SUBTASKS, NUINTERACT_DECISIONS, SYNTH_DECISIONS, EvaluateQAConfig
from pipelines.evaluate.grounding import score_2d
from pipelines.evaluate.suites import (
    NUINTERACT_TEN,
    SuiteMapping,
    mapping_of,
    score_predictions,
    score_table,
    with_mapping,
)
from pipelines.evaluate.text import Tokenizer, text_scores

DESC = "It is a red car, moving in the same direction as the ego vehicle."
BOX = "<CAM_FRONT> <box>(0,0),(10,10)</box>"
CENTRE = "center: (10.00, 0.00, 0.50), size: (4.00, 2.00, 1.50)"
# (task, category, answer, prediction)
CASES = [
    (
        "rdp",
        "2D_perception_infos",
        "The object is approximately 12.0 meters away from the ego vehicle.",
        "About 13.0 m.",
    ),
    ("rdp", "2D_perception_infos", "The object is approximately 8.0 meters away from the ego vehicle.", "No idea."),
    ("rdp", "region_description", DESC, DESC),
    ("rdp", "region_description", "It is a pedestrian in blue, standing.", "It is a pedestrian in blue, standing."),
    ("vg2d", "2D_visual_grounding", BOX, BOX),  # IoU 1
    ("vg2d", "2D_visual_grounding", BOX, "It is on the left."),  # malformed
    ("vg3d", "3D_visual_grounding", CENTRE, CENTRE),  # 0 m
    ("vg3d", "3D_visual_grounding", CENTRE, "center: (13.00, 0.00, 0.50), size: (4.00, 2.00, 1.50)"),  # 3 m
    ("plan", "planning_speed", "Accelerate. Reason: the lane is clear.", "Accelerate. Reason: it is clear."),
    ("plan", "planning_direction", "Turn left. Reason: the road bends.", "Go straight. Reason: straight road."),
    ("traj", "trajectory_prediction", "[PT, [0, 0, 0, 0, 0, 0, 1]]", "[PT]"),
]
COLUMNS = ("task", "category", "answer", "prediction")


def rows(cases=CASES):
    return [
        {"sample_id": f"s/{i:05d}", "scene": "s", "frame": i, "instruction": "q", **dict(zip(COLUMNS, c, strict=True))}
        for i, c in enumerate(cases)
    ]


def texts(cases, categories):
    sel = [c for c in cases if c[1] in categories]
    return [c[2] for c in sel], [c[3] for c in sel]


def test_every_suite_by_hand():
    r = score_predictions(rows())
    m = r.metrics
    ap_half = 100 * 51 / 101  # one hit ranked first of 2 ground truths: precision 1 up to recall 1/2
    assert m["nuinteract/vg2d_map"] == pytest.approx(ap_half)
    assert m["nuinteract/vg2d_f1"] == pytest.approx(100 * 2 / 3)  # precision 1, recall 1/2
    assert m["nuinteract/vg2d_miou"] == pytest.approx(50.0)
    assert m["nuinteract/vg3d_pr"] == pytest.approx(50.0)
    assert m["nuinteract/vg3d_f1"] == pytest.approx(50.0)
    assert m["nuinteract/vg3d_map"] == pytest.approx((3 * ap_half + 100) / 4)  # the 3 m one hits only at 4 m
    assert m["nuinteract/plan_acc"] == pytest.approx(50.0)
    rdp = text_scores(*texts(CASES, {"2D_perception_infos", "region_description"}))
    assert (m["nuinteract/rdp_bleu"], m["nuinteract/rdp_rouge_l"], m["nuinteract/rdp_cider"]) == pytest.approx(
        (rdp["bleu"], rdp["rouge_l"], rdp["cider"])
    )
    # the aggregates are means of the values as printed (2 decimals, half up), as in the paper, exact in Decimal
    shown = [Decimal(fmt(m[k], 2)) for k in NUINTERACT_TEN]
    assert m["nuinteract/avg"] == float(sum(shown) / 10)

    assert m["nuinstruct/mae"] == pytest.approx(1.0)  # |13 - 12|; the unparsed one is left out
    assert m["nuinstruct/acc"] == pytest.approx(50.0)
    assert m["nuinstruct/map"] == pytest.approx(ap_half)
    assert m["nuinstruct/bleu"] == pytest.approx(100.0)  # predictions equal the captions
    assert m["nuinstruct/average_star"] == pytest.approx((50.0 + 50.50 + 100.0 - 1.0) / 4, abs=1e-12)

    omni = text_scores(*texts(CASES, {"region_description", "planning_speed", "planning_direction"}))
    assert m["omnidrive/bleu"] == pytest.approx(omni["bleu"])
    printed = [Decimal(fmt(omni[k], 2)) for k in ("bleu", "cider", "rouge_l")]
    assert m["omnidrive/avg"] == float(sum(printed) / 3)

    assert len(m) == 20
    assert r.counts["nuinteract/rdp"] == 4 and r.counts["omnidrive/text"] == 4
    assert (r.counts["nuinteract/vg2d"], r.counts["malformed/nuinteract/vg2d"]) == (2, 1)
    assert (r.counts["nuinstruct/regression"], r.counts["malformed/nuinstruct/regression"]) == (2, 1)
    assert r.counts["bad_answer/nuinteract/vg3d"] == 0
    assert set(r.protocol) == set(m) == set(r.labels)
    assert "rows: vg2d" in r.protocol["nuinteract/vg2d_map"]
    assert set(r.proxy) == {k for k in m if not k.startswith("nuinteract/")}  # the default mapping's proxy suites


def test_flat_is_float_and_mlflow_legal():
    flat = score_predictions(rows()).flat()
    assert flat["count/malformed/nuinteract/vg2d"] == 1.0
    assert all(isinstance(v, float) for v in flat.values())
    assert all(re.fullmatch(r"[\w\-. :/]+", k) for k in flat)


def test_absent_family_and_aggregates():
    only_grounding = [c for c in CASES if c[0] == "vg2d"]
    r = score_predictions(rows(only_grounding))
    assert set(r.metrics) == {"nuinteract/vg2d_map", "nuinteract/vg2d_f1", "nuinteract/vg2d_miou", "nuinstruct/map"}
    assert "nuinteract/avg" not in r.metrics and "omnidrive/text" not in r.counts
    assert score_predictions([]).metrics == {}


def test_table_input_equals_dicts():
    table = pa.Table.from_pylist(rows())
    assert score_predictions(table).metrics == score_predictions(rows()).metrics


def test_scores_do_not_depend_on_what_was_scored_before():
    """The parsers and the row selection are memoised (a bootstrap re-scores the same rows for every resample): a
    table's metrics are the same whatever was scored before it and under which mapping, and a row without a task
    is still selected by its category."""
    first = score_predictions(rows()).metrics
    swapped = SuiteMapping(nuinteract_vg2d=["vg3d"], nuinteract_vg3d=["vg2d"])
    other = score_predictions(rows(), swapped)
    # each family's answers are the other's bad answers: no grounding metric, every reference counted as unparsed
    assert other.counts["bad_answer/nuinteract/vg2d"] == other.counts["bad_answer/nuinteract/vg3d"] == 2
    assert "nuinteract/vg2d_map" not in other.metrics and first["nuinteract/vg2d_map"] == pytest.approx(
        50.495, abs=1e-3
    )
    assert score_predictions(rows()).metrics == first
    untasked = [(None, c[1], c[2], c[3]) for c in CASES if c[1] == "2D_perception_infos"]
    assert (
        score_predictions(rows(untasked)).metrics
        == {"nuinstruct/mae": first["nuinstruct/mae"]}
        == {"nuinstruct/mae": 1.0}
    )


def test_mapping_selects_release_categories():
    release = [("rdp", "NuInstruct/caption", DESC, DESC), ("vg2d", "NuInstruct/detection", BOX, BOX)]
    default = score_predictions(rows(release))
    assert "nuinstruct/bleu" not in default.metrics and "nuinstruct/map" not in default.metrics
    mapping = SuiteMapping(
        nuinstruct_caption=["NuInstruct/caption"], nuinstruct_detection=["NuInstruct/det*"], proxy=[]
    )
    r = score_predictions(rows(release), mapping)
    assert r.proxy == {} and "proxy" not in r.protocol["nuinstruct/bleu"]
    assert r.metrics["nuinstruct/bleu"] == pytest.approx(100.0)
    assert r.metrics["nuinstruct/map"] == pytest.approx(score_2d([BOX], [BOX]).metrics["map"])
    assert r.metrics["nuinstruct/map"] == pytest.approx(100.0)


def test_missing_column_names_the_row():
    with pytest.raises(ValueError, match=r"row 0 \(x\) lacks \['prediction'\]"):
        score_predictions([{"sample_id": "x", "task": "rdp", "category": "c", "answer": "a"}])


def test_wanted_metrics_are_the_same_numbers_computed_alone():
    from pipelines.evaluate.suites import score_table

    rows = [
        {"task": t, "category": c, "answer": a, "prediction": p}
        for t, c, a, p in [
            ("rdp", "region_description", "a red car is parked on the left", "a red car parked left"),
            ("rdp", "region_description", "two pedestrians cross ahead", "one pedestrian ahead"),
            ("plan", "planning_speed", "Keep speed. The road is clear.", "Keep speed. Clear."),
            ("plan", "planning_speed", "Stop. A pedestrian crosses.", "Keep speed."),
        ]
    ]
    full = score_table(rows)
    some = score_table(rows, {"nuinteract/rdp_cider", "nuinteract/plan_acc"})
    assert some == {k: full[k] for k in ("nuinteract/rdp_bleu", "nuinteract/rdp_rouge_l", "nuinteract/rdp_cider",
                                          "nuinteract/plan_acc")}  # fmt: skip
    assert "omnidrive/bleu" in full and "omnidrive/bleu" not in some


@pytest.mark.parametrize("tokenizer", [Tokenizer.fallback, pytest.param(Tokenizer.ptb, marks=pytest.mark.skipif(
    shutil.which("java") is None, reason="no java"))])  # fmt: skip
def test_labels_official_text_metrics_on_ptb_only(tokenizer):
    r = score_predictions(rows(), tokenizer=tokenizer)
    text = {"nuinteract/rdp_bleu", "nuinteract/rdp_rouge_l", "nuinteract/rdp_cider", "nuinstruct/bleu",
            "omnidrive/bleu", "omnidrive/cider", "omnidrive/rouge_l", "omnidrive/avg"}  # fmt: skip
    expected = "official" if tokenizer is Tokenizer.ptb else "approximate"
    assert r.labels == {k: expected if k in text else "approximate" for k in r.metrics}
    assert r.tokenizer is tokenizer
    assert r.protocol["omnidrive/bleu"].startswith(f"{expected}: BLEU-4 x100")
    assert ("PTBTokenizer (Stanford" in r.protocol["nuinteract/rdp_bleu"]) == (tokenizer is Tokenizer.ptb)
    params = r.params()
    assert params["protocol/nuinteract/vg2d_map"] == "approximate" and params["text_tokenizer"] == tokenizer.value
    assert params["proxy/omnidrive/bleu"] == (
        "rows region_description, planning_speed, planning_direction stand in for OmniDrive's own data"
    )
    assert "proxy/nuinteract/rdp_bleu" not in params


def test_average_star_is_the_paper_printed_mean_half_up():
    cases = [
        ("rdp", "2D_perception_infos", "The object is approximately 12.0 meters away.", "About 12.33 m."),
        ("vg2d", "2D_visual_grounding", BOX, BOX),
        ("rdp", "region_description", DESC, DESC),
        ("plan", "planning_speed", "Stop. Reason: a car ahead.", "Stop. Reason: a car."),
        ("plan", "planning_speed", "Accelerate. Reason: clear.", "Accelerate. Reason: clear."),
        ("plan", "planning_direction", "Turn left. Reason: bend.", "Go straight. Reason: none."),
    ]
    m = score_predictions(rows(cases), tokenizer=Tokenizer.fallback).metrics
    acc, map_, bleu, mae = (m[f"nuinstruct/{k}"] for k in ("acc", "map", "bleu", "mae"))
    naive = (acc + map_ + bleu - mae) / 4  # 66.58416...: what the unrounded parts give
    assert f"{naive:.2f}" == "66.58"
    assert m["nuinstruct/average_star"] == 66.585  # (66.67 + 100.00 + 100.00 - 0.33) / 4: the printed parts' mean
    assert fmt(m["nuinstruct/average_star"], 2) == "66.59"


def test_score_table_rescores_with_the_mapping_the_table_carries():
    mapping = SuiteMapping(nuinteract_plan=["planning_direction"], proxy=[])
    table = with_mapping(pa.Table.from_pylist(rows()), mapping)
    assert mapping_of(table) == mapping and mapping_of(pa.Table.from_pylist(rows())) is None
    assert score_table(table, {"nuinteract/plan_acc"}) == {"nuinteract/plan_acc": 0.0}  # only the wrong turn
    assert score_table(table.take([0, 9]), {"nuinteract/plan_acc"}) == {"nuinteract/plan_acc": 0.0}
    assert score_table(pa.Table.from_pylist(rows()), {"nuinteract/plan_acc"}) == {"nuinteract/plan_acc": 50.0}


def test_suite_mapping_is_a_config_group():
    cfg = load_config()
    default = EvaluateQAConfig(**OmegaConf.to_container(cfg.stage.evaluate_qa, enum_to_str=True))  # as a stage gets it
    assert default.suites == SuiteMapping()  # conf/stage/evaluate_qa/suites/proxy.yaml = the schema's defaults
    assert default.suites.proxy == ["nuinstruct", "omnidrive"]
    assert list(SPEED_DECISIONS + DIRECTION_DECISIONS) == SYNTH_DECISIONS
    tiny = load_config(
        ["stage/evaluate_qa=tiny", "stage/evaluate_qa/suites=proxy", "stage.evaluate_qa.suites.proxy=[]"]
    )
    assert list(tiny.stage.evaluate_qa.suites.proxy) == [] and tiny.stage.evaluate_qa.max_samples == 24
    from gdwm.config import ConfigError

    with pytest.raises(ConfigError, match="config group 'stage/evaluate_qa/suites' has no option 'real'; allowed "
                                          "values: nuinstruct, nuinteract, omnidrive, proxy"):  # fmt: skip
        load_config(["stage/evaluate_qa/suites=real"])


def _suite(option: str) -> SuiteMapping:
    cfg = load_config([f"stage/evaluate_qa/suites={option}"])
    return EvaluateQAConfig(**OmegaConf.to_container(cfg.stage.evaluate_qa, enum_to_str=True)).suites


def test_benchmark_suites_are_the_importers_taxonomies():
    nuinteract, nuinstruct, omnidrive = (_suite(o) for o in ("nuinteract", "nuinstruct", "omnidrive"))
    assert nuinteract.proxy == nuinstruct.proxy == omnidrive.proxy == []
    assert nuinteract.decision_labels == NUINTERACT_DECISIONS and nuinteract.decision_match == "first"
    assert nuinstruct.nuinstruct_protocol == "per_subtask"
    assert {k: getattr(nuinstruct, f"nuinstruct_{k}") for k in NUINSTRUCT_SUBTASKS} == NUINSTRUCT_SUBTASKS
    assert omnidrive.omnidrive_text == ["desc", "conv"]
    for m, own in ((nuinteract, "nuinteract"), (nuinstruct, "nuinstruct"), (omnidrive, "omnidrive")):
        others = [f for f in vars(m) if f.startswith(("nuinteract_", "nuinstruct_", "omnidrive_"))]
        assert all(getattr(m, f) == [] for f in others if not f.startswith(own) and f != "nuinstruct_protocol"), own


def test_nuinteract_suite_reads_the_decision_anywhere():
    cases = [
        ("plan", "planning_go_straight", "The ego car should go straight.", "Go straight, the road is clear."),
        ("plan", "planning_turn_left", "Turn left at the junction.", "It should turn right, then turn left."),
        ("plan", "planning_turn_right", "Turn right.", "Stop."),
    ]
    r = score_predictions(rows(cases), _suite("nuinteract"))
    assert r.metrics == {"nuinteract/plan_acc": pytest.approx(100 / 3)}  # the first named decision counts
    assert r.counts["malformed/nuinteract/plan"] == 1
    assert "(the first of the decision labels the text names)" in r.protocol["nuinteract/plan_acc"]


NUINSTRUCT_CASES = [
    ("perception", "perception-distance", "(10.0, 1.0)", "(12.0, 0.0)"),  # 1.5
    ("perception", "perception-distance", "(0.0, 0.0)", "(0.5, 0.5)"),  # 0.5
    ("perception", "perception-instance_count", "3", "5"),  # 2
    ("perception", "perception-closest", "<car>[c1,0,0,10,10]", "<car>[c1,1,1,9,9]"),  # right
    ("prediction", "prediction-status_ego", "Moving.", "Stopped."),  # wrong
    ("risk", "risk-overtaking", "<car>[c1,0,0,10,10];<pedestrian>[c4,20,20,30,40]", "<car>[c1,0,0,10,10]"),
    ("risk", "risk-non", "There is no risk object.", "None."),  # nothing to score
    ("reasoning", "reasoning-reasoning", DESC, DESC),
]


def test_nuinstruct_suite_is_its_protocol_per_subtask():
    r = score_predictions(rows(NUINSTRUCT_CASES), _suite("nuinstruct"), tokenizer=Tokenizer.fallback)
    m = r.metrics
    assert m["nuinstruct/mae"] == pytest.approx((1.0 + 2.0) / 2)  # distance (1.5 + 0.5) / 2, count 2
    assert m["nuinstruct/acc"] == pytest.approx((100.0 + 0.0) / 2)  # closest, status_ego
    assert m["nuinstruct/map"] == pytest.approx(100 * 51 / 101)  # risk-non has no scored sample
    assert m["nuinstruct/bleu"] == pytest.approx(100.0)
    printed = [Decimal(fmt(v, 2)) for v in (50.0, 100 * 51 / 101, 100.0, -1.5)]
    assert m["nuinstruct/average_star"] == float(sum(printed) / 4)
    assert set(m) == {f"nuinstruct/{k}" for k in ("mae", "acc", "map", "bleu", "average_star")}
    assert r.subtasks["nuinstruct/mae"] == {"perception-distance": 1.0, "perception-instance_count": 2.0}
    assert r.counts["empty/nuinstruct/detection"] == 1 and r.counts["nuinstruct/detection"] == 1
    assert r.labels["nuinstruct/map"] == "approximate" and r.proxy == {}
    assert r.protocol["nuinstruct/mae"].startswith("approximate: mean over its subtasks (row category) of the MAE")


def test_average_star_floors_at_zero():
    cases = [("perception", "perception-distance", "(40.0, 0.0)", "(0.0, 0.0)"), NUINSTRUCT_CASES[4],
             ("risk", "risk-overtaking", "<car>[c1,0,0,10,10]", "None."), ("reasoning", "reasoning-reasoning", DESC,
             "No.")]  # fmt: skip
    m = score_predictions(rows(cases), _suite("nuinstruct"), tokenizer=Tokenizer.fallback).metrics
    assert (m["nuinstruct/mae"], m["nuinstruct/acc"], m["nuinstruct/map"]) == (20.0, 0.0, 0.0)
    assert (m["nuinstruct/bleu"] - 20.0) / 4 < 0
    assert m["nuinstruct/average_star"] == 0.0  # VGGDrive: max(..., 0)


def test_omnidrive_suite_pools_descriptions_and_dialogue():
    cases = [
        ("desc", "scene_description", "The ego car drives on a wet road behind a grey car.", "A grey car ahead."),
        ("conv", "general_dialogue", "Yes, a grey car drives ahead.", "Yes, a car drives ahead."),
        ("vqa", "vqa", "The grey car ahead.", "Nothing."),  # trained on, not scored
    ]
    r = score_predictions(rows(cases), _suite("omnidrive"), tokenizer=Tokenizer.fallback)
    want = text_scores(*texts(cases, {"scene_description", "general_dialogue"}), Tokenizer.fallback)
    assert r.metrics["omnidrive/bleu"] == pytest.approx(want["bleu"])
    assert r.metrics["omnidrive/cider"] == pytest.approx(want["cider"])
    assert r.metrics["omnidrive/rouge_l"] == pytest.approx(want["rouge_l"])
    assert r.metrics["omnidrive/avg"] == float(sum(Decimal(fmt(want[k], 2)) for k in ("bleu", "cider", "rouge_l")) / 3)
    assert r.counts == {"omnidrive/text": 2} and r.proxy == {}
