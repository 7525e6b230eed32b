"""Reproducible stage executions: every stage starts from the same random state and thread count.

A Ray worker process runs many tasks, one after another, in an order the scheduler picks. Whatever a stage leaves in
the process-wide random generators (torch, numpy, ``random``) or in torch's thread count is what the next stage in
that worker starts from, so an unseeded draw (a module's weight init, a dropout mask) or a reduction split over a
different number of threads gives other numbers whenever the scheduling differs: alone or next to other trials, cold
or warm cache. ``stage_start`` resets all of it at the start of every stage execution, from the stage's seed.

``run.deterministic`` (one switch, ``null`` = on without CUDA) also makes CUDA kernels deterministic
(``torch.use_deterministic_algorithms``, cuDNN without autotuning, cuBLAS with a fixed workspace). That costs speed
on GPUs, so a GPU cluster may turn it off; on CPU the fixed thread count and seeds cost nothing measurable.
"""

from __future__ import annotations

import os
import random
import sys
from collections.abc import Iterable

CUBLAS_WORKSPACE = ":4096:8"
"""cuBLAS needs a fixed workspace for deterministic GEMMs; it reads the variable when CUDA initialises."""


def resolve(deterministic: bool | None) -> bool:
    """``run.deterministic`` where the stage runs: null means on without a CUDA device, off with one."""
    if deterministic is not None:
        return bool(deterministic)
    import torch

    return not torch.cuda.is_available()


def worker_env(deterministic: bool | None) -> dict[str, str]:
    """Environment of every Ray worker (set before a worker initialises CUDA): cuBLAS's fixed workspace unless
    determinism is switched off."""
    return {} if deterministic is False else {"CUBLAS_WORKSPACE_CONFIG": CUBLAS_WORKSPACE}


TORCH_LIBRARIES = frozenset({"torch", "transformers", "peft", "diffusers", "accelerate", "safetensors", "gsplat"})
"""Distributions whose use means torch runs in the stage (``gdwm.fingerprint``'s libraries of its code)."""


def uses_torch(libraries: Iterable[str] | None) -> bool:
    """Whether a stage whose code fingerprint lists ``libraries`` (None: unknown) needs torch seeded: it imports torch
    or a library built on it, or this process has torch already (an earlier task's state would carry over)."""
    return libraries is None or bool(TORCH_LIBRARIES & set(libraries)) or "torch" in sys.modules


def stage_start(seed: int, num_cpus: float, deterministic: bool | None, torch_used: bool = True) -> bool:
    """Seed ``random``, numpy and torch from ``seed``; when deterministic (see ``resolve``), one fixed torch thread
    count (the stage's CPU allotment, whatever Ray or an earlier task set) and deterministic CUDA kernels. Returns
    whether determinism is on. ``torch_used=False`` (``uses_torch``: the stage's code imports no torch, and no task
    of this process did) leaves torch unimported: seconds of a new worker's start that a light stage doesn't need."""
    random.seed(seed)
    import numpy as np

    np.random.seed(seed % 2**32)
    if not torch_used and "torch" not in sys.modules:
        return deterministic is not False
    import torch

    torch.manual_seed(seed)
    on = resolve(deterministic)
    if on:
        threads = max(1, int(num_cpus))
        if torch.get_num_threads() != threads:
            torch.set_num_threads(threads)
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", CUBLAS_WORKSPACE)
        torch.backends.cudnn.benchmark = False
        torch.backends.cudnn.deterministic = True
    # warn_only: an op without a deterministic CUDA kernel warns (naming itself) instead of failing the stage
    torch.use_deterministic_algorithms(on, warn_only=True)
    return on
