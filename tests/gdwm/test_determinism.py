"""Every stage starts from the same state whatever ran before it in the worker (gdwm.determinism), and a seeded
stage's seed is part of its config and key (gdwm.executor.stage_config)."""

from __future__ import annotations

import random

import numpy as np
import torch
from omegaconf import OmegaConf

from gdwm.determinism import resolve, stage_start, worker_env
from gdwm.executor import RunEnv, stage_config, stage_key
from gdwm.stage import StageDef


def _draws() -> tuple:
    return random.random(), float(np.random.rand()), torch.rand(3).tolist()


def test_stage_start_resets_generators_and_threads_whatever_ran_before():
    threads = torch.get_num_threads()
    try:
        stage_start(7, 1, None)
        first = _draws()
        torch.set_num_threads(2)  # another task in the same worker: other threads, other draws
        _draws()
        torch.rand(100)
        stage_start(7, 1, None)
        assert _draws() == first
        assert torch.get_num_threads() == 1 and torch.are_deterministic_algorithms_enabled()
        stage_start(8, 1, None)
        assert _draws() != first
        stage_start(7, 2, False)  # switched off: seeds still apply, threads and kernels are left alone
        assert _draws() == first and torch.get_num_threads() == 1 and not torch.are_deterministic_algorithms_enabled()
    finally:
        torch.use_deterministic_algorithms(False)
        torch.set_num_threads(threads)


LAZY = """
import json, sys
from gdwm.determinism import stage_start, stage_end
stage_start(7, 1, None)
before = "torch" in sys.modules  # a stage that never imports torch does not pay for it
import torch  # the stage imports it: set up then, as stage_start would have done
out = [before, torch.rand(3).tolist(), torch.get_num_threads(), torch.are_deterministic_algorithms_enabled()]
stage_end()
out.append([type(f).__name__ for f in sys.meta_path if type(f).__name__ == "_TorchOnImport"])
print(json.dumps(out))
"""


def test_a_stage_that_imports_torch_late_gets_the_state_an_early_import_gives():
    import json
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-c", LAZY], capture_output=True, text=True, timeout=120, check=True)
    before, draws, threads, det, hooks = json.loads(r.stdout)
    threads_now = torch.get_num_threads()
    try:
        stage_start(7, 1, None)  # torch imported here already
        assert (before, draws, threads, det, hooks) == (False, torch.rand(3).tolist(), 1, True, [])
    finally:
        torch.use_deterministic_algorithms(False)
        torch.set_num_threads(threads_now)


def test_null_means_on_without_cuda_and_workers_get_the_cublas_workspace():
    assert resolve(None) is (not torch.cuda.is_available())
    assert resolve(True) is True and resolve(False) is False
    assert worker_env(None) == {"CUBLAS_WORKSPACE_CONFIG": ":4096:8"} and worker_env(False) == {}


def _noop(ctx):
    return None


def test_a_seeded_stage_carries_the_trial_seed_in_config_and_key():
    cfg = OmegaConf.create({"seed": 3, "stage": {"x": {"lr": 0.1}}})
    seeded = StageDef("lora", "1", _noop, config=("stage.x",), seeded=True)
    free = StageDef("distill", "1", _noop, config=("stage.x",))
    assert stage_config(seeded, cfg) == {"stage.x": {"lr": 0.1}, "seed": 3}
    assert stage_config(free, cfg) == {"stage.x": {"lr": 0.1}}
    env = RunEnv("/c", "/d", "fp", ("s",), "/k", None, None, None, {})
    other = OmegaConf.merge(cfg, {"seed": 4})
    assert stage_key(seeded, stage_config(seeded, cfg), {}, env) != stage_key(
        seeded, stage_config(seeded, other), {}, env
    )
    assert stage_key(free, stage_config(free, cfg), {}, env) == stage_key(free, stage_config(free, other), {}, env)


def test_model_seeds_follow_the_trial_seed_unless_pinned():
    from gdwm.config import load_config

    cfg = load_config(["seed=5"])
    assert (cfg.model.llm.seed, cfg.model.selector.seed) == (5, 5)
    pinned = load_config(["seed=5", "model.llm.seed=1"])
    assert (pinned.model.llm.seed, pinned.model.selector.seed) == (1, 5)


FLAGS = """
import json, sys
import torch
mode = sys.argv[1]
if mode.startswith("loaded-"):  # inductor in the process already (a stage that compiled, a dynamo import)
    import torch._inductor.config
on = mode.endswith("on")
if mode.startswith("torch"):
    torch.use_deterministic_algorithms(on, warn_only=True)
else:
    from gdwm.determinism import stage_start
    stage_start(7, 1, on)
loaded = "torch._inductor" in sys.modules
import torch._inductor.config as inductor
print(json.dumps([torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled(),
                  inductor.deterministic, loaded]))
"""


def _flags(mode: str) -> list:
    import json
    import os
    import subprocess
    import sys

    from gdwm.determinism import INDUCTOR_DETERMINISTIC

    env = {k: v for k, v in os.environ.items() if k != INDUCTOR_DETERMINISTIC}
    r = subprocess.run([sys.executable, "-c", FLAGS, mode], capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout)


def test_stage_start_sets_torchs_deterministic_flags_as_torch_does_without_loading_inductor():
    # torch.use_deterministic_algorithms imports TorchInductor (1.5-2 s of a worker's CPU) to set its copy of the
    # flag; stage_start gives the same flags (torch's core, warn_only, inductor's copy once it loads) without it
    for on in (True, False):
        torch_flags, gdwm_flags = _flags(f"torch-{'on' if on else 'off'}"), _flags(f"gdwm-{'on' if on else 'off'}")
        assert gdwm_flags[:3] == torch_flags[:3] and gdwm_flags[0] is gdwm_flags[2] is on
        assert (torch_flags[3], gdwm_flags[3]) == (True, False)  # inductor loaded by torch's function, not by ours
    assert _flags("loaded-gdwm-on") == _flags("loaded-torch-on") == [True, True, True, True]
    off = _flags("loaded-gdwm-off")
    assert off == _flags("loaded-torch-off") and (off[0], off[2], off[3]) == (False, False, True)
