"""k8s/: least privilege (issue 16 item 9). Every pod runs as a non-root user with RuntimeDefault seccomp, no
privilege escalation and no capabilities; pods that never call the Kubernetes API mount no service-account
token; ingress is denied by default and each server lets in exactly its clients.

Checked on the rendered YAML only (no KubeRay CRDs, cluster or CNI needed): NetworkPolicy semantics are evaluated
here for pod selectors (matchLabels, matchExpressions) and namespace selectors (on kubernetes.io/metadata.name).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from tests.k8s.render import Obj, _split_image, build
from tests.k8s.test_manifests import K8S, KUSTOMIZATIONS, all_containers, by_kind, one

NAMESPACE = "gdwm"
# The image's user of every image the manifests run: (runAsUser, runAsGroup).
IMAGE_USERS = {
    "gdwm": (1000, 100),  # rayproject/ray: user ray, group users
    "gdwm-mlflow": (10001, 10001),  # USER 10001 in k8s/Dockerfile's mlflow stage
    "postgres": (999, 999),  # the official image's postgres
    "minio": (1000, 1000),  # any user that owns the data volume (fsGroup)
    "mc": (1000, 1000),
    "alpine/k8s": (65534, 65534),  # nobody
}
# Containers whose root filesystem stays writable, each for a reason written beside it in the manifest.
WRITABLE_ROOT = {"ray-head", "ray-worker"}
# Pods that call the Kubernetes API: the nightly CronJob creates RayJobs with its own ServiceAccount.
API_CLIENTS = {"CronJob/gdwm-regress-nightly"}


@pytest.fixture(scope="module", params=KUSTOMIZATIONS)
def objs(request) -> list[Obj]:
    return build(K8S / request.param)


def pod_templates(objs: list[Obj]) -> Iterator[tuple[str, Obj]]:
    """Every pod template of every workload kind, KubeRay's included."""
    for o in objs:
        where = f"{o['kind']}/{o['metadata']['name']}"
        spec = o.get("spec", {})
        if o["kind"] in ("Deployment", "StatefulSet", "Job", "DaemonSet", "ReplicaSet"):
            yield where, spec["template"]
        elif o["kind"] == "CronJob":
            yield where, spec["jobTemplate"]["spec"]["template"]
        elif o["kind"] in ("RayCluster", "RayJob"):
            cluster = spec if o["kind"] == "RayCluster" else spec["rayClusterSpec"]
            if o["kind"] == "RayJob":
                yield f"{where}/submitter", spec["submitterPodTemplate"]
            yield f"{where}/head", cluster["headGroupSpec"]["template"]
            for g in cluster["workerGroupSpecs"]:
                yield f"{where}/{g['groupName']}", g["template"]


def is_ray_node(where: str) -> bool:
    """A Ray cluster's head or worker pod (not a RayJob's submitter)."""
    return where.startswith(("RayCluster/", "RayJob/")) and not where.endswith("/submitter")


def ray_templates(objs: list[Obj]) -> list[tuple[str, Obj]]:
    return [(w, t) for w, t in pod_templates(objs) if w.startswith(("RayCluster/", "RayJob/"))]


def image_user(image: str) -> tuple[int, int]:
    repo, _ = _split_image(image)
    for name, ids in IMAGE_USERS.items():
        if repo == name or repo.endswith("/" + name):
            return ids
    raise AssertionError(f"no known user for image {image}")


def test_every_container_sits_in_a_known_pod_template(objs):
    in_templates = sum(
        len(t["spec"]["containers"]) + len(t["spec"].get("initContainers", [])) for _, t in pod_templates(objs)
    )
    assert in_templates == len(list(all_containers(objs)))


def test_every_pod_runs_as_the_images_non_root_user_with_runtime_default_seccomp(objs):
    bad = []
    for where, template in pod_templates(objs):
        pod = template["spec"]
        sc = pod.get("securityContext", {})
        images = {image_user(c["image"]) for c in pod["containers"]}
        assert len(images) == 1, where
        ((uid, gid),) = images
        want = {"runAsNonRoot": True, "runAsUser": uid, "runAsGroup": gid, "fsGroup": gid}
        got = {k: sc.get(k) for k in want}
        if got != want:
            bad.append(f"{where}: {got} != {want}")
        if sc.get("seccompProfile") != {"type": "RuntimeDefault"}:
            bad.append(f"{where}: seccompProfile {sc.get('seccompProfile')}")
    assert bad == []


