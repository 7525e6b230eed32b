"""Render a kustomization as ``kustomize build`` does, for the subset ``k8s/`` uses.

Written here because PyPI has no kustomize renderer (``kustomize`` 0.6.0 writes kustomization.yaml files from
Python, ``pytest-kustomize`` shells out to the Go binary, which no PyPI package ships); where a kustomize binary
is installed the tests compare this renderer's output with it.

Supported, in kustomize's order: ``resources`` (files, and directories holding a kustomization), ``patches``
(strategic merge — list merge keys for built-in kinds, whole lists replaced for CRDs as kustomize does without
their schema — and JSON 6902 add/replace/remove/test; from a file or inline; with a target or by the patch's own
kind and name), ``namespace`` (RoleBinding subjects of ServiceAccounts in the build included), ``labels``
(``pairs`` on metadata only) and ``images``. Any other field is an error, so the subset cannot drift silently.
"""

from __future__ import annotations

import copy
import re
from pathlib import Path
from typing import Any

import yaml

Obj = dict[str, Any]

SUPPORTED = {"apiVersion", "kind", "resources", "namespace", "labels", "images", "patches"}
CLUSTER_SCOPED = {
    "Namespace",
    "ClusterRole",
    "ClusterRoleBinding",
    "CustomResourceDefinition",
    "PersistentVolume",
    "StorageClass",
    "PriorityClass",
}
# API groups whose kinds kustomize knows the schema of; any other group is a CRD (lists are replaced wholesale).
BUILTIN_GROUPS = {"", "apps", "batch", "networking.k8s.io", "rbac.authorization.k8s.io", "policy", "autoscaling"}
# Strategic-merge keys of the built-in list fields we patch (k8s.io/api's patchMergeKey tags).
MERGE_KEYS = {
    "containers": "name",
    "initContainers": "name",
    "ephemeralContainers": "name",
    "volumes": "name",
    "env": "name",
    "imagePullSecrets": "name",
    "volumeMounts": "mountPath",
}


class KustomizeError(Exception):
    """A kustomization this renderer cannot build; the message names the file and the field."""


def build(directory: Path) -> list[Obj]:
    """The objects ``kustomize build directory`` prints (order aside)."""
    kfile = directory / "kustomization.yaml"
    if not kfile.is_file():
        raise KustomizeError(f"{directory}: no kustomization.yaml")
    k = yaml.safe_load(kfile.read_text()) or {}
    unknown = sorted(set(k) - SUPPORTED)
    if unknown:
        raise KustomizeError(f"{kfile}: fields not supported by tests/k8s/render.py: {unknown}")
    objs: list[Obj] = []
    for entry in k.get("resources", []):
        path = directory / entry
        if path.is_dir():
            objs += build(path)
        elif path.is_file():
            objs += [d for d in yaml.safe_load_all(path.read_text()) if d]
        else:
            raise KustomizeError(f"{kfile}: resource {entry} does not exist")
    _check_unique(objs, kfile)
    for i, patch in enumerate(k.get("patches", [])):
        _apply_patch(objs, patch, directory, f"{kfile} patches[{i}]")
    if "namespace" in k:
        _set_namespace(objs, k["namespace"])
    for entry in k.get("labels", []):
        if entry.get("includeSelectors") or entry.get("includeTemplates"):
            raise KustomizeError(f"{kfile}: labels with includeSelectors/includeTemplates are not supported")
        for o in objs:
            o["metadata"].setdefault("labels", {}).update(entry["pairs"])
    for image in k.get("images", []):
        for o in objs:
            _set_image(o, image)
    return objs


def object_id(o: Obj) -> tuple[str, str, str, str]:
    """(apiVersion, kind, namespace, name): what kustomize keys a resource by."""
    meta = o.get("metadata", {})
    return o["apiVersion"], o["kind"], meta.get("namespace", ""), meta.get("name", "")


def _check_unique(objs: list[Obj], where: Path) -> None:
    seen: set[tuple[str, str, str, str]] = set()
    for o in objs:
        if not o.get("metadata", {}).get("name"):
            raise KustomizeError(f"{where}: a {o.get('kind')} without metadata.name")
        oid = object_id(o)
        if oid in seen:
            raise KustomizeError(f"{where}: {oid} defined twice")
        seen.add(oid)


def _group_version(api_version: str) -> tuple[str, str]:
    group, _, version = api_version.rpartition("/")
    return group, version


def _matches(o: Obj, target: dict[str, str]) -> bool:
    group, version = _group_version(o["apiVersion"])
    meta = o["metadata"]
    checks = {"group": group, "version": version, "kind": o["kind"], "namespace": meta.get("namespace", "")}
    if any(key in target and target[key] != value for key, value in checks.items()):
        return False
    # kustomize anchors a target's name as a regular expression.
    return "name" not in target or re.fullmatch(target["name"], meta["name"]) is not None


