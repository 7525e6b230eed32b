"""Code fingerprints of the whole pipeline: cold (every module parsed), warm (a new launch: the per-file cache on
disk, nothing parsed) and memoised (the trials of one launch after the first).

The warm figure is what every ``gdwm run`` pays before it plans, so a cached re-run stays fast: target <= 50 ms.
"""

from __future__ import annotations

import os
import tempfile

from benchmarks.common import Result, median_time
from gdwm import fingerprint
from gdwm.config import load_config
from gdwm.dag import load_pipeline
from gdwm.executor import stage_config

TARGET_WARM_MS = 50.0


def run(quick: bool = False) -> list[Result]:
    cfg = load_config(["experiment=demo"])
    pipe = load_pipeline(cfg, None)
    subsets = {n: stage_config(pipe.stages[n], cfg) for n in pipe.order}
    repeats = 5 if quick else 20

    def all_stages() -> dict[str, fingerprint.CodeFingerprint]:
        return {n: fingerprint.stage_fingerprint(pipe.stages[n], subsets[n]) for n in pipe.order}

    old = os.environ.get("GDWM_LOCAL_CACHE")
    with tempfile.TemporaryDirectory() as d:
        os.environ["GDWM_LOCAL_CACHE"] = d
        try:

            def cold():
                fingerprint.clear()
                for f in fingerprint._FileCache.path().parent.glob("fingerprints-*.json"):
                    f.unlink()
                return all_stages()

            def warm():
                fingerprint.clear()  # a new process: nothing memoised, the per-file cache on disk
                return all_stages()

            t_cold, _ = median_time(cold, repeats, warmup=1)
            cold()
            t_warm, _ = median_time(warm, repeats, warmup=1)
            t_memo, _ = median_time(all_stages, repeats, warmup=1)
            fps = all_stages()
        finally:
            if old is None:
                os.environ.pop("GDWM_LOCAL_CACHE", None)
            else:
                os.environ["GDWM_LOCAL_CACHE"] = old
    files = len({f for fp in fps.values() for f in fp.files})
    detail = f"{len(fps)} stages of experiment=demo, {files} first-party modules, median of {repeats}"
    return [
        Result("fingerprint", "cold (parse every module)", t_cold * 1e3, "ms", detail=detail),
        Result(
            "fingerprint", "warm (new launch, per-file cache on disk)", t_warm * 1e3, "ms", TARGET_WARM_MS, "<=", detail
        ),
        Result("fingerprint", "memoised (later trials of a launch)", t_memo * 1e3, "ms", detail=detail),
    ]
