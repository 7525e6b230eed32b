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

import contextlib
import importlib.abc
import os
import random
import sys
from collections.abc import Callable
from typing import Any

CUBLAS_WORKSPACE = ":4096:8"
"""cuBLAS needs a fixed workspace for deterministic GEMMs; it reads the variable when CUDA initialises."""
INDUCTOR_DETERMINISTIC = "TORCHINDUCTOR_DETERMINISTIC"
"""TorchInductor's ``config.deterministic`` is this variable == "1" when inductor loads."""


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


def stage_start(seed: int, num_cpus: float, deterministic: bool | None) -> None:
    """Seed ``random``, numpy and torch from ``seed``; when deterministic (see ``resolve``), one fixed torch thread
    count (the stage's CPU allotment, whatever Ray or an earlier task set) and deterministic CUDA kernels.

    A process that has not imported torch is not made to: torch is set up the moment the stage first imports it
    (``_TorchOnImport``), so a stage that never uses torch (a light per-scene step, a file-writing toy) is spared
    the seconds of its import in every new worker, and one that does sees exactly the state an early import would
    have given it (the import itself draws nothing)."""
    random.seed(seed)
    import numpy as np

    np.random.seed(seed % 2**32)
    _TorchOnImport.remove()
    if "torch" in sys.modules:
        _torch_start(sys.modules["torch"], seed, num_cpus, deterministic)
    else:
        _TorchOnImport.install(lambda torch: _torch_start(torch, seed, num_cpus, deterministic))


def stage_end() -> None:
    """The stage is over: a later import of torch in this process is no longer its to set up."""
    _TorchOnImport.remove()


def _torch_start(torch, seed: int, num_cpus: float, deterministic: bool | None) -> None:
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
    _use_deterministic_algorithms(torch, on)


def _use_deterministic_algorithms(torch, on: bool) -> None:
    """``torch.use_deterministic_algorithms(on, warn_only=True)`` without the import of TorchInductor it makes to
    set inductor's own copy of the flag (1.5-2 CPU-s of inductor, dynamo and sympy in every worker that runs a stage,
    most of which never compile anything): the flag goes to torch's core as that function sets it; inductor's copy
    is set where inductor is loaded, else left in the variable inductor reads when it loads."""
    inductor = sys.modules.get("torch._inductor.config")
    if inductor is not None:
        inductor.deterministic = on
    else:
        os.environ[INDUCTOR_DETERMINISTIC] = "1" if on else "0"
    torch._C._set_deterministic_algorithms(on, warn_only=True)


class _TorchOnImport(importlib.abc.MetaPathFinder):
    """Runs a callback on the ``torch`` module right after its first import in this process, then leaves
    ``sys.meta_path``. Written here because the standard library has no post-import hook: it finds torch's spec
    with the other finders and wraps its loader for the one ``exec_module`` call."""

    _installed: _TorchOnImport | None = None

    def __init__(self, then: Callable[[Any], object]):
        self.then = then

    @classmethod
    def install(cls, then: Callable[[Any], object]) -> None:
        cls.remove()
        cls._installed = cls(then)
        sys.meta_path.insert(0, cls._installed)

    @classmethod
    def remove(cls) -> None:
        if cls._installed is not None:
            with contextlib.suppress(ValueError):
                sys.meta_path.remove(cls._installed)
            cls._installed = None

    def find_spec(self, name, path=None, target=None):
        if name != "torch":
            return None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(name, path, target)
            if spec is not None and spec.loader is not None:
                spec.loader = _ThenLoader(spec.loader, self)
                return spec
        return None


class _ThenLoader(importlib.abc.Loader):
    """torch's own loader for one ``exec_module``, then the callback (and the module keeps its real loader)."""

    def __init__(self, loader: importlib.abc.Loader, hook: _TorchOnImport):
        self.loader, self.hook = loader, hook

    def create_module(self, spec):
        return self.loader.create_module(spec)

    def exec_module(self, module) -> None:
        module.__loader__ = self.loader
        if module.__spec__ is not None:
            module.__spec__.loader = self.loader
        self.loader.exec_module(module)
        if _TorchOnImport._installed is self.hook:
            _TorchOnImport.remove()
            self.hook.then(module)
