"""Settings of the evaluate stages (``conf/stage/{evaluate_qa,evaluate_gen}/``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import Annotated

from annotated_types import Ge, Gt, Interval


class FuturePoses(StrEnum):
    recorded = "recorded"
    predicted = "predicted"


class FdExtractor(StrEnum):
    daisy = "daisy"
    inception = "inception"


class Suite(StrEnum):
    nuinteract = "nuinteract"
    nuinstruct = "nuinstruct"
    omnidrive = "omnidrive"


class DecisionMatch(StrEnum):
    head = "head"
    """The text before the answer's first "." is the decision ("Turn left. Reason: ..."): our synthetic answers."""
    first = "first"
    """The label that occurs first in the text (whole words, case-insensitive): free-form answers that name their
    decision anywhere ("The ego car should go straight because ...")."""


class NuInstructProtocol(StrEnum):
    pooled = "pooled"
    """Each NuInstruct metric over all its rows at once, on our answer forms (the proxy suite on synthetic data)."""
    per_subtask = "per_subtask"
    """NuInstruct's own: each metric is the mean of its subtasks' values (the row's category, e.g.
    ``perception-distance``), on NuInstruct's answer forms (``pipelines.evaluate.nuinstruct``)."""


FUTURE_POSES = tuple(p.value for p in FuturePoses)
SYNTH_DECISIONS = ["stop", "decelerate", "accelerate", "keep speed", "turn left", "turn right", "change lane left",
                   "change lane right", "go straight"]  # fmt: skip
"""``pipelines.data.synth.planning``'s speed and direction decisions (not imported: configs stay light)."""
NUINTERACT_DECISIONS = ["go straight", "turn left", "turn right"]
"""NuInteract's closed-set planning decisions (its planning subtasks ``planning_go_straight``, ``_turn_left``,
``_turn_right``); ``conf/stage/evaluate_qa/suites/nuinteract.yaml`` lists the same (a test holds it)."""
NUINSTRUCT_SUBTASKS = {
    "regression": ["perception-distance", "perception-speed", "perception-instance_count", "prediction-motion_ego",
                   "prediction-motion_other"],
    "classification": ["perception-closest", "perception-status", "perception-in_the_same_road",
                       "prediction-status_ego", "prediction-status_others"],
    "detection": ["risk-approaching", "risk-braking", "risk-crossing", "risk-lane_change", "risk-non",
                  "risk-on_coming", "risk-overtaking"],
    "caption": ["reasoning-reasoning"],
}  # fmt: skip
"""NuInstruct's tasks (its ``task`` field) by the metric its Table 2 scores them with: MAE, accuracy, mAP, BLEU.
Perception, prediction, risk and reasoning are its four groups; ``risk-non`` (no risk object) is released beside the
six risk subtasks. ``conf/stage/evaluate_qa/suites/nuinstruct.yaml`` maps the same (a test holds it)."""


@dataclass
class SuiteMapping:
    """Which prediction rows feed each metric group (``conf/stage/evaluate_qa/suites/``): glob patterns (``fnmatch``,
    case-sensitive) matched against a row's ``task`` and its ``category``. Our synthetic QA names categories as
    ``pipelines.data.synth.qa``; release data as ``"<qa_group>/<qa_subtask>"``, e.g. ``NuInteract_RD&P/*``."""

    proxy: list[Suite] = field(default_factory=lambda: [Suite.nuinstruct, Suite.omnidrive])
    """Suites whose rows stand in for the benchmark's own data (NuInteract-style task families scored with that
    suite's metrics): their metrics, tables' titles and captions say "proxy". Empty once the real data is mapped."""
    nuinteract_rdp: list[str] = field(default_factory=lambda: ["rdp"])
    """Region description & perception: BLEU-4, ROUGE-L, CIDEr over all these rows."""
    nuinteract_vg2d: list[str] = field(default_factory=lambda: ["vg2d"])
    """2D grounding ("<CAM> <box>(x1,y1),(x2,y2)</box>"): mAP, F1, mIoU."""
    nuinteract_vg3d: list[str] = field(default_factory=lambda: ["vg3d"])
    """3D grounding ("center: (x, y, z), size: (l, w, h)"): precision, mAP, F1."""
    nuinteract_plan: list[str] = field(default_factory=lambda: ["plan"])
    """Planning: decision accuracy."""
    nuinstruct_regression: list[str] = field(default_factory=lambda: ["2D_perception_infos"])
    """MAE of the first number (our data: object distances in metres)."""
    nuinstruct_classification: list[str] = field(default_factory=lambda: ["planning_speed", "planning_direction"])
    """Decision accuracy."""
    nuinstruct_detection: list[str] = field(default_factory=lambda: ["2D_visual_grounding"])
    """mAP as 2D grounding."""
    nuinstruct_caption: list[str] = field(default_factory=lambda: ["region_description"])
    """BLEU-4."""
    omnidrive_text: list[str] = field(
        default_factory=lambda: ["region_description", "planning_speed", "planning_direction"]
    )
    """BLEU-4, CIDEr, ROUGE-L."""
    decision_labels: list[str] | None = field(default_factory=lambda: list(SYNTH_DECISIONS))
    """Valid predicted decisions, lowercase (another one is malformed); null accepts any (``head`` matching only)."""
    decision_match: DecisionMatch = DecisionMatch.head
    """How a decision is read from an answer: ``head`` (the text before the first ".") or ``first`` (the first of
    ``decision_labels`` the text names; NuInteract's planning answers)."""
    nuinstruct_protocol: NuInstructProtocol = NuInstructProtocol.pooled
    """``pooled`` (the proxy: NuInteract-style rows scored with NuInstruct's metrics) or ``per_subtask``
    (NuInstruct's own protocol on its imported records)."""


