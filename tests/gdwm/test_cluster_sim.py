"""``cluster=sim`` (gdwm.simcluster): a local multi-node Ray cluster with token auth, and a cluster address that
does not answer.

Placement is read from Ray's own actor table (the ``sim placement:`` line the driver prints before it stops the
cluster): per-scene stages run in ``SceneWorker`` actors, training groups in ``RayTrainWorker`` actors.
"""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import torch

from gdwm.cache import Cache
from gdwm.workerlogs import MARK
from tests.gdwm.servers import free_port
from tests.gdwm.test_run import REPO, Toy, _ok

pytestmark = pytest.mark.heavy(2.5)

SIM = ["cluster=sim", "run.live=false"]


def test_unreachable_address_exits_1_naming_it_within_30_s(tmp_path):
    port = free_port()  # bound and released: nothing listens there
    toy = Toy(tmp_path)
    start = time.monotonic()
    r = toy.run("cluster=a100x16", f"cluster.address=127.0.0.1:{port}")
    took = time.monotonic() - start
    assert r.returncode == 1, r.stderr
    assert took < 30, took
    assert r.stderr.strip().splitlines() == [
        f"gdwm run: cluster.address=127.0.0.1:{port}: no Ray cluster answers there (Connection refused within "
        "10 s); is the head up and the address right?"
    ]


_PROBE = textwrap.dedent(
    """
    import json, os, subprocess, sys, time
    import ray
    from gdwm.simcluster import SimCluster, SimConfig

    sim = SimCluster(SimConfig(nodes=2, node_cpus=1, node_gpus=1)).start()
    out = {"env": os.environ["RAY_AUTH_MODE"], "token_mode": oct(os.stat(sim.token_path).st_mode & 0o777)}
    try:
        ray.init(address=sim.address, include_dashboard=False, log_to_driver=False)

        @ray.remote(num_cpus=1, num_gpus=1)
        class Gpu:
            def node(self):
                return ray.get_runtime_context().get_node_id(), os.environ.get("CUDA_VISIBLE_DEVICES")

        actors = [Gpu.remote() for _ in range(2)]  # one GPU per node: one actor on each
        out["placed"] = ray.get([a.node.remote() for a in actors])
        out["nodes"] = [n.node_id for n in sim.nodes]
        out["placement"] = sim.describe_placement()
        # a node that joins without the cluster's token (RAY_AUTH_* unset: Ray's default for `ray start`)
        env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_AUTH")}
        ray_cli = os.path.join(os.path.dirname(sys.executable), "ray")
        r = subprocess.run([ray_cli, "start", "--address", sim.address, "--num-cpus=1"], env=env,
                           capture_output=True, text=True, timeout=120)
        out["join_rc"], out["join_err"] = r.returncode, (r.stdout + r.stderr)[-3000:]
        out["alive"] = sum(n["Alive"] for n in ray.nodes())
    finally:
        ray.shutdown()
        sim.stop()
    out["env_after"] = os.environ.get("RAY_AUTH_MODE")
    print("PROBE " + json.dumps(out))
    """
)


def _probe(code: str, tmp_path: Path, timeout: float) -> tuple[dict, subprocess.CompletedProcess]:
    """Run a probe script in a new Python (Ray started in the test process would outlive the test): the JSON of
    its ``PROBE `` line, and the process (its output)."""
    r = subprocess.run([sys.executable, "-c", code], env=Toy(tmp_path).env(), capture_output=True, text=True,
                       timeout=timeout)  # fmt: skip
    line = next((ln for ln in r.stdout.splitlines() if ln.startswith("PROBE ")), None)
    assert r.returncode == 0 and line, f"exit {r.returncode}\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"
    return json.loads(line.removeprefix("PROBE ")), r


