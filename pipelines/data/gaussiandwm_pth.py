"""One GaussianDWM release ``.pth`` (a LangSplat/3DGS state dict) -> activated Gaussian arrays.

Loading is ``torch.load(weights_only=True)`` only: tensors, containers and plain numeric numpy
arrays are allowed; any other pickled object is refused and the file is never retried unsafely.

Legend: N Gaussians, D feature-code width.
"""

from __future__ import annotations

import pickle
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pipelines.data.layout import DataError

SH_C0 = 0.28209479177387814  # zeroth-order real spherical harmonic (3DGS colour = 0.5 + C0 * dc)
GREY = 0.5
NESTED_KEY = "gaussians_state"
_REFUSED_GLOBAL = re.compile(r"GLOBAL ([A-Za-z_][\w.]*[\w])")
_TORCH_ADVICE = ("Weights only load failed", "Check the documentation", "(1)", "(2)")

_np_core = getattr(np, "_core", None) or np.core  # numpy 2 renamed numpy.core
# Plain numeric arrays only: object arrays still fail, their elements would need more globals.
_NUMPY_GLOBALS = [
    _np_core.multiarray._reconstruct,
    np.ndarray,
    np.dtype,
    np.dtypes.Float16DType,
    np.dtypes.Float32DType,
    np.dtypes.Float64DType,
]


@dataclass(frozen=True)
class ReleaseGaussians:
    """Activated Gaussians of one file, in the release's coordinate frame."""

    arrays: dict[str, np.ndarray]  # xyz_N3, scale_N3, rotation_N4 (unit), opacity_N, color_N3, feature_ND
    has_color: bool  # False: no _features_dc, colour is GREY

    @property
    def count(self) -> int:
        return int(self.arrays["xyz"].shape[0])


def load_payload(path: Path, where: str) -> object:
    """``torch.load(weights_only=True)``; a refused or corrupt file is a DataError naming ``where``."""
    try:
        with torch.serialization.safe_globals(_NUMPY_GLOBALS):
            return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        raise DataError(
            f"{where}: refused by torch.load(weights_only=True): {refusal(str(e))} "
            "(only tensors, containers and numeric arrays are accepted; it is never loaded unsafely)"
        ) from e
    except (RuntimeError, EOFError, KeyError, ValueError, OSError) as e:
        raise DataError(f"{where}: not a readable torch file ({type(e).__name__}: {e})") from e


def refusal(message: str) -> str:
    """What torch's weights-only unpickler refused, e.g. ``unsupported GLOBAL posix.system``.

    Its message leads with advice to retry with ``weights_only`` turned off, which must never be followed for a
    downloaded file; the refused global (or else the first line that is not that advice) is what to report.
    """
    found = _REFUSED_GLOBAL.search(message)
    if found:
        return f"unsupported GLOBAL {found.group(1)}"
    detail = message.split("WeightsUnpickler error:", 1)[-1]
    lines = [ln.strip() for ln in detail.splitlines() if ln.strip()]
    specific = [ln for ln in lines if not ln.startswith(_TORCH_ADVICE)]
    return (specific or lines or ["unpickling refused"])[0]


def state_of(payload: object, where: str) -> Mapping:
    """The field dict, whether at the top level or nested under ``gaussians_state``."""
    if not isinstance(payload, Mapping):
        raise DataError(f"{where}: expected a dict of Gaussian fields, got {type(payload).__name__}")
    nested = payload.get(NESTED_KEY)
    if nested is not None:
        if not isinstance(nested, Mapping):
            raise DataError(f"{where}: '{NESTED_KEY}' is a {type(nested).__name__}, expected a dict")
        return nested
    return payload


