import pytest

from pipelines.data.synth.planning import DIRECTION_DECISIONS, SPEED_DECISIONS
from pipelines.evaluate.planning import decision_accuracy, parse_decision, parse_number, regression_mae

LABELS = SPEED_DECISIONS + DIRECTION_DECISIONS


def test_parse_decision():
    assert parse_decision("Turn left. Reason: the road bends to the left.") == "turn left"
    assert parse_decision("  Keep   speed . Reason: x", LABELS) == "keep speed"
    assert parse_decision("Slow down. Reason: x", LABELS) is None
    assert parse_decision("Slow down. Reason: x") == "slow down"
    assert parse_decision("") is None


def test_decision_accuracy_counts_malformed_as_wrong():
    answers = ["Accelerate. Reason: a", "Turn left. Reason: b", "Stop. Reason: c", "Go straight. Reason: d"]
    predictions = ["Accelerate. Reason: z", "Turn right. Reason: b", "", "Slow down."]
    s = decision_accuracy(answers, predictions, LABELS)
    assert s.metrics == {"acc": 25.0}
    assert (s.samples, s.malformed) == (4, 2)


def test_parse_number():
    assert parse_number("The object is approximately 12.3 meters away.") == 12.3
    assert parse_number("-4.5e1 m") == -45.0
    assert parse_number("far away") is None


def test_regression_mae_leaves_malformed_out_and_counts_them():
    answers = [f"The object is approximately {d} meters away from the ego vehicle." for d in (10.0, 20.0, 30.0)]
    s = regression_mae(answers, ["12.0 m", "far away", "The object is approximately 27.5 meters away."])
    assert s.metrics["mae"] == pytest.approx((2.0 + 2.5) / 2)
    assert (s.samples, s.malformed) == (3, 1)
    none_parsed = regression_mae(answers[:1], ["unknown"])
    assert none_parsed.metrics == {} and none_parsed.malformed == 1


def test_first_named_decision():
    labels = ["go straight", "turn left", "turn right"]
    assert parse_decision("The ego car should go straight.", labels, "first") == "go straight"
    assert parse_decision("Turn right, then turn left.", labels, "first") == "turn right"
    assert parse_decision("It should not go straightforward.", labels, "first") is None  # whole words only
    assert parse_decision("Stop.", labels, "first") is None
    s = decision_accuracy(["Go straight.", "Turn left now."], ["We go straight ahead.", "turn right"], labels, "first")
    assert s.metrics == {"acc": 50.0} and s.malformed == 0
    with pytest.raises(ValueError, match="match='first' needs the labels"):
        parse_decision("Go straight.", None, "first")
