"""Two `gdwm run` drivers on one workdir at once (fresh and existing store, identical and different configs):
both exit 0, every stage key executes once, one MLflow stage run per key.

Each driver is the real CLI with its own local Ray (token auth on).
"""

from __future__ import annotations

import shutil
import subprocess
from collections import Counter
from pathlib import Path

import pytest

from tests.gdwm.test_run import Toy

pytestmark = pytest.mark.heavy(2)


def _together(toy: Toy, *configs: tuple[str, ...]) -> list[subprocess.CompletedProcess]:
    procs = [
        subprocess.Popen(toy.args(*c), env=toy.env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for c in configs
    ]
    out = []
    for p in procs:
        stdout, stderr = p.communicate(timeout=600)
        out.append(subprocess.CompletedProcess(p.args, p.returncode, stdout, stderr))
    for r in out:
        assert r.returncode == 0, f"exit {r.returncode}\nSTDOUT\n{r.stdout[-3000:]}\nSTDERR\n{r.stderr[-5000:]}"
    return out


def _keys_executed(toy: Toy) -> Counter:
    lines = (toy.root / "executions.log").read_text().splitlines()
    return Counter(tuple(line.split()[:3]) for line in lines)  # (stage, scene, key[:12])


def _runs_per_key(toy: Toy) -> Counter:
    return Counter((r.data.tags["gdwm.stage"], r.data.tags["gdwm.cache_key"]) for r in toy.runs())


@pytest.fixture(scope="module")
def fresh_identical(tmp_path_factory) -> tuple[Toy, list[subprocess.CompletedProcess]]:
    toy = Toy(tmp_path_factory.mktemp("identical"))
    return toy, _together(toy, (), ())


def test_identical_drivers_on_a_fresh_store_compute_everything_once(fresh_identical):
    toy, results = fresh_identical
    ex = _keys_executed(toy)
    assert max(ex.values()) == 1
    assert Counter(s for s, _, _ in ex) == {"reconstruct": 3, "distill": 3, "tokenizer": 1, "lora": 1,
                                            "evaluate_qa": 1, "diffusion": 1, "evaluate_gen": 1}  # fmt: skip
    assert max(_runs_per_key(toy).values()) == 1 and len(_runs_per_key(toy)) == 7
    parents = toy.runs("run")
    assert len(parents) == 1 and parents[0].info.status == "FINISHED"  # the second driver continued the same run
    assert {r.info.status for r in toy.runs()} == {"FINISHED"}
    # the second one waited for the first, then found every stage cached
    assert any("waiting for it to finish" in r.stdout for r in results)


def test_different_drivers_on_a_fresh_store_share_their_common_stages(tmp_path):
    toy = Toy(tmp_path)
    _together(toy, ("stage.toy_lora.rank=8",), ("stage.toy_lora.rank=16",))
    ex = _keys_executed(toy)
    assert max(ex.values()) == 1
    # reconstruct, distill and tokenizer are shared; lora and what follows it differ
    assert Counter(s for s, _, _ in ex) == {"reconstruct": 3, "distill": 3, "tokenizer": 1, "lora": 2,
                                            "evaluate_qa": 2, "diffusion": 2, "evaluate_gen": 2}  # fmt: skip
    assert max(_runs_per_key(toy).values()) == 1 and len(_runs_per_key(toy)) == 11
    assert len(toy.runs("run")) == 2
    assert {r.info.status for r in toy.runs() + toy.runs("run")} == {"FINISHED"}


@pytest.mark.parametrize("configs", [(("stage.toy_lora.rank=32",),) * 2,
                                     (("stage.toy_lora.rank=32",), ("stage.toy_lora.rank=64",))],
                         ids=["identical", "different"])  # fmt: skip
def test_drivers_on_an_existing_store(fresh_identical, tmp_path, configs):
    src, _ = fresh_identical
    shutil.copytree(src.root, tmp_path, dirs_exist_ok=True)
    (tmp_path / "executions.log").write_text("")
    toy = Toy(Path(tmp_path))
    before = _runs_per_key(toy)
    _together(toy, *configs)
    ex = _keys_executed(toy)
    assert max(ex.values()) == 1
    n = len(set(configs))
    assert Counter(s for s, _, _ in ex) == {"lora": n, "evaluate_qa": n, "diffusion": n, "evaluate_gen": n}
    after = _runs_per_key(toy)
    assert max(after.values()) == 1 and len(after) == len(before) + 4 * n
