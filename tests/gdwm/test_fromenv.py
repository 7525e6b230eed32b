"""Which keys of a config come from the environment, and what gdwm records instead of their values."""

from __future__ import annotations

from gdwm.fromenv import env_keys, masked, restore, unshown


def test_env_keys_follow_interpolations_to_the_environment():
    raw = {
        "secrets": {"hf": "${oc.env:HF_TOKEN}", "plain": "x"},
        "stage": {
            "a": {"token": "${secrets.hf}", "header": "Bearer ${oc.env:HF_TOKEN,none}", "steps": 3},
            "b": {"copy": "${..a.token}", "all": "${secrets}", "other": "${stage.a.steps}", "path": "${abspath:.}"},
            "c": ["${oc.env:AWS_SECRET_ACCESS_KEY}", 1],
        },
    }
    assert env_keys(raw) == {
        "secrets.hf": "<env:HF_TOKEN>",
        "stage.a.header": "Bearer <env:HF_TOKEN>",
        "stage.a.token": "<secrets.hf>",
        "stage.b.all": "<secrets>",  # a subtree that holds a secret
        "stage.b.copy": "<..a.token>",  # relative
        "stage.c[0]": "<env:AWS_SECRET_ACCESS_KEY>",
    }


def test_masked_and_restored_subsets():
    subset = {"stage.a": {"token": "s3cret-value", "n": [1, "s3cret-too"]}, "seed": 0}
    from_env = {"stage.a.token": "<env:HF_TOKEN>", "stage.a.n[1]": "<env:X>", "stage.z": "<env:Y>"}
    shown = masked(subset, from_env)
    assert shown == {"stage.a": {"token": "<env:HF_TOKEN>", "n": [1, "<env:X>"]}, "seed": 0}
    assert subset["stage.a"]["token"] == "s3cret-value"  # a copy
    assert restore(shown, {"stage.a.token": "s3cret-value", "stage.a.n[1]": "s3cret-too"}) == subset


def test_a_recorded_config_reads_the_environment_again():
    # gdwm reproduce composes a run from its recorded config.yaml, which shows secrets as <env:NAME>
    recorded = {"stage": {"h": "Bearer <env:HF_TOKEN>", "l": ["<env:A_1>", 3], "n": 2, "s": "<not an env>"}}
    assert unshown(recorded) == {
        "stage": {"h": "Bearer ${oc.env:HF_TOKEN}", "l": ["${oc.env:A_1}", 3], "n": 2, "s": "<not an env>"}
    }
