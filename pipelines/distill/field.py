"""The reconstructed field as distillation sees it: canonical Gaussians, their poses per frame, and per-view
compositing weights over the canonical rows.

Legend: N canonical Gaussians, V views, P = H*W pixels, d_f feature dims.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from model_zoo.render import composite_weights
from pipelines.recon.init import View
from pipelines.recon.optimize import FramePoses, Gaussians, camera_of


@dataclass
class Field:
    g: Gaussians
    instances: list[str]
    poses: dict[int, FramePoses]
    excluded_frames: list[int]


def load_field(rec_dir: Path) -> Field:
    state = torch.load(rec_dir / "canonical.pt", map_location="cpu", weights_only=True)
    meta = json.loads((rec_dir / "instances.json").read_text())
    qc = json.loads((rec_dir / "qc.json").read_text())
    g = Gaussians(**state)
    poses = {
        int(f): FramePoses.build(meta["instances"], {k: np.asarray(m).reshape(4, 4) for k, m in ps.items()})
        for f, ps in meta["poses"].items()
    }
    return Field(g, meta["instances"], poses, list(qc["excluded_frames"]))


def view_weights(field: Field, v: View, min_weight: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """(sparse CSR [P, N] weights over canonical rows, weights < ``min_weight`` dropped; rows visible then)."""
    g = field.g
    with torch.no_grad():
        means, quats, keep = field.poses[v.frame].apply(g)
        w = composite_weights(
            means, g.log_scales[keep].exp(), quats, torch.sigmoid(g.opacity_logits[keep]), camera_of(v)
        )
        w = on_rows(w, torch.nonzero(keep).squeeze(1), len(g), min_weight)
    return w, keep


def on_rows(w: torch.Tensor, rows: torch.Tensor, n: int, min_weight: float = 0.0) -> torch.Tensor:
    """CSR ``[P, n]``: the coalesced weights ``w`` of the visible Gaussians with column j renumbered to ``rows[j]``
    (increasing), weights < ``min_weight`` dropped. Still sorted and unique, so no second coalesce (a tenth of the
    time: ``python -m benchmarks distill``)."""
    idx, vals = w.indices(), w.values()
    big = vals >= min_weight
    out = torch.sparse_coo_tensor(torch.stack([idx[0, big], rows[idx[1, big]]]), vals[big], (w.shape[0], n),
                                  is_coalesced=True)  # fmt: skip
    return out.to_sparse_csr()
