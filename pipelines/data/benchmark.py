"""A benchmark's released QA attached to a converted nuScenes dataset: the shared half of ``gdwm data
import-nuinteract|import-nuinstruct|import-omnidrive`` (the readers are ``nuinteract``, ``nuinstruct``,
``omnidrive``).

The result is a dataset of its own (``data=nuinteract`` ...): the converted dataset's tables and files (hard links:
no image is copied) and a ``qa`` table of the benchmark's records, each on the frame whose nuScenes sample token it
names. Every record keeps

- ``task``: the benchmark's task group (NuInteract: rdp, vg2d, vg3d, plan; NuInstruct: perception, prediction, risk,
  reasoning; OmniDrive: desc, conv, vqa) and ``category``: its subtask (``perception-distance``, ``caption``);
- the answer as released, and the question with ``<gauss>`` put at its head (as the paper trains), InternVL's
  ``<image>`` placeholders dropped (the views are the record's ``views``, read from the dataset's images);
- its split as released: ``train``, and the released ``test``/``val`` as our ``val`` (``gt.released_split`` and
  ``dataset.json`` say which).

Matching (``attach``): a record's sample token must be a frame of the converted dataset (``frames.token``); a record
that also names a scene token (NuInteract) must name that frame's scene (the converter records ``scene_tokens``).
Records whose sample is not in the converted dataset are counted and named (``benchmark/unmatched.json``, the summary
and ``dataset.json``), never silently dropped; if none matches, nothing is published. Refused, in one line naming
file, record and field, with nothing published: a record missing a field, an answer that does not parse for its
metric, the same question of a sample twice with different answers, a file of another benchmark.
"""

from __future__ import annotations

import json
import logging
import re
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

from rich.console import RenderableType
from rich.table import Table

from pipelines.data.config import DatasetConfig
from pipelines.data.layout import (
    CAMERAS,
    GAUSS_TOKEN,
    ROUTES_FILE,
    TABLES,
    DataError,
    DatasetWriter,
    content_params,
    gaussians_relpath,
    image_relpath,
)
from pipelines.data.reader import GSQADataset

log = logging.getLogger(__name__)

UNMATCHED_FILE = "benchmark/unmatched.json"
"""``{sample token: records}`` of the records whose sample is not in the converted dataset."""
RELEASED_SPLITS = {"train": "train", "training": "train", "val": "val", "valid": "val", "validation": "val",
                   "test": "val"}  # fmt: skip
"""A released split name (a folder or a word of a file name) -> ours (the layout has train and val)."""
NAMED = 5
"""Unmatched sample tokens named in messages (all of them are in ``UNMATCHED_FILE``)."""


@dataclass
class BenchmarkConfig(DatasetConfig):
    """A benchmark's released QA attached to a converted nuScenes dataset (``pipelines.data.benchmark``)."""

    nuscenes: str = "${workdir}/data/nuscenes"
    """The converted nuScenes dataset (``gdwm data convert-nuscenes``) whose frames the records attach to."""
    summarizer: str = "pipelines.data.benchmark.render"
    """Prints the dataset's summary with the QA per task and subtask, and the unmatched records."""


@dataclass
class QARecord:
    """One released question and answer, read and checked by a benchmark's reader."""

    sample_token: str
    """The nuScenes sample (keyframe) it asks about."""
    task: str
    """The benchmark's task group."""
    category: str
    """The benchmark's subtask."""
    question: str
    """As released, but InternVL's ``<image>`` placeholders."""
    answer: str
    """As released."""
    released_split: str | None
    """The split's name as released (``test``); None: the split of its scene's other records, else train."""
    where: str
    """File and record: ``test/planning_test.pkl record 3 (id p3)``; errors start with it."""
    answer_field: str
    """Where the answer is in the record (``Answer``, ``conversations[1].value``)."""
    scene_token: str | None = None
    """The nuScenes scene token, where the record names one."""
    views: list[str] = field(default_factory=list)
    """Cameras it reads; empty: all six."""
    ident: str = ""
    """The benchmark's own id of the record, kept in ``gt``."""
    context_tokens: list[str] = field(default_factory=list)
    """Other samples it reads (NuInstruct's earlier frames): they must be frames of the same scene when converted."""


