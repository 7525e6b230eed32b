"""The three understanding benchmarks' released QA, a few records each, in their documented formats, on the samples of
the nuScenes fixture (``fixtures_nuscenes.write_nuscenes``: scene-0001 and scene-0002, 3 frames each, sample tokens
``scene-000N-sample-K``, scene tokens ``scene-000N``). Held-out records are on scene-0002 (the converter's val scene);
each benchmark also names one sample that is not in the conversion (``UNMATCHED``).

- NuInteract (zc-zhao/DriveMonkey README, tools/load_dense_caption.py): ``NuInteract/{train,test}/<task file>.pkl``,
  pickled lists of InternVL conversation records, and ``all_caption_public/*.json`` dense captions.
- NuInstruct (xmed-lab/NuInstruct README, "Annotation Details"): ``annotations/{train,test}.json``, lists of
  ``{task, qa_id, img_path, Question, Answer, sample_list}``.
- OmniDrive (NVlabs/OmniDrive docs/setup.md and its VQA loader): ``{desc,conv,vqa}/{train,val}/<sample token>.json``.
"""

from __future__ import annotations

import json
import pickle
from pathlib import Path

UNMATCHED = "0a1b4e0aa3824b0a96bafae7105c58cc"
"""A sample token of a nuScenes sample the fixture's conversion does not hold."""


def tok(scene: int, k: int) -> str:
    return f"scene-000{scene}-sample-{k}"


def _conv(question: str, answer: str) -> list[dict]:
    return [{"from": "human", "value": f"<image>\n{question}"}, {"from": "gpt", "value": answer}]


def nuinteract_record(rid: str, scene: int, k: int, question: str, answer: str, task: str | None = None,
                      cams: tuple[str, ...] = ("CAM_FRONT",)) -> dict:  # fmt: skip
    r = {
        "id": rid,
        "token": tok(scene, k),
        "scene_token": f"scene-000{scene}",
        "image": [f"samples/{cam}/scene-000{scene}_{k}_{cam}.jpg" for cam in cams],
        "conversations": _conv(question, answer),
    }
    if task is not None:
        r["task"] = task
    return r


NUINTERACT_TASKS = {
    "train/2D Visual Grounding.pkl": [
        nuinteract_record("g1", 1, 0, "Where is the car ahead?", "<CAM_FRONT> <box>[[420, 380, 610, 520]]</box>",
                          "2D_perception_location"),
        nuinteract_record("g2", 1, 1, "Where is the car ahead?", "<CAM_FRONT> <box>[[430, 380, 620, 520]]</box>",
                          "2D_perception_location"),
    ],
    "train/Region Description and Prediction.pkl": [
        nuinteract_record("r1", 1, 0, "Describe the object in <box>[[420, 380, 610, 520]]</box>.",
                          "It is a grey car driving ahead of the ego vehicle.", "2D_perception_infos"),
        nuinteract_record("r2", 1, 2, "What will the car ahead do next?", "It will keep driving straight ahead.",
                          "prediction"),
    ],
    "train/planning.pkl": [
        nuinteract_record("p1", 1, 1, "What should the ego car do next?", "The ego car should go straight.",
                          "planning_go_straight", tuple(["CAM_FRONT", "CAM_BACK"])),
    ],
    "train/3D Visual Grounding.pkl": [
        nuinteract_record("v1", 1, 2, "Locate the car ahead in 3D.", "center: (10.0, 1.0, 0.8), size: (4.5, 1.8, 1.6)",
                          "perception"),
    ],
    "test/2D Region Description Prediction and Visual Grounding.pkl": [
        nuinteract_record("t1", 2, 0, "Describe the object in <box>[[400, 370, 600, 510]]</box>.",
                          "It is a grey car driving ahead of the ego vehicle."),
        nuinteract_record("t2", 2, 1, "Where is the car ahead?", "<CAM_FRONT> <box>[[410, 375, 605, 515]]</box>"),
        nuinteract_record("t3", 2, 0, "Where is the car ahead?", "<CAM_FRONT> <box>[[400, 370, 600, 510]]</box>"),
    ],
    "test/planning_test.pkl": [
        nuinteract_record("tp", 2, 2, "What should the ego car do next?", "Turn left at the next junction.",
                          "planning_turn_left", tuple(["CAM_FRONT", "CAM_BACK"])),
        {**nuinteract_record("tu", 1, 0, "What should the ego car do next?", "Go straight."), "token": UNMATCHED,
         "scene_token": "scene-0099"},
    ],
    "test/3D Visual Grounding.pkl": [
        nuinteract_record("tv", 2, 1, "Locate the car ahead in 3D.", "center: (10.0, 1.0, 0.8), size: (4.5, 1.8, 1.6)",
                          "perception"),
    ],
}  # fmt: skip
"""Task file -> records: 6 in train (scene-0001), 6 in test (5 on scene-0002, one on an unknown sample)."""
CAPTIONS = [
    {"token": tok(1, 0), "prev": "", "next": tok(1, 1), "frame_idx": 0, "scene_token": "scene-0001",
     "cam_path": {"CAM_FRONT": "samples/CAM_FRONT/scene-0001_0_CAM_FRONT.jpg"}, "gpt_prompt": "...",
     "gemini_caption": {"CAM_FRONT": "A grey car drives ahead on a wet road.", "CAM_BACK": "The road behind is empty.",
                        "FRONT": "Ahead, a grey car drives on a wet road. ", "BACK": "Behind, the road is empty."}},
]  # fmt: skip
"""One dense-caption record: 2 camera captions and the surround one (FRONT + BACK) -> 3 rdp/caption records."""


