"""The release's JSONL records (QA and world), validated and converted to the paper's conversation schema.

A release record (one JSON object per line); ``major_task`` says its kind, ``qa`` or ``world``::

    {"major_task": "qa", "sample_uid": "...", "scene_idx": 0, "frame_idx": 0, "views": ["CAM_FRONT"],
     "image_paths": ["images/x.png"], "gauss_paths": ["gauss/.../00000.pth"],
     "conversations": [{"role": "user", "content": "What is likely to happen next?"},
                       {"role": "assistant", "content": "..."}],
     "qa_group": "NuInteract_RD&P", "qa_subtask": "prediction",
     "clip_text_embed_path": "clip_text/features_000000.npy", "clip_text_embed_row": 0}

A world record has no ``qa_group`` and adds the generation fields of ``gaussiandwm_world``. The text holds no
``<gauss>``: the release's loader (``data/dataset.py``, ``_build_qwen_messages``) puts one Gaussian item in the
first user turn, after its images and right before its text; ``insert_gauss_token`` does the same with our
placeholder. Errors name ``file:line`` and, once known, the sample.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

from pipelines.data.gaussiandwm_world import WorldFields, parse_world
from pipelines.data.layout import GAUSS_TOKEN, SPLITS, TASKS, DataError

ROLES = {"user": "human", "assistant": "gpt", "system": "system"}
KINDS = ("qa", "world")  # the release's major_task values
# Release QA groups (configs/qa/budgets.yaml of the release) onto our task families.
DEFAULT_TASK_MAP = {
    "NuInteract_RD&P": "rdp",
    "NuInteract_Caption": "rdp",
    "NuInteract_2DVG": "vg2d",
    "NuInteract_3DVG": "vg3d",
    "NuInteract_Planning": "plan",
    "NuInteract_Trajectory": "traj",
}
_SPLIT_WORDS = {"train": "train", "training": "train", "val": "val", "valid": "val", "validation": "val", "test": "val"}


@dataclass(frozen=True)
class ClipRef:
    """A QA record's CLIP text feature: row ``row`` of the release's [N, D] ``.npy`` shard ``path``."""

    path: str
    row: int


@dataclass(frozen=True)
class ReleaseRecord:
    kind: str  # major_task: qa | world
    sample_uid: str
    scene_idx: int | str
    frame_idx: int
    views: list[str]
    image_paths: list[str]
    gauss_paths: list[str]
    conversations: list[dict[str, str]]  # ours: {"from": human|gpt|system, "value": ...}
    qa_group: str  # "" for world records
    qa_subtask: str
    split: str | None  # from the record or its file name; None: decided by scene later
    where: str  # file:line
    gauss_token_inserted: bool
    content: str  # the record as canonical JSON without 'split': equal content = the same record
    clip: ClipRef | None = None
    world: WorldFields | None = None


def read_records_file(path: Path, rel: str, insert_gauss_token: bool) -> list[ReleaseRecord]:
    """Every record (QA or world) of one JSONL file; blank lines are skipped."""
    file_split = split_from_name(path.name)
    out = []
    with open(path, encoding="utf-8") as f:
        for lineno, line in enumerate(f, start=1):
            if not line.strip():
                continue
            where = f"{rel}:{lineno}"
            try:
                raw = json.loads(line.rstrip("\r\n"))
            except json.JSONDecodeError as e:
                raise DataError(f"{where}: malformed JSON ({e.msg} at column {e.colno})") from e
            if not isinstance(raw, dict):
                raise DataError(f"{where}: expected a JSON object, got {type(raw).__name__}")
            out.append(parse_record(raw, where, file_split, insert_gauss_token))
    return out


def parse_record(raw: dict, where: str, file_split: str | None, insert_gauss_token: bool) -> ReleaseRecord:
    uid = raw.get("sample_uid")
    if not isinstance(uid, str) or not uid:
        raise DataError(f"{where}: missing or empty 'sample_uid'")
    at = f"{where} sample '{uid}'"
    kind = raw.get("major_task")
    if kind not in KINDS:
        raise DataError(f"{at}: 'major_task' is {kind!r}, expected one of {list(KINDS)}")
    scene_idx = _scene_idx(raw.get("scene_idx"), at)
    frame_idx = raw.get("frame_idx")
    if not isinstance(frame_idx, int) or isinstance(frame_idx, bool) or frame_idx < 0:
        raise DataError(f"{at}: 'frame_idx' must be a non-negative int, got {frame_idx!r}")
    conversations = _conversations(raw.get("conversations"), at)
    gauss_paths = _str_list(raw, "gauss_paths", at)
    inserted = _place_gauss_token(conversations, at, insert_gauss_token) if gauss_paths else False
    split = raw.get("split", file_split)
    if split is not None and split not in SPLITS:
        split = _SPLIT_WORDS.get(str(split).lower())
        if split is None:
            raise DataError(f"{at}: 'split' is {raw.get('split')!r}, expected one of {list(SPLITS)}")
    return ReleaseRecord(
        kind=kind,
        sample_uid=uid,
        scene_idx=scene_idx,
        frame_idx=frame_idx,
        views=_str_list(raw, "views", at),
        image_paths=_str_list(raw, "image_paths", at),
        gauss_paths=gauss_paths,
        conversations=conversations,
        qa_group=_str(raw, "qa_group", at) if kind == "qa" else "",
        qa_subtask=_str(raw, "qa_subtask", at, default="") if kind == "qa" else "",
        split=split,
        where=where,
        gauss_token_inserted=inserted,
        content=json.dumps({k: v for k, v in raw.items() if k != "split"}, sort_keys=True),
        clip=_clip_ref(raw, at) if kind == "qa" else None,
        world=parse_world(raw, at) if kind == "world" else None,
    )


def _place_gauss_token(conversations: list[dict[str, str]], at: str, insert: bool) -> bool:
    """Put ``<gauss>`` where the release's loader puts its Gaussian item; True when it was inserted."""
    first_user = next((t for t in conversations if t["from"] == "human"), None)
    if first_user is None:
        raise DataError(f"{at}: conversations have no user turn")
    if GAUSS_TOKEN in first_user["value"]:
        return False
    if not insert:
        raise DataError(
            f"{at}: first user turn lacks '{GAUSS_TOKEN}' although the record has gauss_paths "
            "(set insert_gauss_token=true to insert it as the release's loader does)"
        )
    # The release's item goes right before the turn's text, no separator (data/dataset.py of the release).
    first_user["value"] = GAUSS_TOKEN + first_user["value"]
    return True