def split_of(name: str, where: str) -> str:
    """Our split of a released split name."""
    split = RELEASED_SPLITS.get(name.lower())
    if split is None:
        raise DataError(f"{where}: split '{name}' is not one of {sorted(RELEASED_SPLITS)}")
    return split


def released_split_in(rel: str) -> str | None:
    """The released split a source-relative path names: a folder or a word of the file name (``planning_test``)."""
    parts = Path(rel).parts
    for part in reversed(parts[:-1]):
        if part.lower() in RELEASED_SPLITS:
            return part.lower()
    for word in re.split(r"[^a-z]+", Path(rel).stem.lower()):
        if word in RELEASED_SPLITS:
            return word
    return None


def cameras_in(values: Iterable[str]) -> list[str]:
    """The nuScenes camera names the strings mention (image paths ``samples/CAM_FRONT/...``, ``<CAM_FRONT>`` tags),
    in the rig's order."""
    found = {cam for v in values for cam in CAMERAS if re.search(rf"(?<![A-Z_]){cam}(?![A-Z_])", str(v))}
    return [c for c in CAMERAS if c in found]


def question_text(question: str) -> str:
    """The question as the model reads it: ``<gauss>`` at its head (the paper's placement), InternVL's ``<image>``
    placeholders dropped."""
    q = re.sub(r"<image>\s*", "", question).strip()
    return q if q.startswith(GAUSS_TOKEN) else GAUSS_TOKEN + q


def foreign(obj: object) -> str | None:
    """Which benchmark a loaded QA file's content is from, by its fields (None: none recognised)."""
    first = obj[0] if isinstance(obj, list) and obj else obj
    if not isinstance(first, dict):
        return None
    keys = set(first)
    if {"Question", "Answer"} <= keys and keys & {"sample_list", "qa_id"}:
        return "NuInstruct"
    if "gemini_caption" in keys or ("conversations" in keys and keys & {"token", "sample_token", "scene_token"}):
        return "NuInteract"
    if ({"question", "answer"} <= keys and len(keys) <= 3) or ("description" in keys and not keys & {"task"}):
        return "OmniDrive"
    return None


COMMANDS = {"NuInteract": "import-nuinteract", "NuInstruct": "import-nuinstruct", "OmniDrive": "import-omnidrive"}


def refuse_foreign(obj: object, expected: str, where: str) -> None:
    """A DataError if ``obj`` (a loaded file) is another benchmark's QA: one line naming the file and the command."""
    other = foreign(obj)
    if other is not None and other != expected:
        raise DataError(f"{where}: a QA file of {other}, not of {expected}; import it with gdwm data {COMMANDS[other]}")


def load_json(path: Path, where: str) -> object:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DataError(f"{where}: not JSON ({e})") from e


# ---------------------------------------------------------------------------------------------------------- attach
@dataclass
class _Base:
    """The converted nuScenes dataset: its frames by sample token and its scenes' tokens."""

    ds: GSQADataset
    frames: dict[str, tuple[str, int]]
    scene_of_token: dict[str, str]
    cameras: list[str]


