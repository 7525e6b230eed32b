"""Options with a fixed set of values are Enums in their schema (issue 16): a typo fails at compose time, exit 2,
naming the key and the allowed values, instead of silently meaning something else."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import itertools
import json
import os
import re
import subprocess
import sys
import textwrap
import types
import typing
from enum import Enum
from pathlib import Path

import pytest
from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf

from gdwm.cache import cache_key, canonical_json
from gdwm.config import _register_all, load_config
from gdwm.executor import stage_config

REPO = Path(__file__).resolve().parents[2]

# Open sets: names looked up in model_zoo.registry, which plugins extend with their own variants (an unknown name
# fails there with UnknownVariant listing the registered ones), so their schemas keep them as ``str``.
REGISTRY_NAMES = {
    ("SelectorConfig", "name"),
    ("AlignmentConfig", "name"),
    ("FineAdapterConfig", "name"),
}

_LIT = r"``[A-Za-z_][\w-]*``"  # a backticked identifier-like literal (not a path, URI or zoo reference)
_CHOICE_PATTERNS = (
    re.compile(r"\bone of\b", re.IGNORECASE),
    # ``a`` ... or ``b`` in one clause: "``fail`` the stage ..., or ``skip`` the scene", "``x`` (...) or ``y``"
    re.compile(_LIT + r"[^`;]{0,100}?,?\s+or\s+" + _LIT),
    # a|b|c, none | kl
    re.compile(r"(?<![\w|`/])[A-Za-z_][\w-]*(?:\s*\|\s*[A-Za-z_][\w-]*)+(?![\w|`/])"),
    # "Rasterizer backend: auto, torch, gsplat." -- a label followed by >= 3 bare identifiers ending the sentence
    re.compile(r":\s*[a-z_][\w-]*(?:,\s*[a-z_][\w-]*){2,}\s*(?:\.|$)"),
)


def lists_choices(doc: str) -> str | None:
    """The part of a field docstring that enumerates allowed values, or None."""
    text = " ".join(doc.split())
    bare = re.sub(r"``.*?``", "``", text)  # a|b and "x: a, b, c" only outside literals (paths, templates)
    for pattern, where in zip(_CHOICE_PATTERNS, (text, text, bare, bare), strict=True):
        if m := pattern.search(where):
            return m.group(0)
    return None


def field_docs(cls: type) -> dict[str, str]:
    """Field name -> the string literal right after its annotated assignment, over the dataclass's MRO."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass) or klass is object:
            continue
        tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        body = tree.body[0].body
        for stmt, nxt in itertools.pairwise(body):
            if (
                isinstance(stmt, ast.AnnAssign)
                and isinstance(stmt.target, ast.Name)
                and isinstance(nxt, ast.Expr)
                and isinstance(nxt.value, ast.Constant)
                and isinstance(nxt.value.value, str)
            ):
                docs[stmt.target.id] = nxt.value.value
    return docs


def _nested(tp: object) -> list[type]:
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        return [tp]
    return [c for a in typing.get_args(tp) for c in _nested(a)]


def registered_schemas() -> list[type]:
    """Every dataclass stored in the ConfigStore after registration, plus the dataclasses nested in their fields."""
    _register_all()
    found: list[type] = []

    def walk_repo(node: dict) -> None:
        for value in node.values():
            if isinstance(value, dict):
                walk_repo(value)
            elif (t := OmegaConf.get_type(value.node)) is not None and dataclasses.is_dataclass(t):
                todo.append(t)

    todo: list[type] = []
    walk_repo(ConfigStore.instance().repo)
    while todo:
        cls = todo.pop()
        if cls in found:
            continue
        found.append(cls)
        for tp in typing.get_type_hints(cls).values():
            todo.extend(_nested(tp))
    return found


def _is_str(tp: object) -> bool:
    return tp is str or (typing.get_origin(tp) in (typing.Union, types.UnionType) and str in typing.get_args(tp)
                         and all(a in (str, type(None)) for a in typing.get_args(tp)))  # fmt: skip


def test_detector_flags_choice_docstrings():
    # the docstrings of fields that were free ``str`` before issue 16
    old = [
        "Per-scene user errors: ``fail`` the stage after the other scenes finish, or ``skip`` the scene.",
        "``train``, or ``zero_shot``: no training at all and no Gaussian tokens (the conference table's first row).",
        "Foundation encoder variant: ``daisy`` (CPU) or ``qwen3_vl_vision`` (a local Qwen3-VL checkpoint).",
        "Compact code variant: ``foundation`` (``d_z`` dims) or ``langsplat3`` (3 dims, like the public release).",
        "Where future targets' camera poses come from: ``recorded`` (the dataset's ego poses, i.e. the trajectory\n"
        "    QA) or ``predicted`` (the LoRA'd LLM answers the trajectory question from the 4 history frames).",
        "Features of the Fréchet distance: ``daisy`` (``fd_daisy``, approximate) or ``inception`` (FID, needs\n"
        "    ``fd_weights``).",
        "Rasterizer backend: auto, torch, gsplat.",
        "``BCa`` (its jackknife rescores every row once per held-out sample), ``percentile`` or ``basic``.",
        "Alignment variant: none | kl.",
        "Fine adapter variant: similarity | query_xattn | identity.",
        "Mode, one of train or eval.",
    ]
    for doc in old:
        assert lists_choices(doc), doc
    # free-form values that mention literals are not choices
    for doc in [
        "Ray address (``auto`` or ``ray://...``); null starts a local Ray with ``num_cpus``.",
        "Take the stage's model from the model zoo instead of training it, e.g. ``zoo:gdwm-lora@champion`` or\n"
        "    ``zoo:gdwm-lora/3`` (``gdwm run`` pins an alias to its version before planning: the cache key names it).",
        "A version number, or ``@ALIAS``; show/load: null = by ``alias``, else the latest version.",
        "Parameter dtype (``bfloat16`` on CUDA).",
        "Compare the runs an MLflow filter string selects, e.g. \"tags.`gdwm.pipeline` = 'gaussiandwm_pp'\".",
        "ls: list this stage's entries (null = one summary row per stage); gc: only this stage; invalidate: required.",
        "lambda of (1 - lambda) L1 + lambda D-SSIM.",
        "Output folder; null = ``<workdir>/reports/<sweep name | runs | filter | all>``.",
    ]:
        assert lists_choices(doc) is None, doc


