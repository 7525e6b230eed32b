"""NuInstruct's protocol (pipelines.evaluate.nuinstruct) against values computed by hand."""

import pytest

from pipelines.evaluate.nuinstruct import (
    RiskObject,
    class_label,
    classification_scores,
    parse_objects,
    parse_value,
    per_subtask,
    regression_error,
    regression_scores,
    risk_scores,
    sample_ap,
)

CAR = "<car>[c1,0.0,0.0,10.0,10.0]"
PED = "<pedestrian>[c4,20.0,20.0,30.0,40.0]"
HALF = 100 * 51 / 101
"""COCO 101-point AP of one hit ranked first among 2 references: precision 1 up to recall 1/2."""


def test_values_are_vectors_or_first_numbers():
    assert parse_value("(10.0, -1.5)") == (10.0, -1.5)
    assert parse_value("There are 3 cars.") == 3.0
    assert parse_value("The car is at (2, 3), 4 m away.") == (2.0, 3.0)  # the vector wins
    assert parse_value("far away") is None
    assert regression_error((10.0, 1.0), "(12.0, 0.0)") == 1.5  # (|2| + |-1|) / 2
    assert regression_error(3.0, "5 cars") == 2.0
    assert regression_error((10.0, 1.0), "12") is None and regression_error(3.0, "(1, 2)") is None


def test_objects_parse_in_order_and_a_broken_one_is_malformed():
    assert parse_objects(f"{CAR};{PED}") == [
        RiskObject("car", "c1", (0.0, 0.0, 10.0, 10.0)),
        RiskObject("pedestrian", "c4", (20.0, 20.0, 30.0, 40.0)),
    ]
    assert parse_objects("<Car>[CAM_FRONT,10,10,0,0]") == [RiskObject("car", "CAM_FRONT", (0.0, 0.0, 10.0, 10.0))]
    assert parse_objects("There is no risk object.") == []
    assert parse_objects(f"{CAR};<truck>[c2,1,2]") is None


def test_class_labels():
    assert class_label(f"{PED}; {CAR}") == frozenset({("car", "c1"), ("pedestrian", "c4")})
    assert class_label("  Moving.  ") == "moving"
    assert class_label("") is None and class_label("<car>[c1,1]") is None


def test_regression_is_over_parsed_predictions():
    s = regression_scores(["(10.0, 1.0)", "3", "4"], ["(12.0, 0.0)", "5 cars", "no idea"])
    assert s.metrics["mae"] == pytest.approx((1.5 + 2.0) / 2)
    assert (s.samples, s.malformed, s.bad_answers) == (3, 1, 0)


def test_classification_accuracy():
    answers = [CAR, "Moving.", "Stopped.", f"{CAR};{PED}"]
    predictions = ["<car>[c1,3,3,9,9]", "moving", "Moving.", CAR]  # boxes do not count; the set must be equal
    s = classification_scores(answers, predictions)
    assert s.metrics["acc"] == 50.0
    assert (s.samples, s.malformed) == (4, 0)


def test_sample_ap_by_hand():
    two = parse_objects(f"{CAR};{PED}")
    assert sample_ap(two, parse_objects(CAR)) == pytest.approx(HALF)  # one of two found, at every IoU
    assert sample_ap(two, parse_objects("<car>[c2,0,0,10,10]")) == 0.0  # another camera
    assert sample_ap(two, parse_objects("<truck>[c1,0,0,10,10]")) == 0.0  # another class
    # IoU 0.62 (the box 10 x 6.2 inside 10 x 10): a hit at 0.50, 0.55, 0.60 of the ten thresholds
    assert sample_ap(parse_objects(CAR), parse_objects("<car>[c1,0,0,10,6.2]")) == pytest.approx(30.0)
    # a false alarm ranked first, then the hit: precision 1/2 at recall 1
    assert sample_ap(parse_objects(CAR), parse_objects(f"{PED};{CAR}")) == pytest.approx(50.0)


def test_risk_map_skips_nothing_to_report_and_counts_misses():
    answers = [f"{CAR};{PED}", CAR, "No risk object.", "No risk object.", CAR, CAR]
    predictions = [CAR, "<car>[c1,0,0,10,6.2]", "None.", CAR, "I do not know.", "<car>[c1,0,0]"]
    s = risk_scores(answers, predictions)
    # scored: HALF, 30, (skipped: both empty), 0 (false alarm), 0 (no object), 0 (broken list)
    assert s.metrics["map"] == pytest.approx((HALF + 30.0) / 5)
    assert (s.samples, s.empty, s.malformed, s.bad_answers) == (5, 1, 2, 0)


def test_per_subtask_is_the_mean_of_the_subtasks():
    rows = [
        {"category": "perception-distance", "answer": "(10.0, 1.0)", "prediction": "(12.0, 0.0)"},
        {"category": "perception-distance", "answer": "(0.0, 0.0)", "prediction": "(0.5, 0.5)"},
        {"category": "perception-instance_count", "answer": "3", "prediction": "5"},
    ]
    mean, by = per_subtask(rows, regression_scores, "mae")
    assert by["perception-distance"].metrics["mae"] == pytest.approx((1.5 + 0.5) / 2)
    assert by["perception-instance_count"].metrics["mae"] == 2.0
    assert mean == pytest.approx((1.0 + 2.0) / 2)  # not (1.5 + 0.5 + 2) / 3: each subtask weighs the same
