"""No-op stages for measuring what the platform itself costs (benchmarks only)."""

from __future__ import annotations

from gdwm.stage import StageContext, stage


def _touch(ctx: StageContext) -> None:
    (ctx.out_dir / "out.txt").write_text(ctx.key)


@stage("s1", "1", config=["stage.s1"])
def s1(ctx: StageContext) -> None:
    _touch(ctx)


@stage("s2", "1", config=["stage.s2"], upstream=["s1"])
def s2(ctx: StageContext) -> None:
    _touch(ctx)


@stage("s3", "1", config=["stage.s3"], upstream=["s2"])
def s3(ctx: StageContext) -> None:
    _touch(ctx)


@stage("s4", "1", config=["stage.s4"], upstream=["s3"])
def s4(ctx: StageContext) -> None:
    _touch(ctx)


@stage("s5", "1", config=["stage.s5"], upstream=["s4"])
def s5(ctx: StageContext) -> None:
    _touch(ctx)


@stage("s6", "1", config=["stage.s6"], upstream=["s5"])
def s6(ctx: StageContext) -> None:
    _touch(ctx)


# ---- a sweep's shape (bench_scale): one shared stage, then a fit and an evaluation per trial -----------------------
@stage("prep", "1", config=["stage.prep"])
def prep(ctx: StageContext) -> None:
    _touch(ctx)


@stage("fit", "1", config=["stage.fit"], upstream=["prep"])
def fit(ctx: StageContext) -> None:
    (ctx.out_dir / "x.txt").write_text(str(ctx.cfg("stage.fit")["x"]))


@stage("score", "1", config=["stage.score"], upstream=["fit"], evaluation=True)
def score(ctx: StageContext) -> dict:
    x = float((ctx.upstream["fit"].path / "x.txt").read_text())
    return {"nuinteract/plan_acc": x, "nuinteract/rdp_bleu": x / 2}
