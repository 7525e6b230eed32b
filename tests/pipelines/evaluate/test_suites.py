import re
import shutil
from decimal import Decimal

import pyarrow as pa
import pytest
from omegaconf import OmegaConf

from gdwm.compare.rounding import fmt
from gdwm.config import load_config
from pipelines.data.synth.planning import DIRECTION_DECISIONS, SPEED_DECISIONS
from pipelines.evaluate.config import SYNTH_DECISIONS, EvaluateQAConfig
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
                                          "values: proxy"):  # fmt: skip
        load_config(["stage/evaluate_qa/suites=real"])