def _base(cfg: BenchmarkConfig) -> _Base:
    root = Path(cfg.nuscenes)
    if not (root / "dataset.json").is_file():
        raise DataError(
            f"data.nuscenes={root}: no converted nuScenes dataset there (convert one first: gdwm data convert-nuscenes "
            f"source=DIR, or point data.nuscenes at it)"
        )
    ds = GSQADataset(root)
    if ds.meta.get("format") != "nuscenes":
        raise DataError(
            f"data.nuscenes={root}: dataset '{ds.meta.get('name')}' is not a converted nuScenes dataset (format "
            f"{ds.meta.get('format')!r}); the records attach to nuScenes sample tokens (gdwm data convert-nuscenes)"
        )
    if "benchmark" in ds.meta:
        raise DataError(
            f"data.nuscenes={root}: dataset '{ds.meta.get('name')}' already holds {ds.meta['benchmark']['name']}'s QA; "
            f"attach to the converted nuScenes dataset it was built on ({ds.meta['benchmark']['nuscenes']['root']})"
        )
    t = ds.table("frames")
    frames = {
        tok: (s, int(f))
        for tok, s, f in zip(t["token"].to_pylist(), t["scene_id"].to_pylist(), t["frame_idx"].to_pylist(), strict=True)
    }
    scene_tokens = ds.meta.get("scene_tokens") or {}
    if not scene_tokens:
        log.warning(
            "%s was converted before scene tokens were recorded: records' scene tokens are not checked (re-convert it "
            "with gdwm data convert-nuscenes overwrite=true to check them)",
            root,
        )
    return _Base(ds, frames, {tok: name for name, tok in scene_tokens.items()}, list(ds.cameras))


def _check_duplicates(records: list[QARecord]) -> int:
    """Drop exact repeats (counted); the same question of a sample with another answer is an error."""
    seen: dict[tuple[str, str, str], QARecord] = {}
    kept, repeats = [], 0
    for r in records:
        key = (r.sample_token, r.category, r.question)
        first = seen.setdefault(key, r)
        if first is r:
            kept.append(r)
        elif first.answer == r.answer:
            repeats += 1
        else:
            raise DataError(
                f"{r.where}: field '{r.answer_field}' is {_short(r.answer)}, but {first.where} answers the same "
                f"question of sample {r.sample_token} ({r.category}) with {_short(first.answer)}"
            )
    records[:] = kept
    return repeats


def _short(text: str, n: int = 60) -> str:
    return repr(text if len(text) <= n else text[: n - 3] + "...")


def _matched(records: list[QARecord], base: _Base) -> tuple[list[tuple[QARecord, str, int]], Counter]:
    out, unmatched = [], Counter()
    for r in records:
        at = base.frames.get(r.sample_token)
        if at is None:
            unmatched[r.sample_token] += 1
            continue
        scene, frame = at
        if r.scene_token is not None and base.scene_of_token:
            named = base.scene_of_token.get(r.scene_token)
            if named != scene:
                names = f"scene {named}" if named else "a scene not in the converted dataset"
                raise DataError(
                    f"{r.where}: field 'scene_token' is {r.scene_token} ({names}), but sample {r.sample_token} is a "
                    f"frame of {scene}"
                )
        for tok in r.context_tokens:
            other = base.frames.get(tok)
            if other is not None and other[0] != scene:
                raise DataError(
                    f"{r.where}: field 'sample_list' names {tok}, a frame of {other[0]}, but its current sample "
                    f"{r.sample_token} is a frame of {scene}"
                )
        out.append((r, scene, frame))
    return out, unmatched


