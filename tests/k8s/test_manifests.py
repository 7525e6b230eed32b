"""k8s/: every kustomization renders, validates, and says what the platform needs.

Core kinds are validated with kubernetes-validate (strict: unknown fields fail); KubeRay kinds with jsonschema
against the openAPIV3Schema of the CRDs in ``../shared/schemas/kuberay/`` or ``$GDWM_KUBERAY_CRDS``, unknown
fields failing as ``kubectl apply``'s strict field validation does. Rendering is tests/k8s/render.py, checked
against a kustomize binary where one is installed.
"""

from __future__ import annotations

import configparser
import functools
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import jsonschema
import kubernetes_validate
import pytest
import yaml

from tests.k8s.render import Obj, build, object_id

REPO = Path(__file__).resolve().parents[2]
K8S = REPO / "k8s"
KUSTOMIZATIONS = sorted(str(p.parent.relative_to(K8S)) for p in K8S.rglob("kustomization.yaml"))
OVERLAYS = [k for k in KUSTOMIZATIONS if k.startswith("overlays/")]
K8S_VERSION = "1.33"  # the oldest Kubernetes the manifests target (CronJob timeZone, RWX volumes, ...)
CRD_FILES = {"RayCluster": "ray.io_rayclusters.yaml", "RayJob": "ray.io_rayjobs.yaml"}
MOUNT = "/mnt/gdwm"  # the shared volume in every Ray pod
SECRET_ENV = re.compile(r"PASSWORD|SECRET|TOKEN|ACCESS_KEY|(^|_)KEY($|_)|CREDENTIAL|DATABASE_URI|STORE_URI")
URL_WITH_PASSWORD = re.compile(r"[a-z][a-z0-9+.-]*://[^/\s:@]+:([^@\s/]+)@")


@pytest.fixture(scope="module", params=KUSTOMIZATIONS)
def kustomization(request) -> str:
    return request.param


@pytest.fixture(scope="module")
def objs(kustomization: str) -> list[Obj]:
    return build(K8S / kustomization)


def crd_dir() -> Path | None:
    candidates = [Path(os.environ["GDWM_KUBERAY_CRDS"])] if os.environ.get("GDWM_KUBERAY_CRDS") else []
    candidates.append(REPO.parent / "shared" / "schemas" / "kuberay")
    return next((c for c in candidates if all((c / f).is_file() for f in CRD_FILES.values())), None)


def crd_validator(kind: str) -> jsonschema.Draft7Validator:
    directory = crd_dir()
    if directory is None:
        pytest.skip(
            f"no KubeRay CRDs ({', '.join(CRD_FILES.values())}) in $GDWM_KUBERAY_CRDS or ../shared/schemas/kuberay"
        )
    return _crd_validator(directory / CRD_FILES[kind])


@functools.cache
def _crd_validator(path: Path) -> jsonschema.Draft7Validator:
    crd = yaml.load(path.read_text(), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))  # 1 MB of YAML
    version = next(v for v in crd["spec"]["versions"] if v["name"] == "v1")
    return jsonschema.Draft7Validator(_closed(version["schema"]["openAPIV3Schema"]))


def _closed(schema: Any) -> Any:
    """Reject unknown fields, as the API server's strict field validation does (structural schemas only prune)."""
    if isinstance(schema, dict):
        out = {k: _closed(v) for k, v in schema.items()}
        if (
            "properties" in out
            and "additionalProperties" not in out
            and not out.get("x-kubernetes-preserve-unknown-fields")
        ):
            out["additionalProperties"] = False
        return out
    if isinstance(schema, list):
        return [_closed(s) for s in schema]
    return schema


def crd_errors(o: Obj) -> list[str]:
    errors = crd_validator(o["kind"]).iter_errors(o)
    return [f"{o['kind']}/{o['metadata'].get('name')} {e.json_path}: {e.message}" for e in errors]


def by_kind(objs: list[Obj], kind: str) -> list[Obj]:
    return [o for o in objs if o["kind"] == kind]


def one(objs: list[Obj], kind: str, name: str) -> Obj:
    (hit,) = [o for o in objs if o["kind"] == kind and o["metadata"]["name"] == name]
    return hit


