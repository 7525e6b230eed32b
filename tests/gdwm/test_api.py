"""``gdwm.api`` is the one module of gdwm that pipelines import: a walk over every import in ``pipelines/`` and
``model_zoo/`` (lazy ones inside functions included), the facade's table against what checkers see, and the code
fingerprint following a name through the facade to its defining module only."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

import gdwm.api
from gdwm.fingerprint import closure, first_party

REPO = Path(__file__).resolve().parents[2]


def gdwm_imports(root: Path) -> list[tuple[str, int, str]]:
    """(file under ``root``, line, module) of every import of a ``gdwm`` module."""
    out = []
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            rel = path.relative_to(root).as_posix()
            out += [(rel, node.lineno, n) for n in names if n == "gdwm" or n.startswith("gdwm.")]
    return sorted(out)


def test_pipelines_import_gdwm_api_only_and_the_data_layer_and_zoo_nothing_of_gdwm():
    found = gdwm_imports(REPO / "pipelines")
    assert len(found) > 20  # the walk sees the stages
    assert [f"{f}:{n}: {m}" for f, n, m in found if m != "gdwm.api"] == []
    data = [f"{f}:{n}: {m}" for f, n, m in found if f.startswith("data/")]
    assert data == [] and gdwm_imports(REPO / "model_zoo") == []


def test_the_walk_names_an_import_past_the_api(tmp_path):
    (tmp_path / "stage.py").write_text("def f():\n    from gdwm.training import TrainSession\nimport gdwm.api\n")
    assert gdwm_imports(tmp_path) == [("stage.py", 2, "gdwm.training"), ("stage.py", 3, "gdwm.api")]


def test_the_facades_table_is_what_checkers_see_and_each_name_is_its_modules():
    tree = ast.parse((REPO / "platform" / "gdwm" / "api.py").read_text())
    guarded = next(n for n in tree.body if isinstance(n, ast.If) and ast.unparse(n.test) == "TYPE_CHECKING")
    seen = {a.name: imp.module for imp in guarded.body if isinstance(imp, ast.ImportFrom) for a in imp.names}
    assert seen == gdwm.api.EXPORTS
    for name, module in gdwm.api.EXPORTS.items():
        assert getattr(gdwm.api, name) is getattr(importlib.import_module(module), name), name
    assert sorted(gdwm.api.__all__) == sorted(gdwm.api.EXPORTS)
    with pytest.raises(AttributeError, match=r"module 'gdwm.api' has no attribute 'run_stage' \(the API: Command, "):
        gdwm.api.run_stage  # noqa: B018


def test_a_stages_fingerprint_follows_api_names_to_their_modules_only():
    seen, _ = closure(["pipelines.stages.lora"])
    files = {info.path for info in seen.values()}
    # lora's training loop imports TrainSession and warmup_cosine_lr from gdwm.api: gdwm/training.py counts
    assert {"pipelines/understanding/train.py", "gdwm/training.py", "gdwm/stage.py"} <= files
    # the facade and what it hands on that lora does not use do not
    assert not {"gdwm/api.py", "gdwm/runner.py", "gdwm/cli.py", "gdwm/compare/rounding.py"} & files


def test_first_party_code_is_every_package_of_the_distributions_plugged_into_gdwm():
    # read from the installed metadata (gdwm's own distribution and each one registering gdwm.* entry points), so a
    # wheel in site-packages is hashed as an editable checkout is; the platform names none of them itself
    assert {"gdwm", "pipelines", "model_zoo"} <= first_party()
    assert not {"torch", "ray", "mlflow", "numpy"} & first_party()
