"""What differs between two environment records, in words: the lines ``gdwm reproduce``, ``gdwm compare`` and
``gdwm regress`` print (``toylib 1.0 -> 2.0``, ``CPU capability AVX2 -> AVX512``)."""

from __future__ import annotations

from typing import Any

from gdwm.environment.record import commit_tag

_FIELDS = (
    ("Python", ("python", "version")),
    ("Python implementation", ("python", "implementation")),
    ("OS", ("os", "system")),
    ("machine", ("os", "machine")),
    ("libc", ("os", "libc")),
    ("CPU", ("cpu", "model")),
    ("CPU capability", ("cpu", "capability")),
    ("usable cores", ("cpu", "usable")),
    ("torch threads", ("threads", "torch")),
    ("torch interop threads", ("threads", "torch_interop")),
    ("torch", ("torch", "version")),
    ("torch git", ("torch", "git")),
    ("torch CUDA", ("torch", "cuda")),
    ("cuDNN", ("torch", "cudnn")),
    ("GPU driver", ("gpu", "driver")),
    ("CUDA driver", ("gpu", "cuda_driver")),
)


def _get(rec: dict[str, Any], path: tuple[str, ...]) -> Any:
    for key in path:
        rec = rec.get(key) if isinstance(rec, dict) else None
    return rec


def _shown(value: Any) -> str:
    return "none" if value is None else str(value)


def differences(a: dict[str, Any], b: dict[str, Any], *, code: bool = True) -> list[str]:
    """``a`` -> ``b``, one line each: gdwm's code (with ``code``), machine and build fields, GPUs, then every
    distribution added, removed or at another version. Empty when the environments are the same."""
    out = []
    if code and commit_tag(a) != commit_tag(b):
        out.append(f"gdwm {commit_tag(a)} -> {commit_tag(b)}")
    for label, path in _FIELDS:
        x, y = _get(a, path), _get(b, path)
        if x != y:
            out.append(f"{label} {_shown(x)} -> {_shown(y)}")
    for var in sorted({k for r in (a, b) for k in r.get("threads", {}) if k.isupper()}):
        x, y = a.get("threads", {}).get(var), b.get("threads", {}).get(var)
        if x != y:
            out.append(f"{var} {x or 'unset'} -> {y or 'unset'}")
    gx = [d["name"] for d in (a.get("gpu") or {}).get("devices", [])]
    gy = [d["name"] for d in (b.get("gpu") or {}).get("devices", [])]
    if gx != gy:
        out.append(f"GPUs {', '.join(gx) or 'none'} -> {', '.join(gy) or 'none'}")
    if _get(a, ("torch", "version")) == _get(b, ("torch", "version")) and (
        _get(a, ("torch", "config")) != _get(b, ("torch", "config"))
    ):
        out.append("torch build configuration (BLAS, LAPACK, oneDNN, flags: torch.__config__.show()) differs")
    da, db = a.get("distributions", {}), b.get("distributions", {})
    for name in sorted(da.keys() | db.keys()):
        if da.get(name) != db.get(name):
            out.append(f"{name} {da.get(name, 'absent')} -> {db.get(name, 'absent')}")
    return out


def brief(lines: list[str], limit: int = 6) -> str:
    """The first ``limit`` differences on one line, with how many more."""
    more = len(lines) - limit
    return "; ".join(lines[:limit]) + (f"; and {more} more" if more > 0 else "")
