"""Every row of every shipped sweep builds the model its label names (issue 17).

Each row is composed exactly as ``gdwm sweep`` composes it (``targets``, the sweep's overrides, the row's, the seed),
then its world tokens are built on one fixture scene from the components that config names: the configured encoder
(``load_encoder``, the distill stage's own) describes the scene, a code of the configured width is decoded, the
configured selector picks K_c candidates, the attribute projection and the configured fine adapter turn them into
K_f tokens, as ``WorldModel.world_tokens`` does (same seeds in every row, so only the config tells rows apart).
"""

from __future__ import annotations

import itertools
from functools import cache

import numpy as np
import pytest
import torch
from omegaconf import DictConfig, OmegaConf

from gdwm.cache import cache_key
from gdwm.config import ConfigError, SweepConfig, load_config
from gdwm.dag import load_pipeline
from gdwm.executor import stage_config
from model_zoo import registry
from model_zoo.adapter import AttributeProjection
from model_zoo.feature_ae import FeatureAEConfig, FeatureAutoencoder
from model_zoo.selectors import SelectorInputs, quality_score
from pipelines.stages.distill import load_encoder
from pipelines.understanding.config import LoraMode
from pipelines.understanding.model import Components

SWEEPS = ("conference_ablation", "journal_ablation")
# Factors that change what reaches the LLM as world tokens (the others change training only: LoRA, the KL loss).
TOKEN_FACTORS = {
    "conference_ablation": ("Gaussian", "Sampling"),
    "journal_ablation": ("Foundation-Feature Distillation", "Coarse Selection", "Fine Adapter"),
}
N, HIDDEN, TEXT_LEN = 500, 32, 6


@cache
def sweep(name: str) -> SweepConfig:
    return OmegaConf.to_object(load_config([f"sweep={name}"]).sweep)


@cache
def row_config(name: str, label: str) -> DictConfig:
    """The trial config of one row, composed as ``gdwm.sweep.plan_sweep`` composes it."""
    s = sweep(name)
    row = next(r for r in s.rows if r.label == label)
    return load_config([f"targets=[{','.join(s.targets)}]", *s.overrides, *row.overrides, "seed=0"])


def stage_keys(cfg: DictConfig) -> dict[str, str]:
    """Every stage's cache key on the same data and code: equal keys = one trained model."""
    pipe = load_pipeline(cfg, list(cfg.targets))
    keys: dict[str, str] = {}
    for name in pipe.ancestors(list(cfg.targets)):
        sd = pipe.stages[name]
        keys[name] = cache_key(sd.name, sd.version, stage_config(sd, cfg), {u: keys[u] for u in sd.upstream}, "data")
    return keys


def test_the_conference_tables_last_row_is_the_journal_tables_first_row():
    """Same numbers in both tables of the paper: one model, trained once by a team running both."""
    conference = row_config("conference_ablation", "Top-K + Uniform + Similarity")
    journal = row_config("journal_ablation", "Voxel Top-K + Similarity")
    assert OmegaConf.to_container(conference.model) == OmegaConf.to_container(journal.model)
    assert OmegaConf.to_container(conference, resolve=True) == OmegaConf.to_container(journal, resolve=True)
    assert stage_keys(conference) == stage_keys(journal)
    assert conference.model.selector.name == "topk_uniform" and conference.model.fine_adapter.name == "similarity"


@pytest.mark.parametrize("name", SWEEPS)
def test_every_row_of_a_shipped_sweep_starts_from_one_llm_built_once(name: str):
    """The tiny LLM (the stand-in for the released checkpoint) is a stage of its own keyed by model.llm and the data:
    one build per sweep and seed, shared by every row; the rows' tokenizers still differ."""
    keys = {r.label: stage_keys(row_config(name, r.label)) for r in sweep(name).rows}
    assert len({k["llm"] for k in keys.values() if "llm" in k}) == 1
    assert sum("llm" in k for k in keys.values()) >= len(keys) - 1  # a zero-shot row may not need a tokenizer
    tokenizers = [k["tokenizer"] for k in keys.values() if "tokenizer" in k]
    assert len(set(tokenizers)) > 1
    s = sweep(name)
    seed1 = load_config([f"targets=[{','.join(s.targets)}]", *s.overrides, *s.rows[-1].overrides, "seed=1"])
    assert stage_keys(seed1)["llm"] not in {k.get("llm") for k in keys.values()}  # model.llm.seed follows the seed