def ray_cluster_specs(objs: list[Obj]) -> Iterator[tuple[str, Obj]]:
    """Every Ray cluster the manifests bring up: the standing RayCluster and each RayJob's own."""
    for o in objs:
        if o["kind"] == "RayCluster":
            yield f"RayCluster/{o['metadata']['name']}", o["spec"]
        elif o["kind"] == "RayJob":
            yield f"RayJob/{o['metadata']['name']}", o["spec"]["rayClusterSpec"]


def containers(node: Any, where: str = "") -> Iterator[tuple[str, Obj]]:
    """Every container and init container, wherever its pod template sits (CRDs, CronJobs, ...)."""
    if isinstance(node, dict):
        for key, value in node.items():
            if key in ("containers", "initContainers") and isinstance(value, list):
                for c in value:
                    yield f"{where}/{key}/{c.get('name')}", c
            else:
                yield from containers(value, f"{where}/{key}")
    elif isinstance(node, list):
        for i, item in enumerate(node):
            yield from containers(item, f"{where}/{i}")


def all_containers(objs: list[Obj]) -> Iterator[tuple[str, Obj]]:
    for o in objs:
        yield from containers(o, f"{o['kind']}/{o['metadata']['name']}")


def strings(node: Any) -> Iterator[str]:
    if isinstance(node, dict):
        for value in node.values():
            yield from strings(value)
    elif isinstance(node, list):
        for item in node:
            yield from strings(item)
    elif isinstance(node, str):
        yield node


def gpus(container: Obj) -> int:
    limits = container["resources"]["limits"]
    assert container["resources"]["requests"].get("nvidia.com/gpu") == limits.get("nvidia.com/gpu")
    return int(limits.get("nvidia.com/gpu", 0))


def cpus(quantity: str | int) -> float:
    text = str(quantity)
    return int(text[:-1]) / 1000 if text.endswith("m") else float(text)


def cluster_conf(name: str) -> dict[str, Any]:
    return yaml.safe_load((REPO / "conf" / "cluster" / f"{name}.yaml").read_text())


# ---------------------------------------------------------------- rendering


def test_every_manifest_is_rendered_by_a_kustomization():
    used: set[Path] = set()
    for k in KUSTOMIZATIONS:
        spec = yaml.safe_load((K8S / k / "kustomization.yaml").read_text())
        used |= {(K8S / k / r).resolve() for r in spec.get("resources", [])}
        used |= {(K8S / k / p["path"]).resolve() for p in spec.get("patches", []) if "path" in p}
    manifests = {p.resolve() for p in K8S.rglob("*.yaml") if p.name != "kustomization.yaml"}
    assert sorted(map(str, manifests - used)) == []
    assert KUSTOMIZATIONS == ["base", "overlays/a100x16", "overlays/local"]


def test_renders_into_one_namespace(kustomization, objs):
    assert len(objs) >= 12, kustomization
    assert {o["metadata"]["namespace"] for o in objs} == {"gdwm"}
    assert all(o["metadata"]["labels"]["app.kubernetes.io/part-of"] == "gdwm" for o in objs)


def _kustomize_binary() -> list[str] | None:
    if shutil.which("kustomize"):
        return ["kustomize", "build"]
    if shutil.which("kubectl"):
        return ["kubectl", "kustomize"]
    return None


