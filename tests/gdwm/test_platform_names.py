"""The platform names no pipeline: no file under ``platform/gdwm`` mentions a dataset, stage or module of the pipelines
that plug into it, in code, strings or comments alike. Pipelines bring those through their entry points (schemas,
``gdwm data`` commands, performance benchmarks) and ``conf/`` (defaults such as ``gdwm compare``'s layout)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from gdwm.config import load_config
from gdwm.datasets import build_hint
from gdwm.plan import RunError, ensure_data

PLATFORM = Path(__file__).resolve().parents[2] / "platform" / "gdwm"

NAMES = (
    # datasets and the benchmarks their layouts are named after
    "synthetic_mini",
    "gaussiandwm",
    "nuscenes",
    "nuinteract",
    "nuinstruct",
    "omnidrive",
    # stages of the GaussianDWM pipelines
    "evaluate_qa",
    "evaluate_gen",
    "diffusion_vae",
    # modules: the pipelines package, the perf benchmarks
    "pipelines.",
    "benchmarks.bench_",
    "benchmarks/bench_",
)


def mentions(text: str, names: tuple[str, ...] = NAMES) -> list[tuple[int, str]]:
    """(line number, line) of every line of ``text`` naming one of ``names``, case-insensitive."""
    pattern = re.compile("|".join(map(re.escape, names)), re.IGNORECASE)
    return [(n, line.strip()) for n, line in enumerate(text.splitlines(), 1) if pattern.search(line)]


def platform_files() -> list[Path]:
    return sorted(p for p in PLATFORM.rglob("*") if p.is_file() and "__pycache__" not in p.parts)


def test_no_platform_file_names_a_pipeline():
    files = platform_files()
    assert len(files) > 30 and PLATFORM / "cli.py" in files  # the walk sees the package
    found = [
        f"{rel}:{n}: {line}"
        for p in files
        for rel in [p.relative_to(PLATFORM).as_posix()]
        for n, line in mentions(p.read_text(errors="replace"))
    ]
    assert found == []


def test_the_check_finds_names_in_code_strings_and_comments_whatever_their_case():
    text = (
        "from pipelines.data import x\n"
        'layout = "NuInteract"  # default\n'
        "ok = 1\n"
        "# built by gdwm data convert-nuScenes\n"
        '"""Run ``benchmarks/bench_select.py``."""\n'
    )
    assert mentions(text) == [
        (1, "from pipelines.data import x"),
        (2, 'layout = "NuInteract"  # default'),
        (4, "# built by gdwm data convert-nuScenes"),
        (5, '"""Run ``benchmarks/bench_select.py``."""'),
    ]


@pytest.mark.parametrize(
    ("option", "hint"),
    [
        ("synthetic_mini", "gdwm data synth data=synthetic_mini"),
        ("nuscenes", "gdwm data convert-nuscenes source=DIR data=nuscenes"),
        ("gaussiandwm_release", "gdwm data import-gaussiandwm source=DIR data=gaussiandwm_release"),
    ],
)
def test_how_to_build_a_dataset_comes_from_its_config(option, hint, tmp_path):
    cfg = load_config([f"workdir={tmp_path}", f"data={option}"])
    assert build_hint(cfg.data) == hint


def test_a_missing_dataset_names_the_command_its_config_registers(tmp_path):
    cfg = load_config([f"workdir={tmp_path}", "data=nuscenes"])
    with pytest.raises(RunError) as e:
        ensure_data(cfg)
    assert str(e.value) == (
        f"dataset 'nuscenes' not found at {tmp_path}/data/nuscenes: build it first "
        "(gdwm data convert-nuscenes source=DIR data=nuscenes)"
    )
    # a dataset whose config names no build command still gets a usable hint
    assert build_hint(OmegaConf.create({"name": "toy"})) == "gdwm data <its build command> source=DIR data=toy"