def attach(
    cfg: BenchmarkConfig,
    root: Path,
    source: str | None,
    overwrite: bool,
    benchmark: str,
    read: Callable[[Path], list[QARecord]],
    schema: type,
) -> Path:
    """Read ``source`` with ``read`` (which checks every record), match the records to the converted dataset at
    ``cfg.nuscenes`` and publish the dataset at ``root``; returns it. ``schema``: ``cfg``'s dataclass (its fields
    are the dataset's ``params``)."""
    if source is None:
        raise DataError(f"source= is required: the folder of {benchmark}'s released QA files")
    src = Path(source).expanduser().resolve()
    if not src.is_dir():
        raise DataError(f"source={source}: no such directory")
    base = _base(cfg)
    records = read(src)
    if not records:
        raise DataError(f"source={src}: no {benchmark} QA records found (see data.* globs)")
    repeats = _check_duplicates(records)
    matched, unmatched = _matched(records, base)
    if not matched:
        raise DataError(
            f"source={src}: none of the {len(records)} {benchmark} records names a sample of {base.ds.root} "
            f"({len(base.frames)} frames; unknown: {_named(unmatched)}); is data.nuscenes the conversion of the "
            f"nuScenes version the benchmark was built on?"
        )
    rows, views_dropped = _qa_rows(matched, base, benchmark)
    if unmatched:
        log.warning(
            "%s: %s not in %s, left out (all named in %s)", benchmark, _named(unmatched), base.ds.root, UNMATCHED_FILE
        )
    params = content_params(cfg, schema, skip=("nuscenes",))
    with DatasetWriter(root, cfg.name, source=f"{src} on {base.ds.root}", overwrite=overwrite, params=params) as w:
        for name in TABLES:
            if name != "qa":
                w.put_table(name, base.ds.table(name))
        for rel in base.ds.meta.get("files", {}):
            if rel.startswith("scenes/") or rel == ROUTES_FILE:
                w.link_file(rel, base.ds.root / rel)
        w.extend("qa", rows)
        w.path(UNMATCHED_FILE).write_text(json.dumps(dict(sorted(unmatched.items())), indent=1))
        keep = {k: v for k, v in base.ds.meta.items() if k not in _OWN_META}
        released = Counter(r.released_split or "-" for r, _, _ in matched)
        w.extra_meta = {
            **keep,
            "qa": f"{benchmark}'s released QA on the frames of {base.ds.meta.get('name')} (pipelines.data.benchmark)",
            "scene_splits": _scene_splits(rows, base.ds.meta.get("scene_splits") or {}),
            "benchmark": {
                "name": benchmark,
                "source": str(src),
                "nuscenes": {"root": str(base.ds.root), "fingerprint": base.ds.fingerprint},
                "records": len(records) + repeats,
                "matched": len(matched),
                "repeats_dropped": repeats,
                "views_not_converted": views_dropped,
                "released_splits": {k: RELEASED_SPLITS.get(k, "train") for k in sorted(released)},
                "unmatched": {
                    "records": sum(unmatched.values()),
                    "sample_tokens": len(unmatched),
                    "named": sorted(unmatched)[:NAMED],
                    "file": UNMATCHED_FILE,
                },
            },
        }
    return w.root


_OWN_META = {"name", "layout_version", "source", "cameras", "num_scenes", "scenes", "num_frames", "num_files",
             "bytes", "tables", "fingerprint", "params", "files", "qa", "scene_splits"}  # fmt: skip
"""``dataset.json`` keys the writer or the import sets; the converted dataset's others are kept (format, version,
image size, conventions, modalities, scene tokens)."""


def _named(unmatched: Counter) -> str:
    """``3 records of 2 sample tokens: a, b``, naming the first ``NAMED`` tokens."""
    names = ", ".join(sorted(unmatched)[:NAMED])
    more = f" and {len(unmatched) - NAMED} more" if len(unmatched) > NAMED else ""
    return f"{_count(sum(unmatched.values()), 'record')} of {_count(len(unmatched), 'sample token')}: {names}{more}"


def _count(n: int, what: str) -> str:
    return f"{n} {what}{'' if n == 1 else 's'}"


def _qa_rows(matched: list[tuple[QARecord, str, int]], base: _Base, benchmark: str) -> tuple[list[dict], int]:
    """Rows of the ``qa`` table; the records' splits resolved (a record without one takes its scene's)."""
    scene_val = {scene for r, scene, _ in matched if r.released_split and split_of(r.released_split, r.where) == "val"}
    count: Counter = Counter()
    rows, dropped = [], 0
    for r, scene, frame in matched:
        views = [c for c in (r.views or CAMERAS) if c in base.cameras]
        if not views:  # the conversion left out every camera the record reads
            dropped += 1
            continue
        k = count[(scene, frame)]
        count[(scene, frame)] += 1
        split = split_of(r.released_split, r.where) if r.released_split else ("val" if scene in scene_val else "train")
        gt = {"benchmark": benchmark, "record": r.where, "id": r.ident, "released_split": r.released_split,
              "sample_token": r.sample_token, "scene_token": r.scene_token}  # fmt: skip
        rows.append(
            {
                "sample_id": f"{scene}/{frame:05d}/{benchmark.lower()}/{k:04d}",
                "scene_token": scene,
                "frame_idx": frame,
                "task": r.task,
                "category": r.category,
                "conversations": [
                    {"from": "human", "value": question_text(r.question)},
                    {"from": "gpt", "value": r.answer},
                ],
                "image": [image_relpath(scene, cam, frame) for cam in views],
                "views": views,
                "gauss": [gaussians_relpath(scene, frame)],
                "split": split,
                "gt": json.dumps(gt, sort_keys=True),
            }
        )
    return rows, dropped