@dataclass
class EvaluateQAConfig:
    """Greedy answers of the trained world model on the held-out QA, scored with every benchmark metric."""

    split: str = "val"
    """QA split that is answered and scored."""
    batch_size: Annotated[int, Ge(1)] = 8
    """Samples per generate() call."""
    max_new_tokens: Annotated[int, Ge(1)] = 64
    """Answer length bound (tokens)."""
    max_samples: Annotated[int, Ge(0)] = 0
    """Score at most N samples of the split (0 = all): an even share per task family, spread over the scenes and
    frames (``pipelines.understanding.data.balanced_subset``)."""
    tasks: list[str] = field(default_factory=list)
    """Task families answered (``rdp``, ``vg2d``, ``vg3d``, ``plan``, ``traj``); empty = all."""
    suites: SuiteMapping = field(default_factory=SuiteMapping)
    """Which rows feed which benchmark's metrics (config group ``stage/evaluate_qa/suites``: ``proxy``)."""

    def __post_init__(self):
        if isinstance(self.suites, dict):  # the stage gets its config as plain containers
            self.suites = SuiteMapping(**self.suites)


@dataclass
class EvaluateGenConfig:
    """Held-out generation: every target of the val scenes generated by the trained diffusion model and scored
    against ground truth (PSNR, SSIM, depth AbsRel/RMSE, a Fréchet distance per target)."""

    cameras: list[str] = field(default_factory=lambda: ["CAM_FRONT"])
    """Cameras whose views are targets."""
    shifts_m: Annotated[list[float], Interval(ge=-100, le=100)] = field(
        default_factory=lambda: [1.0, -1.0, 2.0, -2.0, 4.0, -4.0]
    )
    """Lateral shifts, metres (+ = left); ground truth is re-rendered (synthetic data only)."""
    horizons_s: Annotated[list[float], Gt(0)] = field(default_factory=lambda: [1.0, 2.0])
    """Future horizons, seconds ahead."""
    future_poses: FuturePoses = FuturePoses.recorded
    """Where future targets' camera poses come from: ``recorded`` (the dataset's ego poses, i.e. the trajectory
    QA) or ``predicted`` (the LoRA'd LLM answers the trajectory question from the 4 history frames; scored as
    ``future_pred_<s>s`` against what the camera recorded)."""
    frames: Annotated[int, Ge(1)] = 10
    """Frames per held-out scene that are scored (the first N)."""
    batch_size: Annotated[int, Ge(1)] = 8
    """Views per sampling call."""
    fd_extractor: FdExtractor = FdExtractor.daisy
    """Features of the Fréchet distance: ``daisy`` (``fd_daisy``, approximate) or ``inception`` (FID, needs
    ``fd_weights``)."""
    fd_weights: str | None = None
    """Local TorchScript file of the standard Inception weights (``fd_extractor: inception``); never downloaded.
    Trusted input: ``torch.jit.load`` runs the file's TorchScript code (there is no weights-only TorchScript load), so
    point it only at a file your team exported or checked (e.g. by its published sha256), never at a user upload."""
    fvd_weights: str | None = None
    """Local I3D TorchScript file of FVD (``i3d_torchscript.pt``, the StyleGAN-V export): given, FVD is computed with
    it (a missing file is an error naming it; never downloaded; trusted input as ``fd_weights``); null: the labelled
    stand-in ``fd_video_daisy`` (DAISY features over the same clips, approximate) is reported instead."""
    fvd_clip_frames: Annotated[int, Ge(1)] = 10
    """Frames per FVD clip: consecutive scored frames of one scene, camera and target (the I3D export needs >= 10)."""