def test_two_node_sim_places_gpu_actors_on_both_nodes_and_refuses_a_node_without_the_token(tmp_path):
    out, _ = _probe(_PROBE, tmp_path, timeout=240)
    assert out["env"] == "token" and out["token_mode"] == "0o600"
    assert sorted(n for n, _ in out["placed"]) == sorted(out["nodes"])  # one actor per worker node
    assert [gpu for _, gpu in out["placed"]] == ["0", "0"]  # each node's own (fake) GPU 0
    assert out["placement"] == "sim placement: sim-worker-1: Gpu x1; sim-worker-2: Gpu x1"
    assert out["join_rc"] != 0
    assert (
        "AuthenticationError: RPC error: InvalidAuthToken: Authentication token is missing or incorrect"
        in (out["join_err"])
    )
    assert out["alive"] == 3  # head + 2 workers: the refused node never joined
    assert out["env_after"] is None  # the auth environment is restored after stop


_STOP_PROBE = textwrap.dedent(
    """
    import json, logging, ray
    from ray._private import ray_constants, worker
    from gdwm.simcluster import stop_monitor

    ray.init(address="local", num_cpus=1, include_dashboard=False, logging_level=logging.WARNING)
    node = worker._global_node
    procs = {t: [i.process for i in infos] for t, infos in node.all_processes.items()}
    (monitor,) = procs[ray_constants.PROCESS_TYPE_MONITOR]
    stop_monitor(node)
    out = {"monitor_rc": monitor.returncode, "task": ray.get(ray.remote(lambda: 7).remote())}
    out["alive_before"] = sorted(t for t, ps in procs.items() for p in ps if p.poll() is None)
    ray.shutdown()
    out["alive_after"] = sorted(t for t, ps in procs.items() for p in ps if p.poll() is None)
    print("PROBE " + json.dumps(out))
    """
)


def test_stop_monitor_kills_only_the_autoscaler_monitor_and_the_node_still_serves_then_stops(tmp_path):
    out, r = _probe(_STOP_PROBE, tmp_path, timeout=120)
    assert out["monitor_rc"] == -signal.SIGKILL  # killed, so its SIGTERM handler never waits on a stopped GCS
    assert out["task"] == 7
    assert out["alive_before"] == ["dashboard", "gcs_server", "log_monitor", "raylet"]
    assert out["alive_after"] == []
    assert "autoscaler failed" not in r.stderr and "Terminated with signal" not in r.stderr


_DRAIN_PROBE = textwrap.dedent(
    """
    import json, logging, sys, ray
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy
    from gdwm.simcluster import SimCluster, SimConfig
    from gdwm.workerlogs import drain

    sim = SimCluster(SimConfig(nodes=2, node_cpus=1, node_gpus=0)).start()
    try:
        ray.init(address=sim.address, include_dashboard=False, log_to_driver=True, logging_level=logging.WARNING)

        @ray.remote(num_cpus=0)
        def say(i):
            print(f"said-{i}", file=sys.stderr if i % 2 else sys.stdout, flush=True)

        on = [NodeAffinitySchedulingStrategy(n.node_id, soft=False) for n in sim.nodes]
        ray.get([say.options(scheduling_strategy=on[i % 2]).remote(i) for i in range(4)])
        out = {"drained": drain(timeout_s=60)}
        ray.shutdown()
    finally:
        sim.stop()
    print("PROBE " + json.dumps(out))
    """
)


def test_drain_prints_every_line_workers_wrote_on_every_node_and_no_marker(tmp_path):
    """``run.worker_logs``: Ray shut down right after a stage no longer loses the stage's last lines."""
    out, r = _probe(_DRAIN_PROBE, tmp_path, timeout=240)
    assert out == {"drained": True}
    assert sorted(re.findall(r"said-\d", r.stdout)) == ["said-0", "said-2"], r.stdout
    assert sorted(re.findall(r"said-\d", r.stderr)) == ["said-1", "said-3"], r.stderr
    assert MARK.strip() not in r.stdout + r.stderr


def _placement(stdout: str) -> dict[str, dict[str, int]]:
    line = next(ln for ln in stdout.splitlines() if ln.startswith("sim placement: "))
    assert re.fullmatch(r"sim placement: [\w-]+: \w+ x\d+(, \w+ x\d+)*(; [\w-]+: \w+ x\d+(, \w+ x\d+)*)*", line), line
    out = {}
    for part in line.removeprefix("sim placement: ").split("; "):
        node, _, actors = part.partition(": ")
        out[node] = {a.rsplit(" x", 1)[0]: int(a.rsplit(" x", 1)[1]) for a in actors.split(", ")}
    return out