def test_no_str_field_documents_a_fixed_set_of_values():
    schemas = registered_schemas()
    names = {c.__name__ for c in schemas}
    assert {"RunSettings", "LoraStageConfig", "EvaluateGenConfig", "CompareArgs", "MetricCheck"} <= names
    offenders, checked = [], 0
    for cls in schemas:
        hints = typing.get_type_hints(cls)
        docs = field_docs(cls)
        for f in dataclasses.fields(cls):
            if not _is_str(hints[f.name]) or (cls.__name__, f.name) in REGISTRY_NAMES:
                continue
            checked += 1
            if (hit := lists_choices(docs.get(f.name, ""))) is not None:
                offenders.append(f"{cls.__module__}.{cls.__name__}.{f.name}: {hit!r}")
    assert checked > 20
    assert not offenders, "str fields whose docstring lists their values (make them a StrEnum):\n" + "\n".join(
        offenders
    )


def test_registry_exemptions_are_str_fields_that_list_variants():
    """Each exemption is a str field whose docstring lists the shipped variants (a stale entry must go)."""
    by_name = {c.__name__: c for c in registered_schemas()}
    for cls_name, field_name in REGISTRY_NAMES:
        cls = by_name[cls_name]
        assert _is_str(typing.get_type_hints(cls)[field_name])
        assert lists_choices(field_docs(cls)[field_name]), (cls_name, field_name)


CONVERTED = {
    "run.on_scene_error": ("fail", "skip"),
    "stage.lora.mode": ("train", "zero_shot"),
    "stage.distill.encoder": ("daisy", "qwen3_vl_vision", "langsplat_proxy", "langsplat"),
    "stage.distill.feature_tokenizer": ("foundation", "langsplat3"),
    "model.selector.path": ("route", "extrapolated"),
    "stage.evaluate_gen.future_poses": ("recorded", "predicted"),
    "stage.evaluate_gen.fd_extractor": ("daisy", "inception"),
    "stage.reconstruct.backend": ("auto", "torch", "gsplat"),
}


def test_converted_fields_are_enums_with_their_values():
    cfg = load_config()
    for key, allowed in CONVERTED.items():
        value = OmegaConf.select(cfg, key)
        assert isinstance(value, Enum) and isinstance(value, str), key
        assert tuple(m.value for m in type(value)) == allowed, key


@pytest.mark.parametrize(
    ("override", "key", "allowed"),
    [
        ("run.on_scene_error=fial", "run.on_scene_error", "fail, skip"),
        ("stage.lora.mode=zeroshot", "stage.lora.mode", "train, zero_shot"),
    ],
)
def test_typo_exits_2_naming_key_and_allowed_values(override, key, allowed):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "platform"), str(REPO)])}
    proc = subprocess.run(
        [sys.executable, "-m", "gdwm", "config", "show", override],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stdout + proc.stderr
    bad = override.split("=", 1)[1]
    assert f"invalid value for '{key}'" in proc.stderr
    assert f"Invalid value '{bad}', expected one of [{allowed}]" in proc.stderr


def test_bootstrap_method_is_an_enum():
    cfg = load_config(["args=compare", "args.bootstrap_method=percentile"])
    args = OmegaConf.to_object(cfg.args)
    assert args.bootstrap_method == "percentile" and isinstance(args.bootstrap_method, Enum)


def test_stage_config_subset_keeps_plain_strings_and_cache_keys():
    """Enum members in a stage's config subset serialise as their plain value: cache keys do not change."""
    cfg = load_config(["stage.distill.feature_tokenizer=langsplat3", "run.on_scene_error=skip"])
    sd = types.SimpleNamespace(config=["stage.distill", "stage.reconstruct", "run"], seeded=False)
    subset = stage_config(sd, cfg)
    value = subset["stage.distill"]["feature_tokenizer"]
    assert isinstance(value, str) and value == "langsplat3" and str(value) == "langsplat3"
    assert subset["run"]["on_scene_error"] == "skip"
    plain = {k: OmegaConf.to_container(OmegaConf.select(cfg, k), resolve=True, enum_to_str=True) for k in sd.config}
    assert type(plain["stage.distill"]["feature_tokenizer"]) is str
    assert canonical_json(subset) == canonical_json(plain)
    decoded = json.loads(canonical_json(subset))
    assert decoded["stage.distill"]["feature_tokenizer"] == "langsplat3"
    assert decoded["stage.reconstruct"]["backend"] == "auto"
    assert cache_key("distill", "1", subset, {}, "data") == cache_key("distill", "1", plain, {}, "data")