def test_every_container_drops_all_capabilities_and_privilege_escalation(objs):
    bad = []
    for where, template in pod_templates(objs):
        volumes = {v["name"]: v for v in template["spec"].get("volumes", [])}
        for c in template["spec"]["containers"] + template["spec"].get("initContainers", []):
            name = f"{where}/{c['name']}"
            sc = c.get("securityContext", {})
            if sc.get("allowPrivilegeEscalation") is not False:
                bad.append(f"{name}: allowPrivilegeEscalation {sc.get('allowPrivilegeEscalation')}")
            if sc.get("capabilities") != {"drop": ["ALL"]}:
                bad.append(f"{name}: capabilities {sc.get('capabilities')}")
            if sc.get("privileged"):
                bad.append(f"{name}: privileged")
            want_ro = c["name"] not in WRITABLE_ROOT
            if sc.get("readOnlyRootFilesystem") is not want_ro:
                bad.append(f"{name}: readOnlyRootFilesystem {sc.get('readOnlyRootFilesystem')} (want {want_ro})")
            if want_ro:  # a writable /tmp, from a volume of the pod
                tmp = [m for m in c.get("volumeMounts", []) if m["mountPath"] == "/tmp"]
                if not (tmp and "emptyDir" in volumes.get(tmp[0]["name"], {})):
                    bad.append(f"{name}: no emptyDir on /tmp")
    assert bad == []


def test_the_autoscaler_sidecar_is_locked_down_and_alone_gets_an_api_token(objs):
    for rc in by_kind(objs, "RayCluster"):
        spec = rc["spec"]
        if not spec.get("enableInTreeAutoscaling"):
            continue
        options = spec["autoscalerOptions"]
        sc = options.get("securityContext", {})
        assert sc["allowPrivilegeEscalation"] is False and sc["capabilities"] == {"drop": ["ALL"]}
        head = spec["headGroupSpec"]["template"]["spec"]
        assert head.get("automountServiceAccountToken") is False
        (mount,) = [m for m in options["volumeMounts"] if m["mountPath"].startswith("/var/run/secrets/kubernetes.io")]
        assert mount["mountPath"] == "/var/run/secrets/kubernetes.io/serviceaccount" and mount["readOnly"] is True
        (volume,) = [v for v in head["volumes"] if v["name"] == mount["name"]]
        sources = volume["projected"]["sources"]
        assert {"path": "token", "expirationSeconds": 3607} in [s.get("serviceAccountToken") for s in sources]
        assert any(s.get("configMap", {}).get("name") == "kube-root-ca.crt" for s in sources)
        # The Ray containers themselves mount no token.
        for c in head["containers"]:
            assert mount["name"] not in {m["name"] for m in c.get("volumeMounts", [])}


def test_only_kubernetes_api_clients_mount_a_service_account_token(objs):
    ray = ray_templates(objs)
    assert len(ray) >= 8  # head, workers and submitter of every RayJob; head and workers of the RayCluster
    mounted = []
    for where, template in pod_templates(objs):
        if template["spec"].get("automountServiceAccountToken") is not False:
            mounted.append(where)
    assert sorted(mounted) == sorted(a for a in API_CLIENTS if a in {w for w, _ in pod_templates(objs)})
    for where, template in ray:
        assert template["spec"]["automountServiceAccountToken"] is False, where


# ---------------------------------------------------------------- NetworkPolicies


def _selects(selector: dict[str, Any], labels: dict[str, str]) -> bool:
    if not selector.get("matchLabels", {}).items() <= labels.items():
        return False
    for e in selector.get("matchExpressions", []):
        key, op, values = e["key"], e["operator"], e.get("values", [])
        ok = {
            "Exists": key in labels,
            "DoesNotExist": key not in labels,
            "In": labels.get(key) in values,
            "NotIn": key not in labels or labels[key] not in values,
        }[op]
        if not ok:
            return False
    return True


def _peer_matches(peer: dict[str, Any], labels: dict[str, str], namespace: str) -> bool:
    if "ipBlock" in peer:
        return False
    if "namespaceSelector" in peer:
        if not _selects(peer["namespaceSelector"], {"kubernetes.io/metadata.name": namespace}):
            return False
    elif namespace != NAMESPACE:
        return False
    return _selects(peer.get("podSelector", {}), labels)


def selecting(objs: list[Obj], labels: dict[str, str]) -> list[Obj]:
    return [
        p
        for p in by_kind(objs, "NetworkPolicy")
        if "Ingress" in p["spec"].get("policyTypes", ["Ingress"]) and _selects(p["spec"]["podSelector"], labels)
    ]


def admits(objs: list[Obj], target: dict[str, str], source: dict[str, str], port: int, namespace=NAMESPACE) -> bool:
    """Whether a connection from a pod labelled `source` (in `namespace`) to `target`:`port` is let in."""
    policies = selecting(objs, target)
    if not policies:
        return True  # a pod no policy selects is open
    for p in policies:
        for rule in p["spec"].get("ingress", []):
            ports = [x["port"] for x in rule.get("ports", []) if x.get("protocol", "TCP") == "TCP"]
            if rule.get("ports") and port not in ports:
                continue
            if "from" not in rule or any(_peer_matches(peer, source, namespace) for peer in rule["from"]):
                return True
    return False


