"""The three understanding benchmarks end to end on the nuScenes fixture: convert, import each benchmark's released
QA, then one `gdwm sweep` trains the tiny flavors on each and evaluates it with the benchmark's own suite (the
demo's shape: reconstruct -> distill -> llm -> tokenizer -> lora -> evaluate_qa). The evaluation stage is what this
proves: every benchmark's metrics, labelled, with the report in the benchmark's layout. The metric code itself is held
to hand-computed values in tests/pipelines/evaluate."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from pipelines.data.nuinstruct import NuInstructConfig
from pipelines.data.nuinstruct import build as import_nuinstruct
from pipelines.data.nuinteract import NuInteractConfig
from pipelines.data.nuinteract import build as import_nuinteract
from pipelines.data.nuscenes import NuScenesConfig
from pipelines.data.nuscenes import build as convert
from pipelines.data.omnidrive import OmniDriveConfig
from pipelines.data.omnidrive import build as import_omnidrive
from tests.pipelines.conftest import gdwm_cli
from tests.pipelines.data.fixtures_benchmarks import write_nuinstruct, write_nuinteract, write_omnidrive
from tests.pipelines.data.fixtures_nuscenes import write_nuscenes

pytestmark = pytest.mark.heavy(1.5)

CHEAP = ["cluster.resources.gpu.num_workers=1", "cluster.resources.cpu.num_workers=1"]
"""One scene actor per per-scene stage: the three datasets' reconstructions run side by side on 2 CPUs."""
METRICS = {
    "NuInteract": {f"nuinteract/{k}" for k in ("rdp_bleu", "rdp_rouge_l", "rdp_cider", "vg2d_map", "vg2d_f1",
                                               "vg2d_miou", "vg3d_pr", "vg3d_map", "vg3d_f1", "plan_acc", "avg")},
    "NuInstruct": {f"nuinstruct/{k}" for k in ("mae", "acc", "map", "bleu", "average_star")},
    "OmniDrive": {f"omnidrive/{k}" for k in ("bleu", "cider", "rouge_l", "avg")},
}  # fmt: skip


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    """A workdir with the fixture's CAM_FRONT converted (64 x 36) and the three benchmarks imported on it."""
    work = tmp_path_factory.mktemp("bench") / "w"
    nus = write_nuscenes(work.parent / "nuscenes-src")
    base = convert(
        NuScenesConfig(width=64, height=36, cameras=["CAM_FRONT"]), work / "data" / "nuscenes", str(nus.root)
    )
    for build, cfg, write in [
        (import_nuinteract, NuInteractConfig, write_nuinteract),
        (import_nuinstruct, NuInstructConfig, write_nuinstruct),
        (import_omnidrive, OmniDriveConfig, write_omnidrive),
    ]:
        c = cfg(nuscenes=str(base))
        build(c, work / "data" / c.name, str(write(work.parent / f"{c.name}-src")))
    return work


def test_journal_ablation_plans_on_an_imported_benchmark(work):
    """The paper's sweep, unchanged, on NuInstruct's records with its suite: every row composes and plans."""
    r = gdwm_cli("sweep", "sweep=journal_ablation", "data=nuinstruct", "stage/evaluate_qa/suites=nuinstruct",
                 "model.selector.path=extrapolated", f"workdir={work}", "--dry-run")  # fmt: skip
    assert "sweep journal_ablation: 5 trials" in r.stdout
    assert "19 stage executions to run, 11 shared, 0 cached" in r.stdout


def test_each_benchmark_is_evaluated_with_its_own_suite(work):
    r = gdwm_cli("sweep", "sweep=tiny_benchmarks", f"workdir={work}", "compare=nuinstruct", *CHEAP, timeout=1800)
    evaluations = [json.loads(p.read_text()) for p in sorted((work / "cache" / "evaluate_qa").glob("*/*/metrics.json"))]
    by_benchmark = {b: m for m in evaluations for b, names in METRICS.items() if names <= set(m)}
    assert sorted(by_benchmark) == ["NuInstruct", "NuInteract", "OmniDrive"], r.stdout[-2000:]
    for benchmark, metrics in by_benchmark.items():
        others = {n for b, names in METRICS.items() if b != benchmark for n in names}
        assert not others & set(metrics), benchmark  # a benchmark's records feed its own suite only
        assert all(0 <= metrics[n] <= 100 or n.endswith(("mae", "cider")) for n in METRICS[benchmark])
    assert by_benchmark["NuInteract"]["count/answered"] == 5  # its 5 test records on scene-0002 (CAM_FRONT views)
    assert by_benchmark["NuInstruct"]["count/answered"] == 7
    assert by_benchmark["OmniDrive"]["count/answered"] == 2
    assert by_benchmark["NuInstruct"]["count/empty/nuinstruct/detection"] + by_benchmark["NuInstruct"][
        "count/nuinstruct/detection"] == 2  # fmt: skip
    protocols = [json.loads(p.read_text()) for p in (work / "cache" / "evaluate_qa").glob("*/*/protocol.json")]
    labels = {k: v.split(":")[0] for p in protocols for k, v in p.items()}
    assert labels["nuinstruct/map"] == labels["nuinteract/vg2d_map"] == "approximate"
    assert {labels[k] for k in ("omnidrive/bleu", "nuinteract/rdp_cider")} <= {"official", "approximate"}
    subtasks = [json.loads(p.read_text()) for p in (work / "cache" / "evaluate_qa").glob("*/*/subtasks.json")]
    assert len(subtasks) == 1 and set(subtasks[0]["nuinstruct/mae"]) <= {"perception-distance",
                                                                          "perception-instance_count"}  # fmt: skip
    report = (work / "reports" / "tiny_benchmarks" / "nuinstruct.md").read_text()  # compare= picked the layout
    assert "| row | Benchmark | MAE ↓ | Accuracy ↑ | mAP ↑ | BLEU ↑ | Average* ↑ |" in report
    assert "Approximate: MAE, Accuracy, mAP, Average*." in report
