"""Layout (README): ``platform/`` holds the gdwm package without being a package itself."""

import subprocess
import sys
import sysconfig
from pathlib import Path

import gdwm

REPO = Path(__file__).resolve().parents[2]


def test_platform_dir_is_not_a_package():
    assert (REPO / "platform" / "gdwm" / "__init__.py").is_file()
    assert not (REPO / "platform" / "__init__.py").exists()


def test_import_platform_is_the_standard_library():
    # A fresh interpreter started in the repo root, where a `platform` folder sits on sys.path[0].
    out = subprocess.run(
        [sys.executable, "-c", "import platform, gdwm; print(platform.__file__); print(platform.system())"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    stdlib = Path(sysconfig.get_paths()["stdlib"]).resolve()
    assert Path(out[0]).resolve() == stdlib / "platform.py"
    assert out[1] == "Linux"


def test_gdwm_imports_from_platform_dir():
    assert Path(gdwm.__file__).resolve() == REPO / "platform" / "gdwm" / "__init__.py"


def test_ruff_enforces_a005():
    text = (REPO / "pyproject.toml").read_text()
    assert 'extend-select = ["A005"]' in text
