"""Test-only stages of the model-zoo tests: ``zoo_train`` registers a component, ``zoo_use`` reads one from the zoo."""

from __future__ import annotations

import json
import shutil

from gdwm.stage import StageContext, stage


@stage("zoo_train", "1", config=["stage.toy_zoo_train"])
def zoo_train(ctx: StageContext) -> dict:
    """Bytes that depend on ``value``, registered as ``gdwm-toy``; ``fail: true`` raises after registering."""
    c = ctx.cfg("stage.toy_zoo_train")
    model = ctx.out_dir / "model"
    (model / "sub").mkdir(parents=True)
    (model / "sub" / "weights.bin").write_bytes(bytes(range(c["value"], c["value"] + 16)))
    (model / "meta.json").write_text(json.dumps({"value": c["value"]}))
    ctx.register("gdwm-toy", "model", f"toy-v{c['value']}", {"toy.note": "from a test"})
    if c["fail"]:
        raise ValueError("injected failure after ctx.register")
    return {"score": c["value"] / 10, "label": "not a metric"}


@stage("zoo_use", "1", config=["stage.toy_zoo_use"])
def zoo_use(ctx: StageContext) -> dict:
    """Copies the zoo version's ``meta.json`` into its output."""
    source = ctx.cfg("stage.toy_zoo_use")["source"]
    shutil.copy(ctx.zoo_path(source) / "meta.json", ctx.out_dir / "meta.json")
    return {"source": source}
