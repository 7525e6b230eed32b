import re

import pyarrow as pa
import pytest

from pipelines.evaluate.grounding import score_2d
from pipelines.evaluate.suites import NUINTERACT_TEN, SuiteMapping, score_predictions
from pipelines.evaluate.text import text_scores

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
    assert m["nuinteract/avg"] == pytest.approx(sum(m[k] for k in NUINTERACT_TEN) / 10)

    assert m["nuinstruct/mae"] == pytest.approx(1.0)  # |13 - 12|; the unparsed one is left out
    assert m["nuinstruct/acc"] == pytest.approx(50.0)
    assert m["nuinstruct/map"] == pytest.approx(ap_half)
    assert m["nuinstruct/bleu"] == pytest.approx(100.0)  # predictions equal the captions
    assert m["nuinstruct/average_star"] == pytest.approx((50.0 + ap_half + 100.0 - 1.0) / 4)

    omni = text_scores(*texts(CASES, {"region_description", "planning_speed", "planning_direction"}))
    assert m["omnidrive/bleu"] == pytest.approx(omni["bleu"])
    assert m["omnidrive/avg"] == pytest.approx((omni["bleu"] + omni["cider"] + omni["rouge_l"]) / 3)

    assert len(m) == 20
    assert r.counts["nuinteract/rdp"] == 4 and r.counts["omnidrive/text"] == 4
    assert (r.counts["nuinteract/vg2d"], r.counts["malformed/nuinteract/vg2d"]) == (2, 1)
    assert (r.counts["nuinstruct/regression"], r.counts["malformed/nuinstruct/regression"]) == (2, 1)
    assert r.counts["bad_answer/nuinteract/vg3d"] == 0
    assert set(r.protocol) == set(m) and all(v.startswith("approximate: ") for v in r.protocol.values())
    assert "rows: vg2d" in r.protocol["nuinteract/vg2d_map"]


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
    mapping = SuiteMapping(nuinstruct_caption=("NuInstruct/caption",), nuinstruct_detection=("NuInstruct/det*",))
    r = score_predictions(rows(release), mapping)
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
