"""Stage cache: cost of a verified cache hit (manifest + sha256 of every file) against an unverified one."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from benchmarks.common import Result, median_time
from gdwm.cache import Cache, cache_key

N_FILES, FILE_BYTES = 10, 4096


def run(quick: bool = False) -> list[Result]:
    repeats = 20 if quick else 50
    config, upstream = {"lora": {"rank": 8, "alpha": 16.0}}, {"tokenizer": "0" * 64}
    key = cache_key("lora", "1", config, upstream, "bench")
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp, "src")
        src.mkdir()
        for i in range(N_FILES):
            Path(src, f"part_{i:02d}.bin").write_bytes(os.urandom(FILE_BYTES))
        cache = Cache(Path(tmp, "cache"))
        cache.publish("lora", key, src, config=config, upstream=upstream, data_fingerprint="bench", version="1")
        # Both sides read the same published entry with a warm page cache; only verification differs.
        t_verify, _ = median_time(lambda: cache.lookup("lora", key), repeats, warmup=3)
        t_plain, _ = median_time(lambda: cache.lookup("lora", key, verify=False), repeats, warmup=3)
        assert cache.lookup("lora", key) is not None
    detail = f"local fs, {N_FILES} files x {FILE_BYTES // 1024} KiB, page cache warm, median of {repeats}"
    return [
        Result("cache", "lookup + verify (size and sha256 of every file)", t_verify * 1e3, "ms", 5.0, "<=", detail),
        Result("cache", "lookup, manifest only (verify=False)", t_plain * 1e3, "ms", detail=detail),
        Result("cache", "verify overhead (verified / manifest only)", t_verify / t_plain, "x", detail=detail),
    ]