def read_release_gaussians(path: Path, where: str, feature_dim: int) -> ReleaseGaussians:
    """Load, validate (naming ``where`` and the release's field) and activate one ``.pth``."""
    state = state_of(load_payload(path, where), where)
    xyz = _field(state, "_xyz", where)
    n = xyz.shape[0] if xyz.ndim == 2 else -1
    _check_shape(xyz, "_xyz", (n, 3), where)
    scaling = _check_shape(_field(state, "_scaling", where), "_scaling", (n, 3), where)
    rotation = _check_shape(_field(state, "_rotation", where), "_rotation", (n, 4), where)
    opacity = _field(state, "_opacity", where)
    opacity = _check_shape(opacity.reshape(-1, 1) if opacity.ndim == 1 else opacity, "_opacity", (n, 1), where)
    feature = _check_shape(_field(state, "_language_feature", where), "_language_feature", (n, feature_dim), where)
    dc = state.get("_features_dc")
    if dc is not None:
        dc = _field(state, "_features_dc", where)
        dc = _check_shape(dc.reshape(n, 3) if dc.shape == (n, 1, 3) else dc, "_features_dc", (n, 3), where)

    with np.errstate(over="ignore"):  # overflow is reported below, naming the file
        scale = np.exp(scaling.astype(np.float64)).astype(np.float32)
    bad = ~np.isfinite(scale) | (scale <= 0)
    if bad.any():
        raise DataError(
            f"{where}: field '_scaling' gives exp(_scaling) outside float32 range "
            f"({int(bad.sum())} values, first at row {_first_row(bad)})"
        )
    norm = np.linalg.norm(rotation.astype(np.float64), axis=1, keepdims=True)
    if (norm < 1e-8).any():
        raise DataError(f"{where}: field '_rotation' has a zero quaternion at row {_first_row(norm < 1e-8)}")
    arrays = {
        "xyz": xyz,
        "scale": scale,
        "rotation": (rotation / norm).astype(np.float32),
        # Our schema stores probabilities; the release stores logits (tanh form avoids exp overflow).
        "opacity": (0.5 * (1.0 + np.tanh(0.5 * opacity.astype(np.float64)))).astype(np.float32).reshape(-1),
        "color": np.full((n, 3), GREY, np.float32) if dc is None else _sh_dc_to_rgb(dc),
        "feature": feature,
    }
    return ReleaseGaussians(arrays, has_color=dc is not None)


def concat(parts: list[ReleaseGaussians]) -> dict[str, np.ndarray]:
    """Gaussians of several files of one frame (e.g. one file per view) as one set."""
    return {k: np.concatenate([p.arrays[k] for p in parts], axis=0) for k in parts[0].arrays}


def _sh_dc_to_rgb(dc_N3: np.ndarray) -> np.ndarray:
    return np.clip(GREY + SH_C0 * dc_N3.astype(np.float64), 0.0, 1.0).astype(np.float32)


def _field(state: Mapping, key: str, where: str) -> np.ndarray:
    if key not in state:
        raise DataError(f"{where}: missing field '{key}' (has {sorted(map(str, state))})")
    value = state[key]
    if isinstance(value, torch.Tensor):
        # float() first: numpy has no bfloat16.
        arr = value.detach().to("cpu", torch.float32).numpy()
    elif isinstance(value, np.ndarray) and np.issubdtype(value.dtype, np.number):
        arr = value.astype(np.float32)
    else:
        raise DataError(f"{where}: field '{key}' is a {type(value).__name__}, expected a tensor")
    bad = ~np.isfinite(arr)
    if bad.any():
        raise DataError(f"{where}: field '{key}' has NaN/Inf ({int(bad.sum())} values, first at row {_first_row(bad)})")
    return arr


def _check_shape(arr: np.ndarray, key: str, want: tuple[int, int], where: str) -> np.ndarray:
    n, width = want
    if arr.ndim != 2 or arr.shape[1] != width or (n >= 0 and arr.shape[0] != n):
        rows = "N" if n < 0 else str(n)
        raise DataError(f"{where}: field '{key}' has shape {list(arr.shape)}, expected [{rows}, {width}]")
    return arr


def _first_row(mask: np.ndarray) -> int:
    return int(np.argwhere(mask)[0][0]) if mask.ndim else 0