def _clip_ref(raw: dict, at: str) -> ClipRef | None:
    path, row = raw.get("clip_text_embed_path"), raw.get("clip_text_embed_row")
    if path is None and row is None:
        return None
    if not isinstance(path, str) or not path:
        raise DataError(f"{at}: 'clip_text_embed_path' must be a non-empty string when 'clip_text_embed_row' is set")
    if not isinstance(row, int) or isinstance(row, bool) or row < 0:
        raise DataError(f"{at}: 'clip_text_embed_row' must be a non-negative int, got {row!r}")
    return ClipRef(path, row)


def map_task(record: ReleaseRecord, task_map: dict[str, str]) -> str:
    """``"<qa_group>/<qa_subtask>"`` first, then ``"<qa_group>"``; an unmapped group is an error."""
    key = f"{record.qa_group}/{record.qa_subtask}"
    task = task_map.get(key, task_map.get(record.qa_group))
    if task is None:
        raise DataError(
            f"{record.where} sample '{record.sample_uid}': qa_group '{record.qa_group}' has no task mapping "
            f"(task_map keys: {sorted(task_map)})"
        )
    if task not in TASKS:
        raise DataError(f"task_map maps '{key}' to '{task}', not one of {list(TASKS)}")
    return task


def split_from_name(name: str) -> str | None:
    """``qa_train.jsonl`` -> train, ``nuinteract_val.jsonl``/``test`` -> val, otherwise None."""
    for word in re.split(r"[^a-z]+", name.lower()):
        if word in _SPLIT_WORDS:
            return _SPLIT_WORDS[word]
    return None


def _scene_idx(value: object, at: str) -> int | str:
    if isinstance(value, int) and not isinstance(value, bool) and value >= 0:
        return value
    if isinstance(value, str) and value.isdigit():
        return int(value)
    if isinstance(value, str) and re.fullmatch(r"[A-Za-z0-9_.-]+", value):
        return value
    raise DataError(f"{at}: 'scene_idx' must be a non-negative int or a [A-Za-z0-9_.-] name, got {value!r}")


def _conversations(value: object, at: str) -> list[dict[str, str]]:
    if not isinstance(value, list) or not value:
        raise DataError(f"{at}: 'conversations' must be a non-empty list")
    out = []
    for i, turn in enumerate(value):
        if not isinstance(turn, dict):
            raise DataError(f"{at}: conversations[{i}] is a {type(turn).__name__}, expected an object")
        role, content = turn.get("role"), turn.get("content")
        if role not in ROLES:
            raise DataError(f"{at}: conversations[{i}].role is {role!r}, expected one of {sorted(ROLES)}")
        if not isinstance(content, str):
            raise DataError(f"{at}: conversations[{i}].content must be a string")
        out.append({"from": ROLES[role], "value": content})
    return out


def _str_list(raw: dict, key: str, at: str) -> list[str]:
    value = raw.get(key, [])
    if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
        raise DataError(f"{at}: '{key}' must be a list of non-empty strings")
    return list(value)


def _str(raw: dict, key: str, at: str, default: str | None = None) -> str:
    value = raw.get(key, default)
    if not isinstance(value, str) or (default is None and not value):
        raise DataError(f"{at}: missing or empty '{key}'")
    return value