def test_toy_run_on_sim_uses_both_nodes_and_matches_local(tmp_path):
    sim, local = Toy(tmp_path / "sim"), Toy(tmp_path / "local")
    r = subprocess.run(sim.args("targets=[tokenizer]", *SIM), env=sim.env(), capture_output=True, text=True,
                       timeout=600)  # fmt: skip
    _ok(r)
    assert "sim cluster at " in r.stdout and "head + 2 worker node(s) x 2 CPU, 2 GPU, token auth on" in r.stdout
    if not torch.cuda.is_available():  # said once, on the cluster's line
        assert r.stdout.count("stages placed on GPUs run their CPU kernels") == 1
    placed = _placement(r.stdout)
    assert sorted(placed) == ["sim-worker-1", "sim-worker-2"]
    # reconstruct and distill: two scene actors each, spread over both nodes; the training group of 2
    assert sum(p.get("SceneWorker", 0) for p in placed.values()) == 4
    assert all(p.get("SceneWorker", 0) >= 1 for p in placed.values()), placed
    assert sum(p.get("RayTrainWorker", 0) for p in placed.values()) == 2
    assert not list((sim.work / "sim-cluster").glob("*.json"))  # the cluster's state file goes with it
    _ok(local.run("targets=[tokenizer]"))
    a, b = Cache(sim.work / "cache"), Cache(local.work / "cache")
    for stage in ("reconstruct", "distill", "tokenizer"):
        mine = sorted((m.key, m.scene, m.files) for m in a.entries(stage))
        assert mine == sorted((m.key, m.scene, m.files) for m in b.entries(stage)), stage
    runs = sim.runs()
    assert sorted(x.data.tags["gdwm.stage"] for x in runs) == ["distill", "reconstruct", "tokenizer"]
    assert {x.info.status for x in runs + sim.runs("run")} == {"FINISHED"}
    tok = next(x for x in runs if x.data.tags["gdwm.stage"] == "tokenizer")
    world = sim.client().download_artifacts(tok.info.run_id, "train/world.txt", str(tmp_path))
    assert Path(world).read_text() == "world_size=2"


def test_sim_yaml_nodes_follow_the_sim_shape():
    from gdwm.config import load_config

    c = load_config(["cluster=sim", "cluster.sim.nodes=3", "cluster.sim.node_gpus=4"]).cluster
    assert (c.sim.nodes, c.sim.node_cpus, c.sim.node_gpus) == (3, 2, 4)
    assert [dict(n) for n in c.nodes] == [{"num_cpus": 2.0, "num_gpus": 4.0, "count": 3}]
    assert REPO.joinpath("conf/cluster/sim.yaml").is_file()


def test_sigterm_stops_the_sim_cluster(tmp_path):
    toy = Toy(tmp_path)
    proc = subprocess.Popen(toy.args(*SIM), env=toy.env(GDWM_TEST_BLOCK="distill"), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        end = time.monotonic() + 300
        while not (tmp_path / "blocked-distill").exists():
            assert proc.poll() is None and time.monotonic() < end, proc.communicate()
            time.sleep(0.2)
        (state_file,) = (toy.work / "sim-cluster").glob("*.json")
        state = json.loads(state_file.read_text())
        start = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
        took = time.monotonic() - start
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 143, err[-3000:]
    assert took < 30, took
    assert "gdwm run: terminated (SIGTERM); temp directories removed, runs ended" in err
    assert not state_file.exists() and not Path(state["token_path"]).parent.exists()
    alive = [p for n in state["nodes"] for p in n["pids"] if Path(f"/proc/{p}").exists()]
    assert alive == []
    assert {r.info.status for r in toy.runs() + toy.runs("run")} <= {"KILLED", "FINISHED"}
