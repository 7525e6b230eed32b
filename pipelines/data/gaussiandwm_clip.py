"""The release's CLIP text-feature shards: ``[N, D]`` float ``.npy`` files, one row per QA record.

A QA record names its feature with ``clip_text_embed_path`` (relative to the release's CLIP root, ``clip_text_root``)
and ``clip_text_embed_row``, as the release's ``data/records.py`` maps them; its ``data/clip_text_features.py``
reads ``shard[row]`` of a ``[N, 512]`` array. Shards are loaded without pickles and memory-mapped, so a check reads
only the header.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipelines.data.layout import DataError, contained, numpy_load_error


class ClipChecker:
    """Resolves a record's shard inside the source and checks its shape, dtype and row; each shard is read once."""

    def __init__(self, src: Path, clip_root: str, dim: int):
        self.src = src
        self.clip_root = clip_root
        self.dim = dim
        self._rows: dict[Path, int] = {}

    def check(self, at: str, rel: str, row: int) -> Path:
        path = contained(self.src, Path(self.clip_root, rel), f"{at}: clip_text_embed_path")
        if not path.is_file():
            raise DataError(f"{at}: clip_text_embed_path {rel} not found under {self.src / self.clip_root}")
        if path not in self._rows:
            self._rows[path] = self._shard_rows(path, f"{at}: clip_text_embed_path {rel}")
        n = self._rows[path]
        if row >= n:
            raise DataError(f"{at}: clip_text_embed_row {row} is out of range for {rel} ({n} rows)")
        return path

    def _shard_rows(self, path: Path, where: str) -> int:
        try:
            shard = np.load(path, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError, EOFError) as e:
            raise DataError(f"{where}: not a readable .npy ({numpy_load_error(e)})") from e
        if not isinstance(shard, np.ndarray) or shard.ndim != 2 or shard.shape[1] != self.dim:
            shape = list(shard.shape) if isinstance(shard, np.ndarray) else type(shard).__name__
            raise DataError(f"{where}: shard has shape {shape}, expected [N, {self.dim}] (data.clip_dim)")
        if shard.dtype.kind != "f":
            raise DataError(f"{where}: shard dtype is {shard.dtype}, expected a float type")
        return int(shard.shape[0])