def write_nuinteract(root: Path, tasks: dict | None = None, captions: list | None = None) -> Path:
    """NuInteract's release under ``root`` (``NuInteract/<split>/*.pkl``, ``all_caption_public/*.json``)."""
    for rel, records in (NUINTERACT_TASKS if tasks is None else tasks).items():
        path = root / "NuInteract" / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as f:
            pickle.dump(records, f)
    caps = root / "all_caption_public"
    caps.mkdir(parents=True, exist_ok=True)
    (caps / "scene-0001.json").write_text(json.dumps(CAPTIONS if captions is None else captions))
    (caps / "token_name.json").write_text(json.dumps({tok(1, 0): "n008-2018-08-01"}))
    return root


def nuinstruct_record(qa_id: int, task: str, scene: int, k: int, question: str, answer: str) -> dict:
    frames = range(max(0, k - 1), k + 1)  # the clip: the previous frame and the current one
    cams = ("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_LEFT", "CAM_BACK", "CAM_BACK_RIGHT")
    return {
        "task": task,
        "qa_id": qa_id,
        "img_path": [{c: f"samples/{c}/scene-000{scene}_{f}_{c}.jpg" for c in cams} for f in frames],
        "Question": question,
        "Answer": answer,
        "sample_list": [tok(scene, f) for f in frames],
    }


def _nuinstruct(split_scene: int, base: int) -> list[dict]:
    s = split_scene
    return [
        nuinstruct_record(base + 0, "perception-distance", s, 1, "How far is the car from the ego car?", "(10.0, 1.0)"),
        nuinstruct_record(base + 1, "perception-instance_count", s, 0, "How many cars are around?", "1"),
        nuinstruct_record(base + 2, "perception-closest", s, 2, "Which object is closest in front?",
                          "<car>[c1,20.0,10.0,44.0,30.0]"),
        nuinstruct_record(base + 3, "prediction-status_ego", s, 1, "Is the ego car moving or stopped?", "Moving."),
        nuinstruct_record(base + 4, "risk-overtaking", s, 2, "Which objects may overtake the ego car?",
                          "<car>[c1,20.0,10.0,44.0,30.0];<pedestrian>[c4,5.0,5.0,15.0,30.0]"),
        nuinstruct_record(base + 5, "risk-non", s, 0, "Which objects are a risk?", "There is no risk object."),
        nuinstruct_record(base + 6, "reasoning-reasoning", s, 1, "What should the ego car do, and why?",
                          "Keep driving straight, because the road ahead is clear."),
    ]  # fmt: skip


NUINSTRUCT = {
    "annotations/train.json": _nuinstruct(1, 0),
    "annotations/test.json": [
        *_nuinstruct(2, 100),
        {**nuinstruct_record(199, "perception-speed", 2, 1, "How fast is the car?", "4.5"), "sample_list": [UNMATCHED]},
    ],
}
"""Annotation file -> records: 7 in train (scene-0001), 8 in test (7 on scene-0002, one on an unknown sample)."""


def write_nuinstruct(root: Path, files: dict | None = None) -> Path:
    for rel, records in (NUINSTRUCT if files is None else files).items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(records))
    return root


OMNIDRIVE = {
    f"desc/train/{tok(1, 0)}.json": {"description": "The ego car drives on a wet road behind a grey car.",
                                     "action": "Keep lane."},
    f"desc/train/{tok(1, 1)}.json": {"description": "A grey car drives ahead; the road behind is empty.",
                                     "action": "Keep lane."},
    f"conv/train/{tok(1, 0)}.json": [
        {"question": "What is the weather like?", "answer": "It is raining, the road is wet."},
        {"question": "Is there a car ahead?", "answer": "Yes, a grey car drives ahead in the same lane."},
    ],
    f"vqa/train/{tok(1, 2)}.json": [{"question": "Which objects deserve attention?", "answer": "The grey car ahead."}],
    f"desc/val/{tok(2, 0)}.json": {"description": "The ego car drives on a wet road behind a grey car.",
                                   "action": "Keep lane."},
    f"conv/val/{tok(2, 1)}.json": [{"question": "Is there a car ahead?", "answer": "Yes, a grey car drives ahead."}],
    f"conv/val/{UNMATCHED}.json": [{"question": "Is the road wet?", "answer": "Yes."}],
}  # fmt: skip
"""File -> content: 5 train records (scene-0001), 3 val records (2 on scene-0002, one on an unknown sample)."""


def write_omnidrive(root: Path, files: dict | None = None) -> Path:
    for rel, content in (OMNIDRIVE if files is None else files).items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(content))
    return root
