import pytest

from pipelines.evaluate.grounding import average_precision, box_iou, parse_box, parse_centre_size, score_2d, score_3d

GT = "<CAM_FRONT> <box>(0,0),(10,10)</box>"
GT3 = "center: (10.00, 0.00, 0.50), size: (4.00, 2.00, 1.50)"


def test_parse_box_tolerates_spaces_floats_and_camera_tag():
    assert parse_box(GT) == ("CAM_FRONT", (0.0, 0.0, 10.0, 10.0))
    assert parse_box("here: <box>( 10.5 , 20 ),( 30 ,40.25)</box>.") == (None, (10.5, 20.0, 30.0, 40.25))
    assert parse_box("<CAM_BACK><box>(30,40),(10,20)</box>") == ("CAM_BACK", (10.0, 20.0, 30.0, 40.0))
    assert parse_box("<box>(10,20)</box>") is None
    assert parse_box("") is None


def test_parse_centre_size():
    assert parse_centre_size(GT3) == ((10.0, 0.0, 0.5), (4.0, 2.0, 1.5))
    assert parse_centre_size("Centre:(1,-2.5,3)") == ((1.0, -2.5, 3.0), None)
    assert parse_centre_size("size: (1, 2, 3)") is None


def test_box_iou_by_hand():
    assert box_iou((0, 0, 10, 10), (0, 0, 10, 10)) == 1.0
    assert box_iou((0, 0, 10, 10), (5, 0, 15, 10)) == pytest.approx(50 / 150)  # half of each box overlaps
    assert box_iou((0, 0, 10, 10), (20, 20, 30, 30)) == 0.0
    assert box_iou((0, 0, 0, 0), (0, 0, 0, 0)) == 0.0


def test_average_precision_coco_interpolation_by_hand():
    # hits T, F, T of 4 ground truths: recall .25, .25, .5; precision envelope 1, 2/3, 2/3
    # -> recall points 0.00..0.25 (26) at 1, 0.26..0.50 (25) at 2/3, the rest 0
    assert average_precision([True, False, True], 4) == pytest.approx(100 * (26 + 25 * 2 / 3) / 101)
    assert average_precision([True, True], 2) == pytest.approx(100.0)
    assert average_precision([], 3) == 0.0


def test_score_2d_by_hand():
    answers = [GT] * 4 + ["no box here"]
    predictions = [
        "<CAM_FRONT> <box>(0,0),(10,10)</box>",  # IoU 1
        "<CAM_FRONT> <box>(5,0),(15,10)</box>",  # IoU 1/3: a false positive
        "<box>(0,0),(10,7.8)</box>",  # IoU 0.78: a hit up to threshold 0.75
        "I cannot find it.",  # malformed: a miss, IoU 0
        "<box>(0,0),(10,10)</box>",  # reference unparsable: skipped
    ]
    s = score_2d(answers, predictions)
    assert (s.samples, s.malformed, s.bad_answers) == (4, 1, 1)
    ap_low = (26 + 25 * 2 / 3) / 101  # thresholds 0.50..0.75: hits T, F, T
    ap_high = 26 / 101  # thresholds 0.80..0.95: hits T, F, F
    assert s.metrics["map"] == pytest.approx(100 * (6 * ap_low + 4 * ap_high) / 10)
    # precision 2/3 (parsed boxes), recall 2/4 -> F1 4/7
    assert s.metrics["f1"] == pytest.approx(100 * 4 / 7)
    assert s.metrics["miou"] == pytest.approx(100 * (1 + 1 / 3 + 0.78 + 0) / 4)


def test_score_2d_other_camera_is_a_parsed_miss():
    s = score_2d([GT, GT], ["<CAM_BACK> <box>(0,0),(10,10)</box>", "<box>(0,0),(10,10)</box>"])
    assert s.malformed == 0
    assert s.metrics["miou"] == pytest.approx(50.0)
    assert s.metrics["f1"] == pytest.approx(50.0)  # precision 1/2, recall 1/2
    assert s.metrics["map"] == pytest.approx(100 * 51 / 101 / 2)  # hits F, T: precision 1/2 up to recall 1/2


def test_score_3d_thresholds_by_hand():
    predictions = [
        "center: (10.30, 0.00, 0.50), size: (4, 2, 1.5)",  # 0.3 m
        "center: (11.50, 0.00, 9.00), size: (4, 2, 1.5)",  # 1.5 m (z is not scored)
        "center: (10.00, 3.00, 0.50)",  # 3 m
        "somewhere ahead",  # malformed
        "center: (20.00, 0.00, 0.50), size: (4, 2, 1.5)",  # 10 m
    ]
    s = score_3d([GT3] * 5, predictions)
    assert (s.samples, s.malformed, s.bad_answers) == (5, 1, 0)
    # 5 ground truths; hits per threshold: 0.5 m and 1 m: T F F F; 2 m: T T F F; 4 m: T T T F
    assert s.metrics["map"] == pytest.approx(100 * (21 + 21 + 41 + 61) / 101 / 4)
    assert s.metrics["precision"] == pytest.approx(50.0)  # 2 of 4 parsed within 2 m
    assert s.metrics["f1"] == pytest.approx(100 * 2 * 0.5 * 0.4 / 0.9)  # recall 2/5


def test_empty_and_all_malformed():
    assert score_2d([], []).metrics == {}
    s = score_3d([GT3, GT3], ["", "no idea"])
    assert s.metrics == {"map": 0.0, "precision": 0.0, "f1": 0.0}
    assert s.malformed == 2


def test_internvl_boxes_parse_like_ours():
    assert parse_box("<ref>car</ref><box>[[420, 380, 610, 520]]</box>") == (None, (420.0, 380.0, 610.0, 520.0))
    assert parse_box("<CAM_FRONT> <box>[[610, 520, 420, 380], [1, 2, 3, 4]]</box>") == (
        "CAM_FRONT",
        (420.0, 380.0, 610.0, 520.0),
    )  # the first box of the list, corners ordered
    assert parse_box("<box>[[1, 2, 3]]</box>") is None
