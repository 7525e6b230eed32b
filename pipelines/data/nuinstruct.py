"""NuInstruct's released QA (github xmed-lab/NuInstruct) on a converted nuScenes dataset: ``gdwm data
import-nuinstruct source=DIR``.

``source`` holds its annotation files, JSON lists of records (README, "Annotation Details"); the split is the file's
(``train.json``; ``val``/``test`` -> our val)::

    {"task": "risk-overtaking",           # one of its 17 subtasks (+ risk-non), "<group>-<subtask>"
     "qa_id": 17,
     "img_path": [...],                   # the clip's images; the release names it img_paths, frames as
                                          # {camera: path} (both read)
     "Question": "...", "Answer": "...",
     "sample_list": ["<token>", ...]}     # the clip's nuScenes sample tokens, oldest first

A record attaches to the last sample of ``sample_list`` (the current frame: the clip's timestamps increase); the
earlier ones must be frames of the same scene where they are converted. ``task`` is its group (perception,
prediction, risk, reasoning), ``category`` the full task. The answer must parse for the task's metric
(``data.subtasks``, the same lists as ``conf/stage/evaluate_qa/suites/nuinstruct.yaml``): a number or ``(x, y)`` for
MAE, a well-formed ``<class>[camera,x1,y1,x2,y2]`` list (or none) for mAP, some text otherwise. The views are the
cameras of the current frame's images (all six where it lists none).
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
from pipelines.data.layout import DataError, contained
from pipelines.evaluate.config import NUINSTRUCT_SUBTASKS
from pipelines.evaluate.nuinstruct import class_label, parse_objects, parse_value

BENCHMARK = "NuInstruct"
REQUIRED = ("task", "qa_id", "Question", "Answer", "sample_list")
FORMS = {
    "regression": "a number or an (x, y) vector",
    "detection": "a list of <class>[camera,x1,y1,x2,y2] objects (or none)",
    "classification": "a non-empty answer (well-formed objects where it lists some)",
    "caption": "a non-empty answer",
}


@dataclass
class NuInstructConfig(BenchmarkConfig):
    """NuInstruct's annotation files attached to a converted nuScenes dataset (``pipelines.data.nuinstruct``)."""

    name: str = "nuinstruct"
    """Dataset name; also the folder under ``<workdir>/data/``."""
    builder: str = "pipelines.data.nuinstruct.build"
    """Dotted path of the importer."""
    build_command: str | None = "gdwm data import-nuinstruct"
    """Imports it from ``source=DIR``."""
    files_glob: str = "**/*.json"
    """Glob (relative to the source) of the annotation files; each file's name says its split."""
    subtasks: dict[str, list[str]] = field(default_factory=lambda: {k: list(v) for k, v in NUINSTRUCT_SUBTASKS.items()})
    """Metric kind (regression, classification, detection, caption) -> NuInstruct tasks: what each answer must parse
    as; a task in none of them is refused. Keep it in step with the suite (``stage/evaluate_qa/suites=nuinstruct``)."""


def build(cfg: NuInstructConfig, root: Path, source: str | None, overwrite: bool = False) -> Path:
    """Attach the NuInstruct records under ``source`` to the converted dataset ``cfg.nuscenes`` at ``root``."""
    return attach(cfg, root, source, overwrite, BENCHMARK, lambda src: read(src, cfg), NuInstructConfig)


def read(src: Path, cfg: NuInstructConfig) -> list[QARecord]:
    """Every record of every annotation file, checked; files in path order."""
    kind_of = {task: kind for kind, tasks in cfg.subtasks.items() for task in tasks}
    out = []
    for path in sorted(src.glob(cfg.files_glob)):
        rel = contained(src, path.relative_to(src), "annotation file").relative_to(src).as_posix()
        split = released_split_in(rel)
        if split is None:
            raise DataError(f"{rel}: its name says no split (train, val or test), as NuInstruct's file names do")
        data = load_json(path, rel)
        refuse_foreign(data, BENCHMARK, rel)
        if not isinstance(data, list):
            raise DataError(f"{rel}: a JSON {type(data).__name__}, expected NuInstruct's list of records")
        out += [_record(raw, rel, i, split, kind_of) for i, raw in enumerate(data)]
    return out


def _record(raw: object, rel: str, i: int, split: str, kind_of: dict[str, str]) -> QARecord:
    at = f"{rel} record {i}"
    if not isinstance(raw, dict):
        raise DataError(f"{at}: a {type(raw).__name__}, expected an object with {', '.join(REQUIRED)}")
    if "qa_id" in raw:
        at += f" (qa_id {raw['qa_id']})"
    for key in REQUIRED:
        if key not in raw:
            raise DataError(f"{at}: field '{key}' missing")
    for key in ("task", "Question", "Answer"):
        if not isinstance(raw[key], str) or not raw[key].strip():
            raise DataError(f"{at}: field '{key}' must be a non-empty string, got {raw[key]!r}")
    tokens = raw["sample_list"]
    if not isinstance(tokens, list) or not tokens or not all(isinstance(t, str) and t for t in tokens):
        raise DataError(f"{at}: field 'sample_list' must be a non-empty list of sample tokens, got {tokens!r}")
    task, answer = raw["task"], raw["Answer"]
    kind = kind_of.get(task)
    if kind is None:
        known = sorted(kind_of)
        raise DataError(f"{at}: field 'task' is {task!r}, not one of NuInstruct's tasks (data.subtasks: {known})")
    if not _parses(answer, kind):
        raise DataError(f"{at}: field 'Answer' does not parse for {task}'s metric ({FORMS[kind]}): {answer!r}")
    return QARecord(
        sample_token=tokens[-1],
        task=task.split("-", 1)[0],
        category=task,
        question=raw["Question"],
        answer=answer,
        released_split=split,
        where=at,
        answer_field="Answer",
        views=_views(raw),
        ident=str(raw["qa_id"]),
        context_tokens=list(tokens[:-1]),
    )


def _parses(answer: str, kind: str) -> bool:
    if kind == "regression":
        return parse_value(answer) is not None
    if kind == "detection":
        return parse_objects(answer) is not None
    if kind == "classification":
        return class_label(answer) is not None
    return bool(answer.strip())


def _views(raw: dict) -> list[str]:
    """The cameras of the current (last) frame's images: a frame is a {camera: path} mapping or a list of paths."""
    images = raw.get("img_path", raw.get("img_paths"))
    if isinstance(images, list) and images:
        current = images[-1]
        if isinstance(current, dict):
            return cameras_in(current)
        if isinstance(current, list):
            return cameras_in(current)
        return cameras_in(v for v in images if isinstance(v, str))
    if isinstance(images, dict):
        return cameras_in(images)
    return []
