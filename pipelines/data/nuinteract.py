"""NuInteract's released QA (github zc-zhao/DriveMonkey) on a converted nuScenes dataset: ``gdwm data
import-nuinteract source=DIR``.

``source`` holds what its README has you unpack (either or both):

- ``NuInteract/{train,test}/*.pkl`` (NuInteract.zip): the task files, lists of records in InternVL's conversation
  format, ``{"id", "image": [paths], "conversations": [{"from": "human", "value": ...}, {"from": "gpt", ...}],
  ...}``, each naming its nuScenes sample (``token``, as its dense captions do; ``sample_token`` read too), and its
  scene (``scene_token``, checked where present). The file says the task group (``data.files``): 2D Visual Grounding
  (vg2d), Region Description and Prediction (rdp), planning (plan), 3D Visual Grounding (vg3d); the test file of
  region description and 2D grounding holds both (a record whose answer holds a box is vg2d). A record's subtask is
  its ``task`` field where it has one (e.g. ``2D_perception_infos``), else the file's group. A conversation of several
  exchanges becomes one record per exchange. Pickles are read with ``safe_pickle`` (plain data only).
- ``all_caption_public/*.json`` (cap_public.tar.gz): dense captions per sample, ``{"token", "prev", "next",
  "frame_idx", "scene_token", "cam_path", "gpt_prompt", "gemini_caption": {"CAM_FRONT": ..., ..., "FRONT": ...,
  "BACK": ...}}``, turned into one record per camera caption and one surround record (FRONT + BACK) as its
  ``tools/load_dense_caption.py`` does, with our fixed questions (it draws one of its templates at random). They are
  rdp, subtask ``caption``; released without a split, each takes its scene's (the split of the scene's task records,
  else train). ``token_name.json`` beside them is not a caption file and is skipped.

The split of a task file is its folder (``train``; ``test`` -> our val). Answers must parse for their family's metric:
a box (``<box>(x1,y1),(x2,y2)</box>`` or InternVL's ``<box>[[x1, y1, x2, y2]]</box>``) for 2D grounding, a
``center: (x, y, z)`` for 3D grounding, one of ``data.planning_labels`` for planning. Views: the cameras the record's
images or ``<CAM_...>`` tags name, else all six.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from pipelines.data.benchmark import (
    BenchmarkConfig,
    QARecord,
    attach,
    cameras_in,
    load_json,
    refuse_foreign,
    released_split_in,
)
from pipelines.data.layout import CAMERAS, DataError, contained
from pipelines.data.safe_pickle import load_plain
from pipelines.evaluate.config import NUINTERACT_DECISIONS
from pipelines.evaluate.grounding import parse_box, parse_centre_size
from pipelines.evaluate.planning import parse_decision

BENCHMARK = "NuInteract"
FILES = {
    "2D Visual Grounding": "vg2d",
    "Region Description and Prediction": "rdp",
    "planning": "plan",
    "planning_test": "plan",
    "3D Visual Grounding": "vg3d",
    "2D Region Description Prediction and Visual Grounding": "rdp|vg2d",
}
"""Task file name (stem) -> task group; ``rdp|vg2d``: per record, vg2d where the answer holds a box."""
CAMERA_QUESTION = "Describe the scene of the ego car's {direction} in detail, based on the provided <{camera}> image."
SURROUND_QUESTION = "Describe the road scene around the ego vehicle in detail, based on the provided images."
"""Questions of the dense captions (the release's tool draws one of its templates at random; ours are fixed)."""
SURROUND = ("FRONT", "BACK")
SKIPPED_CAPTION_FILES = ("token_name.json",)


@dataclass
class NuInteractConfig(BenchmarkConfig):
    """NuInteract's task files and dense captions attached to a converted nuScenes dataset
    (``pipelines.data.nuinteract``)."""

    name: str = "nuinteract"
    """Dataset name; also the folder under ``<workdir>/data/``."""
    builder: str = "pipelines.data.nuinteract.build"
    """Dotted path of the importer."""
    build_command: str | None = "gdwm data import-nuinteract"
    """Imports it from ``source=DIR``."""
    tasks_glob: str = "**/*.pkl"
    """Glob (relative to the source) of the task files (their folder, train or test, is their split)."""
    captions_glob: str = "**/all_caption_public/*.json"
    """Glob (relative to the source) of the dense caption files; empty: no captions."""
    files: dict[str, str] = field(default_factory=lambda: dict(FILES))
    """Task file name (without ``.pkl``) -> task group (rdp, vg2d, vg3d, plan; ``rdp|vg2d`` splits by answer)."""
    planning_labels: list[str] = field(default_factory=lambda: list(NUINTERACT_DECISIONS))
    """Closed-set planning decisions a planning answer must name (the suite's ``decision_labels``)."""


def build(cfg: NuInteractConfig, root: Path, source: str | None, overwrite: bool = False) -> Path:
    """Attach the NuInteract records under ``source`` to the converted dataset ``cfg.nuscenes`` at ``root``."""
    return attach(cfg, root, source, overwrite, BENCHMARK, lambda src: read(src, cfg), NuInteractConfig)


def read(src: Path, cfg: NuInteractConfig) -> list[QARecord]:
    """Task records then caption records, each file's in order; files in path order."""
    out = []
    for path in sorted(src.glob(cfg.tasks_glob)):
        rel = _rel(src, path, "task file")
        group = cfg.files.get(path.stem)
        if group is None:
            raise DataError(f"{rel}: not one of NuInteract's task files (data.files: {sorted(cfg.files)})")
        split = released_split_in(rel)
        if split is None:
            raise DataError(f"{rel}: its folder says no split (NuInteract/train or NuInteract/test)")
        data = load_plain(path, rel) if path.suffix == ".pkl" else load_json(path, rel)
        refuse_foreign(data, BENCHMARK, rel)
        if not isinstance(data, list):
            raise DataError(f"{rel}: a {type(data).__name__}, expected NuInteract's list of records")
        for i, raw in enumerate(data):
            out += _task_records(raw, f"{rel} record {i}", path.stem, group, split, cfg)
    if cfg.captions_glob:
        for path in sorted(src.glob(cfg.captions_glob)):
            if path.name in SKIPPED_CAPTION_FILES:
                continue
            rel = _rel(src, path, "caption file")
            data = load_json(path, rel)
            refuse_foreign(data, BENCHMARK, rel)
            if not isinstance(data, list):
                raise DataError(f"{rel}: a JSON {type(data).__name__}, expected a list of dense caption records")
            for i, raw in enumerate(data):
                out += _caption_records(raw, f"{rel} record {i}")
    return out


def _rel(src: Path, path: Path, what: str) -> str:
    return contained(src, path.relative_to(src), what).relative_to(src).as_posix()


def _token(raw: dict, at: str) -> str:
    for key in ("token", "sample_token"):
        if key in raw:
            if not isinstance(raw[key], str) or not raw[key]:
                raise DataError(f"{at}: field '{key}' must be a non-empty sample token, got {raw[key]!r}")
            return raw[key]
    raise DataError(f"{at}: field 'token' missing (the record's nuScenes sample token)")


def _scene_token(raw: dict, at: str) -> str | None:
    value = raw.get("scene_token")
    if value is not None and (not isinstance(value, str) or not value):
        raise DataError(f"{at}: field 'scene_token' must be a non-empty string, got {value!r}")
    return value


def _task_records(raw: object, at: str, stem: str, group: str, split: str, cfg: NuInteractConfig) -> list[QARecord]:
    if not isinstance(raw, dict):
        raise DataError(f"{at}: a {type(raw).__name__}, expected a record with 'token' and 'conversations'")
    if "id" in raw:
        at += f" (id {raw['id']})"
    token = _token(raw, at)
    if "conversations" not in raw:
        raise DataError(f"{at}: field 'conversations' missing")
    turns = raw["conversations"]
    if not isinstance(turns, list) or not turns:
        raise DataError(f"{at}: field 'conversations' must be a non-empty list of turns")
    subtask = raw.get("task") if isinstance(raw.get("task"), str) and raw.get("task") else stem
    out = []
    for k in range(0, len(turns), 2):
        human, gpt = _exchange(turns, k, at)
        family = ("vg2d" if parse_box(gpt) is not None else "rdp") if group == "rdp|vg2d" else group
        where = at if len(turns) == 2 else f"{at} exchange {k // 2}"
        _check_answer(gpt, family, f"{where}: field 'conversations[{k + 1}].value'", cfg)
        views = cameras_in(_strings(raw.get("image"))) or cameras_in([human])
        out.append(
            QARecord(token, family, subtask, human, gpt, split, where, f"conversations[{k + 1}].value",
                     scene_token=_scene_token(raw, at), views=views, ident=str(raw.get("id", "")))
        )  # fmt: skip
    return out


def _exchange(turns: list, k: int, at: str) -> tuple[str, str]:
    """(human, gpt) of turns k, k + 1, checked."""
    pair = turns[k : k + 2]
    roles = [t.get("from") if isinstance(t, dict) else None for t in pair]
    if roles != ["human", "gpt"]:
        raise DataError(f"{at}: field 'conversations[{k}:{k + 2}]' is not a human turn then a gpt turn (got {roles})")
    for j, t in enumerate(pair):
        if not isinstance(t.get("value"), str) or not t["value"].strip():
            raise DataError(f"{at}: field 'conversations[{k + j}].value' must be a non-empty string")
    return pair[0]["value"], pair[1]["value"]


def _check_answer(answer: str, family: str, at: str, cfg: NuInteractConfig) -> None:
    if family == "vg2d" and parse_box(answer) is None:
        form = "<box>(x1,y1),(x2,y2)</box> or <box>[[x1, y1, x2, y2]]</box>"
        raise DataError(f"{at} (the answer) has no box for 2D visual grounding ({form}): {answer!r}")
    if family == "vg3d" and parse_centre_size(answer) is None:
        raise DataError(f"{at} (the answer) has no 'center: (x, y, z)' for 3D visual grounding: {answer!r}")
    if family == "plan" and parse_decision(answer, cfg.planning_labels, "first") is None:
        raise DataError(
            f"{at} (the answer) names none of the planning decisions {cfg.planning_labels} (data.planning_labels): "
            f"{answer!r}"
        )


def _strings(value: object) -> list[str]:
    if isinstance(value, str):
        return [value]
    if isinstance(value, dict):
        return [*map(str, value), *(v for v in value.values() if isinstance(v, str))]
    if isinstance(value, list):
        return [v for v in value if isinstance(v, str)]
    return []


def _caption_records(raw: object, at: str) -> list[QARecord]:
    if not isinstance(raw, dict):
        raise DataError(f"{at}: a {type(raw).__name__}, expected a dense caption record with 'token'")
    token = _token(raw, at)
    if "gemini_caption" not in raw:
        raise DataError(f"{at}: field 'gemini_caption' missing")
    captions = raw["gemini_caption"]
    if not isinstance(captions, dict):
        raise DataError(f"{at}: field 'gemini_caption' must be an object of captions per view")
    scene = _scene_token(raw, at)

    def record(question: str, answer: str, views: list[str], key: str) -> QARecord:
        return QARecord(token, "rdp", "caption", question, answer, None, f"{at} ({key})", f"gemini_caption.{key}",
                        scene_token=scene, views=views, ident=f"caption/{token}/{key}")  # fmt: skip

    out = []
    for cam in CAMERAS:
        text = captions.get(cam)
        if text is None or text == "":  # the release's tool skips a view without a caption
            continue
        if not isinstance(text, str):
            raise DataError(f"{at}: field 'gemini_caption.{cam}' must be a string")
        direction = cam[4:].lower().replace("_", " ")
        out.append(record(CAMERA_QUESTION.format(direction=direction, camera=cam), text, [cam], cam))
    if all(isinstance(captions.get(k), str) and captions.get(k) for k in SURROUND):
        out.append(record(SURROUND_QUESTION, captions["FRONT"] + captions["BACK"], list(CAMERAS), "FRONT+BACK"))
    return out