@pytest.mark.parametrize("name", SWEEPS)
def test_no_two_rows_of_a_shipped_sweep_resolve_to_the_same_stage_keys(name: str):
    keys = {r.label: stage_keys(row_config(name, r.label)) for r in sweep(name).rows}
    for a, b in itertools.combinations(keys, 2):
        assert keys[a]["evaluate_qa"] != keys[b]["evaluate_qa"], (a, b)


def test_identity_rows_hand_k_f_candidates_and_a_mismatch_is_a_config_error():
    for label in ("Random", "Top-K + Uniform"):
        cfg = row_config("conference_ablation", label)
        assert cfg.model.fine_adapter.name == "identity"
        assert cfg.model.selector.k_c == cfg.model.fine_adapter.k_f == 16
    with pytest.raises(ConfigError) as e:
        load_config(["model/selector=topk_uniform", "model/fine_adapter=identity"])
    assert str(e.value).startswith(
        "invalid value for 'model.fine_adapter.name': ValueError raised while resolving interpolation: "
        "model/fine_adapter=identity passes the coarse candidates through as the world tokens, so "
        "model.selector.k_c (256) must equal model.fine_adapter.k_f (16); set model.selector.k_c=16 or choose "
        "another fine adapter"
    )


def test_distillation_off_rows_distil_the_langsplat_stand_in_and_on_rows_the_foundation_encoder():
    """The ✗ arm is a distinct encoder (its name is the trial's MLflow param stage.distill.encoder), not ✓'s."""
    for name in SWEEPS:
        for r in sweep(name).rows:
            d = row_config(name, r.label).stage.distill
            off = r.factors.get("Foundation-Feature Distillation", "✗") == "✗"  # the conference model has none
            assert (d.encoder, d.feature_tokenizer) == (
                ("langsplat_proxy", "langsplat3") if off else ("daisy", "foundation")
            ), (name, r.label)


# ---- world tokens on a fixture scene -----------------------------------------------------------------------------
@cache
def fixture_scene() -> dict[str, torch.Tensor]:
    """A 60 m x 30 m street of N Gaussians and the image their features are read from (blocks of colour and texture,
    so encoders see edges and regions)."""
    rng = np.random.default_rng(0)
    xyz = np.stack([rng.uniform(-20, 40, N), rng.uniform(-15, 15, N), rng.uniform(0, 3, N)], 1)
    img = np.zeros((36, 64, 3), np.uint8)
    for _ in range(12):
        y, x = rng.integers(0, 30), rng.integers(0, 56)
        img[y : y + rng.integers(4, 12), x : x + rng.integers(6, 20)] = rng.integers(0, 256, 3)
    img = np.clip(img + rng.normal(0, 6, img.shape), 0, 255).astype(np.uint8)
    u = np.clip(((xyz[:, 0] + 20) / 60 * 63).round(), 0, 63).astype(int)
    v = np.clip(((xyz[:, 1] + 15) / 30 * 35).round(), 0, 35).astype(int)
    return {
        "xyz": torch.tensor(xyz, dtype=torch.float32),
        "scale": torch.tensor(rng.uniform(0.05, 0.8, (N, 3)), dtype=torch.float32),
        "rotation": torch.tensor(np.tile([1.0, 0, 0, 0], (N, 1)), dtype=torch.float32),
        "opacity": torch.tensor(rng.uniform(0.05, 1.0, N), dtype=torch.float32),
        "image": torch.from_numpy(img),
        "uv": torch.tensor(np.stack([v, u], 1)),
        "text": torch.tensor(rng.normal(size=(1, TEXT_LEN, HIDDEN)), dtype=torch.float32),
        "route": torch.stack([torch.arange(0, 31, dtype=torch.float32), torch.zeros(31)], 1),
    }


