"""``cluster=sim``: a multi-node Ray cluster on one machine, shaped like the real one, token auth on.

Ray's own test cluster (``ray.cluster_utils.Cluster``) starts a head node and ``sim.nodes`` worker nodes as
separate raylets on this machine. As on KubeRay, the head holds no CPUs or GPUs (the driver, the tracking actor
and the progress board live there); each worker node advertises ``sim.node_cpus`` CPUs and ``sim.node_gpus``
GPUs. The GPUs are Ray resources only: stages that ask for them are placed exactly as on the real cluster, and
where this machine has no CUDA they run their CPU kernels (training groups talk over gloo instead of NCCL).

The head generates a fresh token for this cluster (a 0600 file in the cluster's temp dir); the driver and every
node started here read it through ``RAY_AUTH_MODE=token`` and ``RAY_AUTH_TOKEN_PATH``, and a node that joins
without it is refused by the head.

``<workdir>/sim-cluster/<driver pid>.json`` says where the cluster is while it runs (removed on stop)::

    {"address": "10.0.0.5:43125", "token_path": "/tmp/gdwm-sim-x/auth_token",
     "nodes": [{"name": "sim-worker-1", "node_id": "ab12...", "raylet_pid": 1234, "pids": [1234, 1240]}, ...]}

so a rehearsal of a node loss is ``kill -9`` of one node's ``pids`` (what the node-loss tests do).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

from annotated_types import Ge, Gt

log = logging.getLogger(__name__)

FAKE_GPUS_ENV = "GDWM_FAKE_GPUS"
"""Set to 1 in every worker of a sim cluster whose GPUs have no CUDA behind them (``gdwm.training`` picks gloo)."""
_AUTH_ENV = ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN_PATH", "RAY_AUTH_TOKEN")


@dataclass
class SimConfig:
    """Shape of a ``cluster=sim`` cluster (``ClusterConfig.sim``)."""

    nodes: Annotated[int, Ge(1)] = 2
    """Worker nodes (the head node comes on top and holds no CPUs or GPUs, as a KubeRay head)."""
    node_cpus: Annotated[int, Ge(1)] = 2
    """Logical CPUs each worker node advertises (Ray resources: they may exceed this machine's cores)."""
    node_gpus: Annotated[int, Ge(0)] = 2
    """GPUs each worker node advertises; without CUDA here they are Ray resources only."""
    object_store_mb: Annotated[int, Ge(75)] = 200
    """Object store of each node, MiB (Ray's minimum is 75)."""
    health_check_s: Annotated[float, Gt(0)] = 1.0
    """How often the head checks each node; a node that misses 3 checks in a row is declared dead."""


@dataclass
class SimNode:
    name: str
    node_id: str
    raylet_pid: int
    pids: list[int] = field(default_factory=list)


class SimCluster:
    """``start()`` brings the cluster up (the caller then ``ray.init(address=cluster.address)``); ``stop()``
    tears every node down and restores this process's auth environment. Safe to stop twice."""

    def __init__(self, sim: SimConfig, state_dir: str | Path | None = None):
        self.sim = sim
        self.state_dir = Path(state_dir) if state_dir is not None else None
        self.cluster = None
        self.nodes: list[SimNode] = []
        # Short, under /tmp: Ray's unix sockets live in the session dir and their paths must stay under 108 bytes.
        self.tmp = Path(tempfile.mkdtemp(prefix="gdwm-sim-", dir="/tmp"))
        self.token_path = self.tmp / "auth_token"
        self._saved_env = {k: os.environ.get(k) for k in (*_AUTH_ENV, FAKE_GPUS_ENV)}
        self._token_mode_set = False

    @property
    def address(self) -> str:
        return self.cluster.address

    @property
    def state_file(self) -> Path | None:
        return self.state_dir / f"{os.getpid()}.json" if self.state_dir is not None else None

    def start(self) -> SimCluster:
        import ray
        from ray._private.authentication.authentication_token_generator import generate_new_authentication_token
        from ray._raylet import AuthenticationTokenLoader, Config
        from ray.cluster_utils import Cluster

        fd = os.open(self.token_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(generate_new_authentication_token())
        # Nodes started below inherit this process's environment; the driver's ray.init reads it too.
        os.environ.pop("RAY_AUTH_TOKEN", None)
        os.environ.update(RAY_AUTH_MODE="token", RAY_AUTH_TOKEN_PATH=str(self.token_path))
        if not _has_cuda():
            os.environ[FAKE_GPUS_ENV] = "1"
        Config.initialize("")  # this process's cached Ray config: token mode
        self._token_mode_set = True
        AuthenticationTokenLoader.instance().reset_cache()
        period_ms = max(100, int(self.sim.health_check_s * 1000))
        system = {"health_check_period_ms": period_ms, "health_check_timeout_ms": period_ms,
                  "health_check_failure_threshold": 3, "task_oom_retries": 0}  # fmt: skip
        mem = self.sim.object_store_mb * 1024 * 1024
        try:
            # shutdown_at_exit: the nodes share this process's fate (the kernel kills them if it dies, even by SIGKILL)
            self.cluster = Cluster(shutdown_at_exit=True)
            self.cluster.add_node(num_cpus=0, num_gpus=0, include_dashboard=False, object_store_memory=mem,
                                  node_name="sim-head", temp_dir=str(self.tmp), _system_config=system)  # fmt: skip
            for i in range(1, self.sim.nodes + 1):
                node = self.cluster.add_node(num_cpus=self.sim.node_cpus, num_gpus=self.sim.node_gpus,
                                             object_store_memory=mem, node_name=f"sim-worker-{i}")  # fmt: skip
                pids = sorted({p.process.pid for infos in node.all_processes.values() for p in infos})
                raylet = node.all_processes[ray._private.ray_constants.PROCESS_TYPE_RAYLET][0].process.pid
                self.nodes.append(SimNode(f"sim-worker-{i}", node.node_id, raylet, pids))
            self.cluster.wait_for_nodes()
        except BaseException:
            self.stop()
            raise
        self._write_state()
        return self

    def describe(self) -> str:
        """One line: where the cluster is and its shape."""
        s = self.sim
        cuda = "" if _has_cuda() else "; no CUDA here: stages placed on GPUs run their CPU kernels"
        return (f"sim cluster at {self.address}: head + {s.nodes} worker node(s) x {s.node_cpus} CPU, "
                f"{s.node_gpus} GPU, token auth on{cuda}")  # fmt: skip

    def placement(self) -> dict[str, dict[str, int]]:
        """Node name -> actor class -> how many ran there, from the head's actor table (Ray's own record, dead
        actors included); call it while this process is still connected. Per-scene stages run in ``SceneWorker``
        actors, training groups in ``RayTrainWorker`` actors."""
        import ray

        names = {n.node_id: n.name for n in self.nodes}
        out: dict[str, dict[str, int]] = {}
        # ray.util.state would need the dashboard, which the sim does not start; the GCS table is the same record
        for a in ray._private.state.actors().values():
            node = names.get(a["Address"]["NodeID"], "sim-head")
            counts = out.setdefault(node, {})
            counts[a["ActorClassName"]] = counts.get(a["ActorClassName"], 0) + 1
        return dict(sorted(out.items()))

    def describe_placement(self) -> str:
        """One line: ``sim placement: sim-worker-1: RayTrainWorker x2, SceneWorker x2; sim-worker-2: ...``."""
        for attempt in range(3):
            try:
                nodes = self.placement()
                break
            except Exception as e:  # the head already gone (a driver interrupted mid-teardown), or a slow GCS reply
                if attempt == 2:
                    return f"sim placement: unknown ({e!r})"
                time.sleep(1.0)
        placed = [
            f"{node}: " + ", ".join(f"{cls} x{n}" for cls, n in sorted(counts.items()))
            for node, counts in nodes.items()
            if node != "sim-head"
        ]
        return "sim placement: " + ("; ".join(placed) or "no actor ran on a worker node")

    def _write_state(self) -> None:
        if self.state_file is None:
            return
        self.state_file.parent.mkdir(parents=True, exist_ok=True)
        state = {"address": self.address, "token_path": str(self.token_path),
                 "nodes": [vars(n) for n in self.nodes]}  # fmt: skip
        tmp = self.state_file.with_suffix(".tmp")
        tmp.write_text(json.dumps(state, indent=1))
        tmp.rename(self.state_file)

    def stop(self) -> None:
        if self.cluster is not None:
            cluster, self.cluster = self.cluster, None
            for node in list(cluster.worker_nodes):
                try:
                    cluster.remove_node(node, allow_graceful=False)
                except Exception as e:  # a node killed from outside: its processes are gone already
                    log.debug("gdwm: sim node already gone: %r", e)
                    cluster.worker_nodes.discard(node)
            if cluster.head_node is not None:
                stop_monitor(cluster.head_node)
            try:
                cluster.shutdown()
            except Exception as e:
                log.warning("gdwm: sim cluster head did not stop cleanly: %r", e)
        if self.state_file is not None:
            self.state_file.unlink(missing_ok=True)
        for k, v in self._saved_env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        if self._token_mode_set:
            from ray._raylet import Config

            Config.initialize("")  # back to the auth mode this process had before
        shutil.rmtree(self.tmp, ignore_errors=True)


def stop_monitor(node) -> None:
    """SIGKILL the autoscaler monitor of a Ray head ``node`` (``ray._private.node.Node``) this process started, just
    before the node is shut down. Ray stops the GCS first and then SIGTERMs the monitor, whose handler reports its own
    end to the GCS that is gone until Ray's one-second grace runs out: 1.0 s of every local Ray's 1.3 s stop, in
    every launch. Killed first, it reports nothing (no driver is told the autoscaler failed) and Ray finds it gone.
    A node that started no monitor (one this process joined) is left as it is."""
    from ray._private import ray_constants

    for info in node.all_processes.get(ray_constants.PROCESS_TYPE_MONITOR, []):
        if info.process.poll() is None:
            info.process.kill()
            with contextlib.suppress(subprocess.TimeoutExpired):  # stuck in the kernel: Ray's own stop takes it on
                info.process.wait(timeout=10)


def _has_cuda() -> bool:
    try:
        import torch

        return torch.cuda.is_available()
    except ImportError:
        return False