def _scene_splits(rows: list[dict], converted: dict[str, str]) -> dict[str, str]:
    """A scene with held-out records is ``val``, one with records only in train ``train``, others as converted."""
    out = dict(converted)
    by_scene: dict[str, set[str]] = {}
    for r in rows:
        by_scene.setdefault(r["scene_token"], set()).add(r["split"])
    out.update({s: "val" if "val" in splits else "train" for s, splits in by_scene.items()})
    return dict(sorted(out.items()))


# --------------------------------------------------------------------------------------------------------- summary
def render(root: str | Path) -> list[RenderableType]:
    """``gdwm data info`` of a benchmark dataset: the dataset's summary, then its QA per task and subtask and split,
    the released splits and the unmatched records."""
    from pipelines.data.summary import renderables, summarize

    ds = GSQADataset(root)
    # the per-subtask table below replaces the task-family one (its families are NuInteract's)
    out = [p for p in renderables(summarize(root)) if not (isinstance(p, Table) and p.title == "QA per task family")]
    qa = ds.table("qa")
    counts = Counter(zip(qa["task"].to_pylist(), qa["category"].to_pylist(), qa["split"].to_pylist(), strict=True))
    splits = sorted({s for _, _, s in counts})
    t = Table(title="QA per subtask", show_header=True, header_style="bold")
    for col in ("task", "subtask", *splits):
        t.add_column(col, justify="left" if col in ("task", "subtask") else "right")
    for task, category in sorted({(a, b) for a, b, _ in counts}):
        t.add_row(task, category, *(str(counts.get((task, category, s), 0)) for s in splits))
    out.append(t)
    b = ds.meta.get("benchmark", {})
    if b:
        splits = ", ".join(
            f"{k} -> {v}" if k != "-" else "none (dense captions) -> their scene's"
            for k, v in b.get("released_splits", {}).items()
        )
        out.append(
            f"{b.get('name')}: {b.get('matched')} of {b.get('records')} records on frames of {b['nuscenes']['root']} "
            f"(released splits: {splits}; exact repeats dropped: {b.get('repeats_dropped', 0)})"
        )
        if b.get("views_not_converted"):
            out.append(
                f"not attached: {_count(b['views_not_converted'], 'record')} reading only cameras the conversion left "
                f"out ({', '.join(c for c in CAMERAS if c not in ds.cameras)})"
            )
        u = b.get("unmatched", {})
        if u.get("records"):
            more = f" and {u['sample_tokens'] - len(u['named'])} more" if u["sample_tokens"] > len(u["named"]) else ""
            out.append(
                f"unmatched: {_count(u['records'], 'record')} of {_count(u['sample_tokens'], 'sample token')} not in "
                f"the converted dataset, left out: {', '.join(u['named'])}{more} (all in {Path(root) / u['file']})"
            )
    return out


def summary_counts(root: str | Path) -> dict[tuple[str, str, str], int]:
    """(task, subtask, split) -> records: what ``render`` prints, for tests and scripts."""
    qa = GSQADataset(root).table("qa")
    cols = [qa[c].to_pylist() for c in ("task", "category", "split")]
    return dict(Counter(zip(*cols, strict=True)))