@cache
def world_tokens(name: str, label: str) -> tuple[torch.Tensor, frozenset[int]] | None:
    """(Z_G [1, K_f, H], the Gaussians they come from) of one row; None where the LLM gets no Gaussian tokens."""
    cfg = row_config(name, label)
    comp = Components.from_model_cfg(OmegaConf.to_container(cfg.model, resolve=True))
    if not comp.world.gaussian_tokens or cfg.stage.lora.mode == LoraMode.zero_shot:
        return None
    g = fixture_scene()
    dist = OmegaConf.to_container(cfg.stage.distill, resolve=True)
    encoder = load_encoder({"stage.distill": dist})
    feat_HWC = encoder.encode(g["image"].numpy())
    d_z = 3 if dist["feature_tokenizer"] == "langsplat3" else dist["d_z"]
    torch.manual_seed(0)
    ae = FeatureAutoencoder(FeatureAEConfig(d_f=encoder.d_f, d_z=d_z, hidden=16))
    with torch.no_grad():
        code_NZ = ae.encode(feat_HWC[g["uv"][:, 0], g["uv"][:, 1]])  # what distillation stores per Gaussian
        torch.manual_seed(0)
        projection = AttributeProjection(comp.projection, HIDDEN, encoder.d_f)
        fine = registry.build("fine_adapter", comp.fine_adapter.name, comp.fine_adapter, HIDDEN)
        selector = registry.build("selector", comp.selector.name, comp.selector)
        inputs = SelectorInputs(g["xyz"], g["scale"], g["rotation"], g["opacity"], trajectory=g["route"])
        text_mask = torch.ones(1, TEXT_LEN, dtype=torch.bool)
        e_H = g["text"][0].mean(0)
        if selector.needs_similarity:
            tok_NH = projection(
                *(g[k][None] for k in ("xyz", "scale", "rotation", "opacity")), ae.decode(code_NZ)[None]
            )
            inputs.similarity = torch.nn.functional.cosine_similarity(tok_NH[0], e_H[None], dim=-1)
        sel = selector(inputs, generator=torch.Generator().manual_seed(comp.selector.seed))
        idx = sel.index
        g_BKH = projection(*(g[k][idx][None] for k in ("xyz", "scale", "rotation", "opacity")),
                           (ae.decode(code_NZ[idx]) * sel.mask[:, None])[None])  # fmt: skip
        z_BFH, z_mask = fine(g_BKH, sel.mask[None], g["text"], text_mask)
    # The Gaussians a token is made of: itself (identity, similarity), every valid candidate (cross-attention).
    if comp.fine_adapter.name == "query_xattn":
        source = idx[sel.mask]
    else:
        rows = [int(torch.nonzero((g_BKH[0] == z).all(-1))[0]) for z, m in zip(z_BFH[0], z_mask[0], strict=True) if m]
        source = idx[rows]
    return z_BFH, frozenset(source.tolist())


def _same(a, b) -> bool:
    if a is None or b is None:
        return a is b
    return torch.equal(a[0], b[0]) and a[1] == b[1]


@pytest.mark.parametrize("name", SWEEPS)
def test_rows_meant_to_differ_hand_the_llm_different_tokens(name: str):
    rows = sweep(name).rows
    for a, b in itertools.combinations(rows, 2):
        ta, tb = world_tokens(name, a.label), world_tokens(name, b.label)
        meant_alike = all(a.factors[f] == b.factors[f] for f in TOKEN_FACTORS[name])
        assert _same(ta, tb) == meant_alike, (a.label, b.label)
        if not meant_alike and ta is not None and tb is not None:
            assert not torch.allclose(ta[0], tb[0]), (a.label, b.label)


def test_top_k_plus_uniform_hands_the_llm_its_uniform_branch():
    """Before: K_c = 256 candidates sorted by Q_i, the first 16 kept, so the uniform branch never reached the LLM and
    the + Similarity row had the same 16 tokens."""
    cfg = row_config("conference_ablation", "Top-K + Uniform").model.selector
    g = fixture_scene()
    _, source = world_tokens("conference_ablation", "Top-K + Uniform")
    k_f = row_config("conference_ablation", "Top-K + Uniform").model.fine_adapter.k_f
    assert len(source) == k_f
    order = torch.argsort(quality_score(g["scale"], g["rotation"], g["opacity"]), descending=True, stable=True).tolist()
    k_uniform = round(k_f * cfg.uniform_fraction)
    ranked = set(order[: k_f - k_uniform])
    assert ranked <= source and len(source - ranked) == k_uniform  # the top by Q_i, and as many drawn uniformly
    assert source != set(order[:k_f])  # not simply the top K_f by Q_i
    similarity = world_tokens("conference_ablation", "Top-K + Uniform + Similarity")[1]
    random = world_tokens("conference_ablation", "Random")[1]
    assert len({source, similarity, random}) == 3


def test_the_one_model_of_both_tables_gives_the_same_tokens():
    conference = world_tokens("conference_ablation", "Top-K + Uniform + Similarity")
    journal = world_tokens("journal_ablation", "Voxel Top-K + Similarity")
    assert _same(conference, journal)


def test_identity_with_another_k_c_exits_2_naming_both_keys(tmp_path):
    import subprocess
    import sys

    r = subprocess.run(
        [sys.executable, "-m", "gdwm", "run", "model/fine_adapter=identity", f"workdir={tmp_path}", "--dry-run"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 2
    assert "model.selector.k_c (256) must equal model.fine_adapter.k_f (16)" in r.stderr + r.stdout