def test_renderer_matches_the_kustomize_binary(kustomization, objs):
    cmd = _kustomize_binary()
    if cmd is None:
        pytest.skip("no kustomize binary (kustomize or kubectl) on PATH to compare tests/k8s/render.py with")
    out = subprocess.run([*cmd, str(K8S / kustomization)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    reference = {object_id(o): o for o in yaml.safe_load_all(out.stdout) if o}
    assert {object_id(o): o for o in objs} == reference


# ---------------------------------------------------------------- validation


def test_core_kinds_validate_against_kubernetes_schemas(objs):
    core = [o for o in objs if not o["apiVersion"].startswith("ray.io/")]
    errors = []
    for o in core:
        try:
            kubernetes_validate.validate(o, K8S_VERSION, strict=True)
        except kubernetes_validate.ValidationError as e:
            errors.append(f"{o['kind']}/{o['metadata']['name']} {e.caught.json_path}: {e.caught.message}")
    assert errors == []
    assert {"ConfigMap", "PersistentVolumeClaim", "Deployment", "Service", "NetworkPolicy", "CronJob"} <= {
        o["kind"] for o in core
    }


def test_kuberay_kinds_validate_against_the_crds(objs):
    ray = [o for o in objs if o["apiVersion"].startswith("ray.io/")]
    assert sorted(o["kind"] for o in ray) == ["RayCluster", "RayJob", "RayJob"]
    assert [e for o in ray for e in crd_errors(o)] == []


def test_crd_validation_rejects_a_misspelt_field():
    rc = one(build(K8S / "base"), "RayCluster", "gdwm")
    rc["spec"]["authOptions"]["mood"] = "token"
    rc["spec"]["workerGroupSpecs"][0]["replicas"] = "two"
    assert sorted(e.split(" ", 1)[1].split(":")[0] for e in crd_errors(rc)) == [
        "$.spec.authOptions",
        "$.spec.workerGroupSpecs[0].replicas",
    ]


# ---------------------------------------------------------------- what the cluster needs


def test_a100x16_brings_up_16_a100s_in_every_ray_cluster():
    objs = build(K8S / "overlays/a100x16")
    conf = cluster_conf("a100x16")
    specs = dict(ray_cluster_specs(objs))
    assert sorted(specs) == ["RayCluster/gdwm", "RayJob/gdwm-regress-nightly", "RayJob/gdwm-sweep"]
    for where, spec in specs.items():
        head = spec["headGroupSpec"]["template"]["spec"]["containers"][0]
        assert gpus(head) == 0, where
        total = max_total = 0
        for group in spec["workerGroupSpecs"]:
            pod = group["template"]["spec"]
            per_pod = gpus(pod["containers"][0]) * group.get("numOfHosts", 1)
            total += group["replicas"] * per_pod
            max_total += group["maxReplicas"] * per_pod
            assert pod["nodeSelector"] == {"nvidia.com/gpu.product": "NVIDIA-A100-SXM4-80GB"}, where
            assert {"key": "nvidia.com/gpu", "operator": "Exists", "effect": "NoSchedule"} in pod["tolerations"]
        assert (total, max_total) == (16, 16) == (conf["num_gpus"], conf["num_gpus"]), where


def test_a100x16_worker_pods_fit_every_resource_group_of_the_cluster_config():
    """conf/cluster/a100x16.yaml's Ray requests (e.g. 16 train workers x 10 CPUs + 1 GPU) fit the worker pods."""
    objs = build(K8S / "overlays/a100x16")
    conf = cluster_conf("a100x16")
    for where, spec in ray_cluster_specs(objs):
        (group,) = spec["workerGroupSpecs"]
        pods = group["replicas"]
        worker = group["template"]["spec"]["containers"][0]
        pod_cpus, pod_gpus = cpus(worker["resources"]["limits"]["cpu"]), gpus(worker)
        for name, r in conf["resources"].items():
            per_pod = -(-r["num_workers"] // pods)
            assert per_pod * r["num_cpus"] <= pod_cpus, f"{where}: {name} needs {per_pod * r['num_cpus']} CPUs/pod"
            assert per_pod * r["num_gpus"] <= pod_gpus, f"{where}: {name} needs {per_pod * r['num_gpus']} GPUs/pod"


def test_local_overlay_asks_for_no_gpu():
    objs = build(K8S / "overlays/local")
    assert [w for w, c in all_containers(objs) if "nvidia.com/gpu" in c["resources"]["limits"]] == []


def test_token_auth_is_on_in_every_ray_cluster(objs):
    for where, spec in ray_cluster_specs(objs):
        assert spec["authOptions"] == {"mode": "token", "secretName": "gdwm-ray-token"}, where
    modes = {e.get("value") for _, c in all_containers(objs) for e in c.get("env", []) if e["name"] == "RAY_AUTH_MODE"}
    assert modes <= {"token"}


def test_head_pods_are_not_safe_to_evict(objs):
    for where, spec in ray_cluster_specs(objs):
        annotations = spec["headGroupSpec"]["template"]["metadata"]["annotations"]
        assert annotations["cluster-autoscaler.kubernetes.io/safe-to-evict"] == "false", where


def test_every_container_has_resource_requests_and_limits(objs):
    found = list(all_containers(objs))
    assert len(found) >= 10  # head, worker and submitter of each Ray cluster, the CronJob's, MLflow's, ...
    missing = [
        f"{where} resources.{part}.{res}"
        for where, c in found
        for part in ("requests", "limits")
        for res in ("cpu", "memory")
        if res not in c.get("resources", {}).get(part, {})
    ]
    assert missing == []
    for where, spec in ray_cluster_specs(objs):
        if spec.get("enableInTreeAutoscaling"):  # the autoscaler sidecar KubeRay adds to the head
            assert set(spec["autoscalerOptions"]["resources"]) == {"requests", "limits"}, where


def test_no_secret_value_is_written_in_a_manifest(objs):
    assert by_kind(objs, "Secret") == []
    plain = [
        f"{where} env {e['name']}"
        for where, c in all_containers(objs)
        for e in c.get("env", [])
        if SECRET_ENV.search(e["name"]) and "secretKeyRef" not in e.get("valueFrom", {})
    ]
    assert plain == []
    leaked = [
        s
        for o in objs
        for s in strings(o)
        for m in URL_WITH_PASSWORD.finditer(s)
        if not re.fullmatch(r"\$\(\w+\)", m[1])
    ]
    assert leaked == []
    assert [
        s for o in objs for s in strings(o) if re.search(r"AKIA[0-9A-Z]{16}|-----BEGIN [A-Z ]*PRIVATE KEY", s)
    ] == []


def test_every_referenced_secret_key_is_created_in_the_readme(objs):
    readme = (REPO / "README.md").read_text()
    created = {
        (m["name"], key)
        for m in re.finditer(
            r"kubectl -n gdwm create secret generic (?P<name>[\w-]+)(?P<args>(?:[^\n]*\\\n)*[^\n]*)", readme
        )
        for key in re.findall(r"--from-literal=([\w.-]+)=", m["args"])
    }
    refs = {
        (e["valueFrom"]["secretKeyRef"]["name"], e["valueFrom"]["secretKeyRef"]["key"])
        for _, c in all_containers(objs)
        for e in c.get("env", [])
        if "secretKeyRef" in e.get("valueFrom", {})
    }
    refs |= {(s["authOptions"]["secretName"], "auth_token") for _, s in ray_cluster_specs(objs)}
    assert sorted(refs - created) == []


# ---------------------------------------------------------------- RayJobs and the nightly CronJob


def test_rayjob_templates(objs):
    jobs = {o["metadata"]["name"]: o["spec"] for o in by_kind(objs, "RayJob")}
    assert sorted(jobs) == ["gdwm-regress-nightly", "gdwm-sweep"]
    for job, spec in jobs.items():
        assert spec["suspend"] is True, job  # a template: applying the kustomization runs nothing
        assert spec["shutdownAfterJobFinishes"] is True, job
        assert spec["ttlSecondsAfterFinished"] >= 0, job
        assert spec["activeDeadlineSeconds"] > 0, job
        runtime_env = yaml.safe_load(spec["runtimeEnvYAML"])
        assert set(runtime_env) == {"env_vars"}, job  # the image has the wheel: no working_dir, pip or py_modules
    assert shlex.split(jobs["gdwm-sweep"]["entrypoint"])[:2] == ["gdwm", "sweep"]
    assert shlex.split(jobs["gdwm-regress-nightly"]["entrypoint"])[:3] == ["gdwm", "regress", "benchmark=nightly"]
    assert (jobs["gdwm-sweep"]["backoffLimit"], jobs["gdwm-regress-nightly"]["backoffLimit"]) == (2, 0)


@pytest.mark.parametrize("kustomization", OVERLAYS)
def test_rayjob_entrypoints_compose_and_join_the_kuberay_cluster(kustomization, monkeypatch):
    """Each entrypoint is a valid gdwm config that joins the RayJob's cluster and writes to the shared volume."""
    from gdwm.config import load_config

    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://gdwm-mlflow:5000")
    overlay = kustomization.rsplit("/", 1)[1]
    objs = build(K8S / kustomization)
    env = one(objs, "ConfigMap", "gdwm-env")["data"]
    for job in by_kind(objs, "RayJob"):
        argv = shlex.split(job["spec"]["entrypoint"])
        overrides = argv[2:]
        cfg = load_config(overrides)
        if argv[1] == "regress":  # gdwm regress composes the benchmark's overrides under the user's
            cfg = load_config([*cfg.benchmark.overrides, *overrides])
        where = job["metadata"]["name"]
        assert cfg.cluster.name == ("a100x16" if overlay == "a100x16" else "local"), where
        assert cfg.cluster.address == "auto", where  # joins the RayJob's cluster, never starts a Ray in the head pod
        assert cfg.tracking.name == "server" and cfg.tracking.uri == env["MLFLOW_TRACKING_URI"], where
        assert cfg.workdir.startswith(MOUNT + "/"), where
        assert cfg.cache.uri.startswith(("s3://", MOUNT + "/")), where
        head = job["spec"]["rayClusterSpec"]["headGroupSpec"]["template"]["spec"]["containers"][0]
        assert {"name": "shared", "mountPath": MOUNT} in head["volumeMounts"], where


FAKE_KUBECTL = """#!{python}
# kubectl for the CronJob's script: `get` answers with the template as the API server would, `patch --local`
# is the real kubectl where installed (an RFC 7386 merge otherwise), `create -f -` records what was created.
import json, os, subprocess, sys
args = sys.argv[1:]
if args[0] == "get":
    assert args[1:] == ["rayjob", "gdwm-regress-nightly", "-o", "json"], args
    sys.stdout.write(open(os.environ["FAKE_TEMPLATE"]).read())
elif args[0] == "patch":
    assert args[1:7] == ["--local", "-f", "-", "--type", "merge", "-o"] and args[7:9] == ["json", "-p"], args
    real = os.environ.get("REAL_KUBECTL")
    if real:
        sys.exit(subprocess.run([real, *args]).returncode)
    def merge(target, patch):
        if not isinstance(patch, dict):
            return patch
        out = dict(target) if isinstance(target, dict) else {{}}
        for k, v in patch.items():
            if v is None:
                out.pop(k, None)
            else:
                out[k] = merge(out.get(k), v)
        return out
    json.dump(merge(json.load(sys.stdin), json.loads(args[9])), sys.stdout)
elif args[0] == "create":
    assert args[1:] == ["-f", "-"], args
    open(os.environ["FAKE_CREATED"], "w").write(sys.stdin.read())
else:
    sys.exit(f"unexpected kubectl {{args}}")
"""


def test_nightly_cronjob_creates_the_regression_rayjob(objs, tmp_path):
    cron = one(objs, "CronJob", "gdwm-regress-nightly")
    assert cron["spec"]["concurrencyPolicy"] == "Forbid"
    pod = cron["spec"]["jobTemplate"]["spec"]["template"]["spec"]
    (container,) = pod["containers"]
    # Its ServiceAccount may read the template and create RayJobs, nothing else.
    binding = next(b for b in by_kind(objs, "RoleBinding") if b["subjects"][0]["name"] == pod["serviceAccountName"])
    assert binding["subjects"][0]["namespace"] == "gdwm"
    role = one(objs, "Role", binding["roleRef"]["name"])
    assert role["rules"] == [{"apiGroups": ["ray.io"], "resources": ["rayjobs"], "verbs": ["get", "create"]}]

    # Run the container's script against a kubectl that serves the template as the API server would.
    template = one(objs, "RayJob", "gdwm-regress-nightly")
    served = json.loads(json.dumps(template))
    served["metadata"].update(
        resourceVersion="4711",
        uid="0b7c",
        generation=1,
        creationTimestamp="2025-01-01T00:00:00Z",
        annotations={"kubectl.kubernetes.io/last-applied-configuration": "{}"},
    )
    served["status"] = {"jobDeploymentStatus": "Suspended"}
    (tmp_path / "template.json").write_text(json.dumps(served))
    fake = tmp_path / "bin" / "kubectl"
    fake.parent.mkdir()
    fake.write_text(FAKE_KUBECTL.format(python=sys.executable))
    fake.chmod(0o755)
    env = {
        "PATH": f"{fake.parent}{os.pathsep}{os.environ['PATH']}",
        "FAKE_TEMPLATE": str(tmp_path / "template.json"),
        "FAKE_CREATED": str(tmp_path / "created.json"),
        "REAL_KUBECTL": shutil.which("kubectl") or "",
        "HOME": str(tmp_path),
    }
    assert container["command"][0] == "/bin/sh"
    run = subprocess.run(
        [*container["command"], *container["args"]], env=env, capture_output=True, text=True, timeout=120
    )
    assert run.returncode == 0, run.stderr
    created = json.loads((tmp_path / "created.json").read_text())

    assert created["kind"] == "RayJob" and "name" not in created["metadata"]
    assert re.fullmatch(r"gdwm-nightly-\d{8}-", created["metadata"]["generateName"])
    assert created["metadata"]["namespace"] == "gdwm"
    assert created["metadata"]["labels"]["gdwm.io/role"] == "nightly"
    assert set(created["metadata"]) == {"generateName", "namespace", "labels"}
    assert "status" not in created
    assert created["spec"] == {**template["spec"], "suspend": False}
    if crd_dir() is not None:
        assert crd_errors(created) == []


# ---------------------------------------------------------------- MLflow server


@pytest.mark.filterwarnings("ignore:starlette.middleware.wsgi is deprecated")  # mlflow's import, not ours
def test_mlflow_server_auth_and_network_policy(objs, tmp_path, monkeypatch):
    deployment = one(objs, "Deployment", "gdwm-mlflow")
    pod = deployment["spec"]["template"]
    (container,) = pod["spec"]["containers"]
    secret_env = {e["name"]: e["valueFrom"]["secretKeyRef"] for e in container["env"] if "valueFrom" in e}
    assert {"MLFLOW_BACKEND_STORE_URI", "MLFLOW_AUTH_DATABASE_URI", "MLFLOW_FLASK_SERVER_SECRET_KEY"} <= set(secret_env)
    assert secret_env["MLFLOW_AUTH_ADMIN_PASSWORD"] == {"name": "gdwm-mlflow", "key": "admin-password"}
    config = one(objs, "ConfigMap", "gdwm-env")["data"]
    assert config["MLFLOW_ARTIFACTS_DESTINATION"].startswith("s3://")

    # The start script writes the auth ini from the Secret and execs the server; MLflow's own reader gets the URI back.
    database_uri = "postgresql://mlflow:p%40ss@gdwm-postgres:5432/mlflow_auth"
    fake = tmp_path / "bin" / "mlflow"
    fake.parent.mkdir()
    fake.write_text(f'#!/bin/sh\nprintf "%s\\n" "$@" > {tmp_path}/argv\n')
    fake.chmod(0o755)
    ini = tmp_path / "basic_auth.ini"
    env = {"PATH": f"{fake.parent}{os.pathsep}{os.environ['PATH']}", "MLFLOW_AUTH_DATABASE_URI": database_uri}
    env["MLFLOW_AUTH_CONFIG_PATH"] = str(ini)
    run = subprocess.run(
        [*container["command"], *container["args"]], env=env, capture_output=True, text=True, timeout=30
    )
    assert run.returncode == 0, run.stderr
    argv = (tmp_path / "argv").read_text().split()
    assert argv[0] == "server" and "--serve-artifacts" in argv
    assert argv[argv.index("--app-name") + 1] == "basic-auth"
    from mlflow.server.auth.config import read_auth_config

    monkeypatch.setenv("MLFLOW_AUTH_CONFIG_PATH", str(ini))
    monkeypatch.setenv("MLFLOW_AUTH_ADMIN_PASSWORD", "from-the-secret")
    auth = read_auth_config()
    assert (auth.database_uri, auth.admin_username, auth.admin_password) == (database_uri, "admin", "from-the-secret")
    written = configparser.ConfigParser(interpolation=None)
    written.read_string(ini.read_text())
    assert "admin_password" not in written["mlflow"]  # the admin password stays in the environment, from the Secret

    service = one(objs, "Service", "gdwm-mlflow")
    assert service["spec"]["selector"].items() <= pod["metadata"]["labels"].items()
    policy = one(objs, "NetworkPolicy", "gdwm-mlflow")
    assert policy["spec"]["podSelector"]["matchLabels"].items() <= pod["metadata"]["labels"].items()
    (ingress,) = policy["spec"]["ingress"]
    (source,) = ingress["from"]
    client_label = source["podSelector"]["matchLabels"]
    assert ingress["ports"] == [{"protocol": "TCP", "port": 5000}]
    # Every Ray pod (where drivers and workers log) carries the label the policy lets in.
    for where, spec in ray_cluster_specs(objs):
        for template in [spec["headGroupSpec"]["template"], *(g["template"] for g in spec["workerGroupSpecs"])]:
            assert client_label.items() <= template["metadata"]["labels"].items(), where


def test_dashboard_service_behind_mlflow_basic_auth(objs, monkeypatch):
    """The dashboard's Deployment runs `gdwm ui` on the server store with logins checked by the MLflow server, its
    Service selects it, and its arguments compose (exit 2 before anything would serve otherwise)."""
    pod = one(objs, "Deployment", "gdwm-dashboard")["spec"]["template"]
    (container,) = pod["spec"]["containers"]
    assert container["command"] == ["gdwm", "ui"]
    args = container["args"]
    assert {"tracking=server", "ui.auth=mlflow", "ui.host=0.0.0.0", "ui.port=8080"} <= set(args)
    secret_env = {e["name"]: e["valueFrom"]["secretKeyRef"] for e in container["env"] if "valueFrom" in e}
    assert secret_env["MLFLOW_TRACKING_USERNAME"] == {"name": "gdwm-mlflow-client", "key": "username"}
    assert secret_env["MLFLOW_TRACKING_PASSWORD"] == {"name": "gdwm-mlflow-client", "key": "password"}
    service = one(objs, "Service", "gdwm-dashboard")
    assert service["spec"]["selector"].items() <= pod["metadata"]["labels"].items()
    assert service["spec"]["ports"][0]["targetPort"] == "http"
    assert container["readinessProbe"]["httpGet"]["path"] == "/health"
    policy = one(objs, "NetworkPolicy", "gdwm-dashboard")
    assert policy["spec"]["podSelector"]["matchLabels"].items() <= pod["metadata"]["labels"].items()
    monkeypatch.setenv("MLFLOW_TRACKING_URI", one(objs, "ConfigMap", "gdwm-env")["data"]["MLFLOW_TRACKING_URI"])
    from gdwm.config import load_config

    cfg = load_config(args)
    assert (cfg.tracking.uri, str(cfg.ui.auth), cfg.ui.port) == ("http://gdwm-mlflow:5000", "mlflow", 8080)


# ---------------------------------------------------------------- the image


def test_dockerfile_installs_the_wheel_with_matching_ray_and_mlflow():
    import mlflow
    import ray
    import torch

    from gdwm.environment.lock import read_lock

    dockerfile = (K8S / "Dockerfile").read_text()
    version = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["version"]
    py = f"py{sys.version_info.major}{sys.version_info.minor}"
    assert re.search(rf"^ARG RAY_VERSION={re.escape(ray.__version__)}$", dockerfile, re.M)
    assert re.search(rf"^ARG PYTHON_TAG={py}$", dockerfile, re.M)
    assert re.search(rf"^ARG LOCK_PLATFORM=linux-x86_64-{py}$", dockerfile, re.M)
    assert "FROM rayproject/ray:${RAY_VERSION}-${PYTHON_TAG}-gpu" in dockerfile
    assert "pip wheel --no-deps" in dockerfile
    # every version from a lock, hash-checked: the Ray image's (CUDA torch) and the MLflow server's
    assert "pip install --no-cache-dir --require-hashes -r /opt/gdwm/locks/cuda-${LOCK_PLATFORM}.txt" in dockerfile
    assert "pip install --no-cache-dir --require-hashes -r /tmp/mlflow.lock" in dockerfile
    assert "--no-deps /tmp/wheels/gdwm-*.whl" in dockerfile
    cuda = read_lock(REPO / "locks" / f"cuda-linux-x86_64-{py}.txt")
    server = read_lock(REPO / "locks" / f"mlflow-linux-x86_64-{py}.txt")
    assert cuda.pins["ray"] == ray.__version__
    assert cuda.pins["torch"] == torch.__version__.split("+")[0]
    assert cuda.pins["mlflow"] == server.pins["mlflow"] == mlflow.__version__
    for kustomization in KUSTOMIZATIONS:
        objs = build(K8S / kustomization)
        images = {c["image"] for _, c in all_containers(objs)}
        ours = {i for i in images if re.search(r"(^|/)gdwm(-mlflow)?:", i)}
        assert {i.rsplit(":", 1)[1] for i in ours} == {version}, kustomization
        for where, spec in ray_cluster_specs(objs):
            assert spec["rayVersion"] == ray.__version__, where
