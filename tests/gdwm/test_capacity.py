"""Resource shapes against the cluster's nodes: refused before launch, and the shipped a100x16 profile fits the
shipped KubeRay RayCluster."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from omegaconf import OmegaConf

from gdwm.capacity import GPU_SPEEDUP, Duration, Node, cluster_nodes, plan_capacity, shape_errors, stage_durations
from gdwm.config import load_config
from tests.k8s.render import build

ROOT = Path(__file__).resolve().parents[2]
STAGES = {"reconstruct": "gpu", "tokenizer": "train", "evaluate_qa": "eval", "llm": "cpu"}


def raycluster_nodes(overlay: Path) -> list[Node]:
    """The worker groups of the RayCluster that ``overlay`` renders, as Ray sees them (the head runs nothing)."""
    (rc,) = [o for o in build(overlay) if o["kind"] == "RayCluster"]
    head = rc["spec"]["headGroupSpec"]["rayStartParams"]
    assert head.get("num-cpus") == "0"  # drivers and the GCS only
    nodes = []
    for g in rc["spec"]["workerGroupSpecs"]:
        limits = g["template"]["spec"]["containers"][0]["resources"]["limits"]
        cpus = float(g["rayStartParams"].get("num-cpus", limits["cpu"]))
        nodes.append(Node(cpus, float(limits.get("nvidia.com/gpu", 0)), int(g["replicas"])))
    return nodes


def test_the_shipped_a100x16_profile_fits_the_shipped_raycluster_and_says_so():
    nodes = raycluster_nodes(ROOT / "k8s" / "overlays" / "a100x16")
    assert nodes == [Node(88.0, 8.0, 2)]
    cfg = load_config(["cluster=a100x16"])
    resources = OmegaConf.to_container(cfg.cluster.resources, resolve=True)
    assert shape_errors(STAGES, resources, nodes, "a100x16") == []
    assert cluster_nodes(cfg.cluster, live=False) == nodes  # the profile's own nodes are the RayCluster's
    # the train group fills both nodes exactly: 16 workers of 10 CPU + 1 GPU, 8 per node
    assert sum(n.fits(10, 1) * n.count for n in nodes) == resources["train"]["num_workers"] == 16


def test_impossible_shapes_are_named_with_the_largest_node():
    nodes = [Node(88, 8, 2)]
    res = {"gpu": {"num_cpus": 6, "num_gpus": 9, "num_workers": 16},
           "train": {"num_cpus": 10, "num_gpus": 1, "num_workers": 17},
           "eval": {"num_cpus": 2, "num_gpus": 0.25, "num_workers": 64}}  # fmt: skip
    assert shape_errors({"reconstruct": "gpu", "lora": "train", "evaluate_qa": "eval"}, res, nodes, "a100x16") == [
        "stage 'reconstruct': cluster.resources.gpu: 6 CPU, 9 GPU per task, which no node of cluster 'a100x16' can "
        "host (largest node: 88 CPU, 8 GPU)",
        "stage 'lora': a Ray Train group of 17 workers of 10 CPU, 1 GPU (cluster.resources.train) cannot be placed on "
        "cluster 'a100x16': its nodes hold at most 16 (nodes: 2 x 88 CPU, 8 GPU; largest: 88 CPU, 8 GPU)",
    ]
    in_driver = {"train": {"num_cpus": 99, "num_gpus": 9, "num_workers": 0}}
    assert shape_errors({"lora": "train"}, in_driver, nodes, "x") == []  # num_workers 0 runs in the driver


def test_a_launch_with_an_impossible_shape_exits_2_before_anything_starts(tmp_path):
    work = tmp_path / "w"
    args = ["run", f"workdir={work}", "targets=[distill]", "cluster.resources.gpu.num_cpus=4"]
    r = subprocess.run([sys.executable, "-m", "gdwm", *args], capture_output=True, text=True, timeout=300)
    assert r.returncode == 2, r.stderr[-2000:]
    assert (
        "gdwm run: stage 'reconstruct': cluster.resources.gpu: 4 CPU, 0 GPU per task, which no node of cluster "
        "'local' can host (largest node: 2 CPU, 0 GPU)"
    ) in r.stderr
    assert not work.exists()  # refused before the dataset was generated


def test_the_capacity_plan_runs_tasks_in_waves_and_counts_gpu_hours():
    nodes = [Node(88, 8, 2)]
    res = {"gpu": {"num_cpus": 6, "num_gpus": 1, "num_workers": 16},
           "train": {"num_cpus": 10, "num_gpus": 1, "num_workers": 16},
           "eval": {"num_cpus": 2, "num_gpus": 0.25, "num_workers": 64}}  # fmt: skip
    stages = {"reconstruct": ("gpu", True, 40), "lora": ("train", False, 3), "evaluate_qa": ("eval", False, 3)}
    d = {"reconstruct": Duration(60.0, "x"), "lora": Duration(600.0, "x")}
    plans = {p.stage: p for p in plan_capacity(stages, res, nodes, d)}
    rec, lora, ev = plans["reconstruct"], plans["lora"], plans["evaluate_qa"]
    assert (rec.at_once, rec.seconds, rec.gpu_hours) == (16, 3 * 60.0, 40 * 60 / 3600)  # 40 scenes, 16 at once
    assert (lora.width, lora.at_once, lora.seconds) == (16, 1, 3 * 600.0)  # one 16-worker group fills both nodes
    assert lora.gpu_hours == 3 * 600 * 16 / 3600 and lora.shape == "train: 10 CPU, 1 GPU x 16 workers"
    assert (ev.seconds, ev.gpu_hours, ev.source) == (None, None, "unknown")


def test_durations_come_from_the_clusters_own_runs_else_scaled_from_others():
    def run(stage, seconds, cluster=None, scenes=""):
        tags = {"gdwm.stage": stage, "gdwm.scenes": scenes} | ({"gdwm.cluster": cluster} if cluster else {})
        return {"tags": tags, "start_time": 1_000, "end_time": 1_000 + int(seconds * 1000)}

    runs = [run("reconstruct", 400, "local", "a,b,c,d"), run("lora", 100, "a100x16"), run("lora", 900, "local"),
            run("llm", 64, "local")]  # fmt: skip
    d = stage_durations(runs, "a100x16", {"reconstruct": True, "lora": True, "llm": False})
    assert d["lora"] == Duration(100.0, "measured on a100x16")
    assert d["reconstruct"] == Duration(400 / 4 / GPU_SPEEDUP, "scaled from other clusters' runs")
    assert d["llm"] == Duration(64.0, "scaled from other clusters' runs")  # asks no GPU: not sped up


def test_sweep_dry_run_prints_the_capacity_plan_from_a_durations_file(tmp_path):
    f = tmp_path / "d.json"
    f.write_text('{"reconstruct": 120, "llm": 60, "distill": 90, "tokenizer": 300, "lora": 600, "evaluate_qa": 30}')
    args = ["sweep", "--dry-run", "sweep=journal_ablation", "experiment=demo", "cluster=a100x16", "seeds=[0,1,2]",
            f"--durations={f}", f"workdir={tmp_path / 'w'}"]  # fmt: skip
    r = subprocess.run([sys.executable, "-m", "gdwm", *args], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    rows = {line.split("│")[1].strip(): [c.strip() for c in line.split("│")[2:-1]] for line in r.stdout.splitlines()
            if line.startswith("│") and "capacity" not in line and len(line.split("│")) == 9}  # fmt: skip
    # 4 scenes x 2 distinct distillations (✗ and ✓) x 1 (seed-free); 5 rows x 3 seeds of training, 16 workers each
    assert rows["reconstruct"] == ["gpu: 6 CPU, 1 GPU", "4", "4", "2.0 min", "0.13", "file d.json"]
    assert rows["distill"][:3] == ["gpu: 6 CPU, 1 GPU", "8", "8"]
    assert rows["lora"] == ["train: 10 CPU, 1 GPU x 16 workers", "15", "1", "150.0 min", "40.00", "file d.json"]
    assert rows["llm"][:2] == ["cpu: 4 CPU, 0 GPU", "3"]  # one LLM per seed, shared by the 5 rows
    out = " ".join(r.stdout.split())
    assert "capacity plan on cluster 'a100x16' (2 x 88 CPU, 8 GPU)" in out and "GPU-hours" in out