def _apply_patch(objs: list[Obj], spec: Obj, directory: Path, where: str) -> None:
    if ("path" in spec) == ("patch" in spec):
        raise KustomizeError(f"{where}: give exactly one of path and patch")
    text = (directory / spec["path"]).read_text() if "path" in spec else spec["patch"]
    body = yaml.safe_load(text)
    target = spec.get("target")
    if isinstance(body, list):
        if target is None:
            raise KustomizeError(f"{where}: a JSON 6902 patch needs a target")
        hits = [o for o in objs if _matches(o, target)]
        for o in hits:
            for op in body:
                _json6902(o, op, where)
    else:
        if target is None:
            group, version = _group_version(body["apiVersion"])
            target = {
                "group": group,
                "version": version,
                "kind": body["kind"],
                "name": re.escape(body["metadata"]["name"]),
            }
        hits = [o for o in objs if _matches(o, target)]
        for o in hits:
            patch = {k: v for k, v in body.items() if k not in ("apiVersion", "kind")}
            patch["metadata"] = {k: v for k, v in patch.get("metadata", {}).items() if k not in ("name", "namespace")}
            merged = _strategic_merge(o, patch, _group_version(o["apiVersion"])[0] in BUILTIN_GROUPS)
            o.clear()
            o.update(merged)
    if not hits:
        raise KustomizeError(f"{where}: matches no resource")


def _strategic_merge(base: Any, patch: Any, builtin: bool, field: str = "") -> Any:
    if isinstance(base, dict) and isinstance(patch, dict):
        if any(k.startswith("$") for k in patch):
            raise KustomizeError(f"strategic-merge directives are not supported: {sorted(patch)}")
        out = dict(base)
        for k, v in patch.items():
            if v is None:
                out.pop(k, None)
            else:
                out[k] = _strategic_merge(base.get(k), v, builtin, k) if k in base else copy.deepcopy(v)
        return out
    key = MERGE_KEYS.get(field) if builtin else None
    if isinstance(base, list) and isinstance(patch, list) and key:
        out = [copy.deepcopy(b) for b in base]
        for item in patch:
            idx = next((i for i, b in enumerate(out) if b.get(key) == item.get(key)), None)
            if idx is None:
                out.append(copy.deepcopy(item))
            else:
                out[idx] = _strategic_merge(out[idx], item, builtin)
        return out
    return copy.deepcopy(patch)


def _pointer(path: str) -> list[str]:
    if not path.startswith("/"):
        raise KustomizeError(f"JSON pointer {path!r} must start with /")
    return [p.replace("~1", "/").replace("~0", "~") for p in path[1:].split("/")]


def _json6902(o: Obj, op: Obj, where: str) -> None:
    *parents, last = _pointer(op["path"])
    node: Any = o
    try:
        for p in parents:
            node = node[int(p)] if isinstance(node, list) else node[p]
        kind = op["op"]
        if isinstance(node, list):
            idx = len(node) if last == "-" else int(last)
            if kind == "add":
                node.insert(idx, copy.deepcopy(op["value"]))
            elif kind == "replace":
                node[idx] = copy.deepcopy(op["value"])
            elif kind == "remove":
                del node[idx]
            elif kind == "test":
                ok = node[idx] == op["value"]
            else:
                raise KustomizeError(f"{where}: op {kind!r} is not supported")
        else:
            if kind == "add":
                node[last] = copy.deepcopy(op["value"])
            elif kind == "replace":
                if last not in node:  # replace needs the member to exist (RFC 6902 §4.3)
                    raise KeyError(last)
                node[last] = copy.deepcopy(op["value"])
            elif kind == "remove":
                del node[last]
            elif kind == "test":
                ok = node[last] == op["value"]
            else:
                raise KustomizeError(f"{where}: op {kind!r} is not supported")
    except (KeyError, IndexError, ValueError, TypeError) as e:
        raise KustomizeError(f"{where}: {op['op']} {op['path']} on {o['kind']}/{o['metadata']['name']}: {e!r}") from e
    if op["op"] == "test" and not ok:
        raise KustomizeError(
            f"{where}: test {op['path']} == {op['value']!r} failed on {o['kind']}/{o['metadata']['name']}"
        )


def _set_namespace(objs: list[Obj], namespace: str) -> None:
    accounts = {o["metadata"]["name"] for o in objs if o["kind"] == "ServiceAccount"}
    for o in objs:
        if o["kind"] not in CLUSTER_SCOPED:
            o["metadata"]["namespace"] = namespace
        if o["kind"] in ("RoleBinding", "ClusterRoleBinding"):
            for s in o.get("subjects", []):
                if s.get("kind") == "ServiceAccount" and (s["name"] == "default" or s["name"] in accounts):
                    s["namespace"] = namespace


def _split_image(ref: str) -> tuple[str, str]:
    """('registry/repo', ':tag' or '@digest' or '')."""
    if "@" in ref:
        name, digest = ref.split("@", 1)
        return name, "@" + digest
    slash = ref.rfind("/")
    colon = ref.rfind(":")
    return (ref[:colon], ref[colon:]) if colon > slash else (ref, "")


def _set_image(node: Any, image: Obj) -> None:
    # kustomize 5 rewrites every containers/initContainers list, wherever it sits (CRD pod templates too).
    if isinstance(node, dict):
        for key, value in node.items():
            if key in ("containers", "initContainers") and isinstance(value, list):
                for c in value:
                    name, suffix = _split_image(c.get("image", ""))
                    if name == image["name"]:
                        if "digest" in image:
                            suffix = "@" + image["digest"]
                        elif "newTag" in image:
                            suffix = ":" + str(image["newTag"])
                        c["image"] = image.get("newName", name) + suffix
            else:
                _set_image(value, image)
    elif isinstance(node, list):
        for item in node:
            _set_image(item, image)