def labels_of(objs: list[Obj], suffix: str) -> dict[str, str]:
    (labels,) = [t.get("metadata", {}).get("labels", {}) for w, t in pod_templates(objs) if w.endswith(suffix)]
    return labels


def test_ingress_is_denied_by_default(objs):
    deny = [p for p in by_kind(objs, "NetworkPolicy") if p["spec"]["podSelector"] == {}]
    assert [p["spec"] for p in deny] == [{"podSelector": {}, "policyTypes": ["Ingress"]}]
    # A pod nothing else selects (a RayJob submitter, the CronJob's) accepts nothing, even from its namespace.
    submitter = labels_of(objs, "RayJob/gdwm-sweep/submitter")
    assert not admits(objs, submitter, submitter, 8265)


def test_every_server_and_ray_pod_has_a_policy_of_its_own(objs):
    missing = []
    for where, template in pod_templates(objs):
        labels = template.get("metadata", {}).get("labels", {})
        ports = [p["containerPort"] for c in template["spec"]["containers"] for p in c.get("ports", [])]
        own = [p for p in selecting(objs, labels) if p["spec"]["podSelector"] != {}]
        if (ports or is_ray_node(where)) and not own:
            missing.append(where)
    assert missing == []


def test_ray_pods_admit_their_cluster_and_the_head_its_clients(objs):
    for job in ("RayCluster/gdwm", "RayJob/gdwm-sweep", "RayJob/gdwm-regress-nightly"):
        head = labels_of(objs, f"{job}/head")
        worker = labels_of(objs, f"{job}/workers")
        for port in (6379, 8265, 10001, 12345):  # GCS, dashboard, client, one of Ray's run-time ports
            assert admits(objs, head, worker, port), (job, port)
            assert admits(objs, worker, head, port), (job, port)
            assert admits(objs, worker, worker, port), (job, port)
        if job.startswith("RayJob/"):
            assert admits(objs, head, labels_of(objs, f"{job}/submitter"), 8265), job
        assert admits(objs, head, {"app": "notebook"}, 8265), job  # the dashboard from within the namespace
        assert not admits(objs, head, {"app": "notebook"}, 6379), job
        assert not admits(objs, head, {"app": "notebook"}, 8265, namespace="elsewhere"), job
        assert admits(objs, head, {"app.kubernetes.io/name": "kuberay-operator"}, 8265, namespace="ray-system"), job
        assert not admits(objs, worker, {"app": "notebook"}, 12345), job
        assert not admits(objs, worker, labels_of(objs, f"{job}/submitter") if job.startswith("RayJob/") else {}, 8265)


def test_mlflow_admits_only_ray_pods_and_the_dashboard(objs):
    mlflow = labels_of(objs, "Deployment/gdwm-mlflow")
    for where, template in pod_templates(objs):
        labels = template.get("metadata", {}).get("labels", {})
        assert admits(objs, mlflow, labels, 5000) is (is_ray_node(where) or where == "Deployment/gdwm-dashboard"), where
    assert not admits(objs, mlflow, {"app": "notebook"}, 5000)


def test_the_dashboard_admits_only_the_ingress_controller(objs):
    dashboard = labels_of(objs, "Deployment/gdwm-dashboard")
    for where, template in pod_templates(objs):
        assert not admits(objs, dashboard, template.get("metadata", {}).get("labels", {}), 8080), where
    assert not admits(objs, dashboard, {"app": "notebook"}, 8080)
    assert admits(objs, dashboard, {"app.kubernetes.io/name": "ingress-nginx"}, 8080, namespace="ingress-nginx")
    assert not admits(objs, dashboard, {"app.kubernetes.io/name": "ingress-nginx"}, 5000, namespace="ingress-nginx")


def test_postgres_and_minio_admit_only_their_clients():
    objs = build(K8S / "overlays/local")
    postgres = labels_of(objs, "StatefulSet/gdwm-postgres")
    minio = labels_of(objs, "Deployment/gdwm-minio")
    for where, template in pod_templates(objs):
        labels = template.get("metadata", {}).get("labels", {})
        is_mlflow = where == "Deployment/gdwm-mlflow"
        assert admits(objs, postgres, labels, 5432) is is_mlflow, where
        s3_client = is_mlflow or is_ray_node(where) or where == "Job/gdwm-minio-bucket"
        assert admits(objs, minio, labels, 9000) is s3_client, where
    assert one(objs, "NetworkPolicy", "gdwm-postgres")["spec"]["ingress"][0]["ports"] == [
        {"protocol": "TCP", "port": 5432}
    ]
