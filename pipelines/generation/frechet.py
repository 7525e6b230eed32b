"""Fréchet distances between generated and real views, named by what computed them.

- ``fid``: only with the standard Inception weights, a TorchScript file from a local path (the torchmetrics /
  pytorch-fid ``pt_inception-2015-12-05`` export taking [0, 255] images and returning 2048-d pool features).
- ``fd_<extractor>`` (protocol ``approximate``) with anything else, e.g. ``fd_daisy``: our frozen CPU descriptor,
  pooled over the image.
- ``fvd``: only with the I3D TorchScript file (``i3d_torchscript.pt``, the StyleGAN-V export of the Kinetics-400 I3D
  the reference FVD uses) from a local path; a path that holds no such file is a clear error naming it, never a
  download.
- ``fd_video_daisy`` (protocol ``approximate``): the labelled stand-in for FVD when no I3D path is given; the DAISY
  descriptor per frame, pooled over each clip with its frame-to-frame change. It is never named ``fvd``.

Legend: ``N`` images (or clips), ``T`` frames per clip, ``D`` feature width.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy import linalg


def frechet_distance(mu1_D: np.ndarray, cov1_DD: np.ndarray, mu2_D: np.ndarray, cov2_DD: np.ndarray) -> float:
    """||mu1 - mu2||^2 + Tr(C1 + C2 - 2 (C1 C2)^(1/2)) (Heusel et al. 2017), via scipy's ``sqrtm``; the tiny
    imaginary parts of a numerically non-PSD product are dropped (with an offset retry when it is singular)."""
    diff = mu1_D - mu2_D
    with warnings.catch_warnings():  # singular products (fewer images than dimensions) are expected here
        warnings.simplefilter("ignore", (linalg.LinAlgWarning, RuntimeWarning))
        covmean = linalg.sqrtm(cov1_DD @ cov2_DD)
        if not np.isfinite(covmean).all():
            offset = np.eye(len(mu1_D)) * 1e-6
            covmean = linalg.sqrtm((cov1_DD + offset) @ (cov2_DD + offset))
    covmean = np.real(covmean)
    return float(diff @ diff + np.trace(cov1_DD) + np.trace(cov2_DD) - 2.0 * np.trace(covmean))


def feature_stats(feats_ND: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    f = np.asarray(feats_ND, dtype=np.float64)
    if len(f) < 2:
        raise ValueError(f"a Fréchet distance needs >= 2 images per side, got {len(f)}")
    return f.mean(0), np.cov(f, rowvar=False)


@dataclass
class Extractor:
    """What turns images into features, and how its distance is named."""

    name: str
    """Metric name: ``fid`` or ``fd_<extractor>``."""
    protocol: str
    """``official`` (standard Inception weights) or ``approximate``."""
    source: str
    """What was used (a weight file path, or the descriptor's settings)."""
    fn: object

    def __call__(self, images_N3HW: torch.Tensor) -> np.ndarray:
        return self.fn(images_N3HW)


def inception_extractor(path: str | Path) -> Extractor:
    """FID's extractor: the standard Inception TorchScript file at ``path`` (never downloaded)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"FID needs the standard Inception weights as a TorchScript file; {path} does not exist "
            "(export pt_inception-2015-12-05 to TorchScript and pass its local path)"
        )
    net = torch.jit.load(str(path), map_location="cpu").eval()  # runs its code: an operator-vetted file only

    @torch.no_grad()
    def run(images: torch.Tensor) -> np.ndarray:
        return net((images.clamp(0, 1) * 255).to(torch.uint8)).reshape(len(images), -1).double().numpy()

    return Extractor("fid", "official", str(path), run)


def daisy_extractor(d_f: int = 64, seed: int = 0) -> Extractor:
    """The frozen CPU foundation descriptor (DAISY projected to ``d_f``), mean- and max-pooled over the image."""
    from model_zoo import registry
    from model_zoo.encoders.daisy import DaisyConfig

    enc = registry.build("encoder", "daisy", DaisyConfig(d_f=d_f, seed=seed))

    @torch.no_grad()
    def run(images: torch.Tensor) -> np.ndarray:
        out = []
        for img in images:
            u8 = (img.clamp(0, 1).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
            f = enc.encode(u8, out_hw=u8.shape[:2]).float().reshape(-1, d_f)
            out.append(torch.cat([f.mean(0), f.amax(0)]).double().numpy())
        return np.stack(out)

    return Extractor("fd_daisy", "approximate", f"daisy d_f={d_f} seed={seed}, mean+max pooled", run)


def build_extractor(kind: str, path: str | None = None) -> Extractor:
    if kind == "inception":
        if path is None:
            raise FileNotFoundError("FID needs the standard Inception TorchScript file: set its local path")
        return inception_extractor(path)
    if kind == "daisy":
        return daisy_extractor()
    raise ValueError(f"unknown Fréchet feature extractor '{kind}' (inception, daisy)")


I3D_FILE = "i3d_torchscript.pt"
"""The file FVD expects: the StyleGAN-V TorchScript export of the Kinetics-400 I3D (taking ``[N, 3, T, H, W]`` uint8
videos with ``rescale``, ``resize`` and ``return_features`` flags and returning 400-d logit features)."""

STANDIN_NAME = "fd_video_daisy"
"""Metric name of FVD's stand-in (an ``fd_`` name: a Fréchet distance, lower is better, never called FVD)."""


def missing_i3d_message(path: str | Path | None) -> str:
    """The error of an FVD run without its I3D file, naming what was expected where."""
    if path is None:
        return (
            f"FVD needs the I3D TorchScript file {I3D_FILE} from a local path; none was given "
            "(set stage.evaluate_gen.fvd_weights=/path/to/i3d_torchscript.pt; it is never downloaded)"
        )
    return (
        f"FVD needs the I3D TorchScript file {I3D_FILE}; stage.evaluate_gen.fvd_weights={path} does not exist "
        "(place the StyleGAN-V i3d_torchscript.pt export there; it is never downloaded)"
    )


def fvd_extractor(path: str | Path | None) -> Extractor:
    """FVD's I3D network from the local TorchScript file at ``path``; anything else is ``missing_i3d_message``."""
    if path is None or not Path(path).is_file():
        raise FileNotFoundError(missing_i3d_message(path))
    net = torch.jit.load(str(path), map_location="cpu").eval()  # runs its code: an operator-vetted file only

    @torch.no_grad()
    def run(videos_NT3HW: torch.Tensor) -> np.ndarray:
        # StyleGAN-V's call: uint8 [N, 3, T, H, W], rescaled to [-1, 1] and resized to 224 inside the network
        u8 = (videos_NT3HW.clamp(0, 1) * 255).round().to(torch.uint8).permute(0, 2, 1, 3, 4)
        feats = net(u8, rescale=True, resize=True, return_features=True)
        return feats.reshape(len(videos_NT3HW), -1).double().numpy()

    return Extractor("fvd", "official", str(path), run)


def daisy_video_extractor(d_f: int = 64, seed: int = 0) -> Extractor:
    """FVD's labelled stand-in: per clip, [mean over frames, mean |change between consecutive frames|] of the
    per-frame DAISY features (``daisy_extractor``), so both appearance and temporal flicker move the distance."""
    frame = daisy_extractor(d_f, seed)

    def run(videos_NT3HW: torch.Tensor) -> np.ndarray:
        N, T = videos_NT3HW.shape[:2]
        if T < 2:
            raise ValueError(f"{STANDIN_NAME}: clips need >= 2 frames, got {T}")
        f_NTD = frame(videos_NT3HW.reshape(N * T, *videos_NT3HW.shape[2:])).reshape(N, T, -1)
        return np.concatenate([f_NTD.mean(1), np.abs(np.diff(f_NTD, axis=1)).mean(1)], axis=1)

    source = f"stand-in for FVD (no I3D weights): {frame.source}, per clip [frame mean, mean |frame change|]"
    return Extractor(STANDIN_NAME, "approximate", source, run)


def build_video_extractor(i3d_path: str | None) -> Extractor:
    """FVD with the I3D file at ``i3d_path`` (an error naming it when it is missing); no path: the DAISY stand-in."""
    return daisy_video_extractor() if i3d_path is None else fvd_extractor(i3d_path)


def label(extractor: Extractor) -> str:
    """What ``protocol.json`` and the tracker record of a Fréchet metric: name, protocol and source."""
    return f"{extractor.name}: {extractor.protocol} ({extractor.source})"


def frechet(real_N3HW: torch.Tensor, fake_N3HW: torch.Tensor, extractor: Extractor) -> float:
    """The Fréchet distance between two image sets under ``extractor``."""
    return frechet_distance(*feature_stats(extractor(real_N3HW)), *feature_stats(extractor(fake_N3HW)))
