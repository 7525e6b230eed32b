"""OmniDrive-nuScenes' released QA (github NVlabs/OmniDrive) on a converted nuScenes dataset: ``gdwm data
import-omnidrive source=DIR``.

``source`` is the release's ``data/nuscenes`` folder as its docs lay it out (docs/setup.md), one JSON file per
nuScenes sample token, per part and split, read as its loader reads them (LoadAnnoatationVQA)::

    desc/<split>/<token>.json    {"description": "...", "action": "..."}     scene description (task desc)
    conv/<split>/<token>.json    [{"question": "...", "answer": "..."}, ...]  general dialogue (task conv)
    vqa/<split>/<token>.json     [{"question": "...", "answer": "..."}, ...]  attention, counterfactual, planning (vqa)

The paper follows VGGDrive's protocol, which scores the scene descriptions and the general dialogue
(``conf/stage/evaluate_qa/suites/omnidrive.yaml``); ``vqa`` is imported to train on (``data.parts``). The release
ships no question for a description (its loader draws one of its templates at random): the import asks ``QUESTION``.
Every record reads the six cameras; ``category`` is the part's benchmark name (scene_description, general_dialogue,
vqa). Splits are the folders (``val`` stays val).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from pipelines.data.benchmark import BenchmarkConfig, QARecord, attach, load_json, refuse_foreign
from pipelines.data.layout import DataError, contained

BENCHMARK = "OmniDrive"
PARTS = {"desc": "scene_description", "conv": "general_dialogue", "vqa": "vqa"}
"""A part's folder -> its records' category (their task is the folder's name)."""
QUESTION = "Describe the current driving scene and conditions around the ego vehicle, based on the images."
"""The question of a scene description (the release ships none; ours, fixed, so every run asks the same)."""


@dataclass
class OmniDriveConfig(BenchmarkConfig):
    """OmniDrive-nuScenes' desc, conv and vqa files attached to a converted nuScenes dataset
    (``pipelines.data.omnidrive``)."""

    name: str = "omnidrive"
    """Dataset name; also the folder under ``<workdir>/data/``."""
    builder: str = "pipelines.data.omnidrive.build"
    """Dotted path of the importer."""
    build_command: str | None = "gdwm data import-omnidrive"
    """Imports it from ``source=DIR``."""
    parts: list[str] = field(default_factory=lambda: list(PARTS))
    """Which parts to import: ``desc`` (scene descriptions), ``conv`` (general dialogue), ``vqa``."""
    splits: list[str] = field(default_factory=lambda: ["train", "val"])
    """The split folders under each part."""


def build(cfg: OmniDriveConfig, root: Path, source: str | None, overwrite: bool = False) -> Path:
    """Attach the OmniDrive records under ``source`` to the converted dataset ``cfg.nuscenes`` at ``root``."""
    unknown = [p for p in cfg.parts if p not in PARTS]
    if unknown:
        raise DataError(f"data.parts: unknown part(s) {unknown} (OmniDrive's: {list(PARTS)})")
    return attach(cfg, root, source, overwrite, BENCHMARK, lambda src: read(src, cfg), OmniDriveConfig)


def read(src: Path, cfg: OmniDriveConfig) -> list[QARecord]:
    """Every record of every part and split, checked; files in token order."""
    out = []
    for part in cfg.parts:
        for split in cfg.splits:
            folder = src / part / split
            if not folder.is_dir():
                continue
            for path in sorted(folder.glob("*.json")):
                rel = contained(src, path.relative_to(src), f"{part} file").relative_to(src).as_posix()
                out += _records(load_json(path, rel), rel, part, split, path.stem)
    return out


def _records(data: object, rel: str, part: str, split: str, token: str) -> list[QARecord]:
    refuse_foreign(data, BENCHMARK, rel)

    def record(question: str, answer: str, at: str, answer_field: str) -> QARecord:
        return QARecord(token, part, PARTS[part], question, answer, split, at, answer_field, ident=f"{part}/{token}")

    if part == "desc":
        if not isinstance(data, dict):
            raise DataError(f"{rel} record 0: a JSON {type(data).__name__}, expected an object with 'description'")
        if "description" not in data:
            raise DataError(f"{rel} record 0: field 'description' missing")
        if not isinstance(data["description"], str) or not data["description"].strip():
            raise DataError(f"{rel} record 0: field 'description' must be a non-empty string")
        return [record(QUESTION, data["description"], f"{rel} record 0", "description")]
    if not isinstance(data, list):
        raise DataError(f"{rel}: a JSON {type(data).__name__}, expected a list of question/answer pairs")
    out = []
    for i, pair in enumerate(data):
        at = f"{rel} record {i}"
        if not isinstance(pair, dict):
            raise DataError(f"{at}: a {type(pair).__name__}, expected an object with 'question' and 'answer'")
        for key in ("question", "answer"):
            if key not in pair:
                raise DataError(f"{at}: field '{key}' missing")
            if not isinstance(pair[key], str) or not pair[key].strip():
                raise DataError(f"{at}: field '{key}' must be a non-empty string")
        out.append(record(pair["question"], pair["answer"], at, "answer"))
    return out
