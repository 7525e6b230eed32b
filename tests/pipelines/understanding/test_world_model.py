"""The world model end to end on CPU: every row of both ablation tables trains 2 steps in each stage."""

from __future__ import annotations

import pytest
import torch

from model_zoo import registry
from model_zoo.adapter import FineAdapterConfig, ProjectionConfig
from model_zoo.alignment import AlignmentConfig
from model_zoo.llm.qwen3_vl import LLMConfig, WorldLLM
from model_zoo.selectors import SelectorConfig
from pipelines.data.reader import GSQADataset
from pipelines.understanding.config import LoraStageConfig, WorldConfig
from pipelines.understanding.data import FrameStore, load_samples, training_corpus
from pipelines.understanding.model import Components, build_world_model, load_world_model

K_F = 8

# (label, features d_z, world overrides, selector, fine adapter, alignment) — tab:qa-ablation-conference rows 2-5
# and tab:qa-ablation-journal rows 1-5 (the conference's zero-shot row trains nothing: see its own test).
ROWS = [
    ("conf/no_gaussian", 16, {"gaussian_tokens": False}, "random", "identity", "none"),
    ("conf/random", 16, {}, "random", "identity", "none"),
    ("conf/topk_uniform", 16, {}, "topk_uniform", "identity", "none"),
    ("conf/topk_uniform_similarity", 16, {}, "topk_uniform_similarity", "identity", "none"),
    ("journal/voxel_similarity", 3, {"train_decoder": False}, "voxel_topk", "similarity", "none"),
    ("journal/+kl", 3, {"train_decoder": False}, "voxel_topk", "similarity", "kl"),
    ("journal/+xattn", 3, {"train_decoder": False}, "voxel_topk", "query_xattn", "kl"),
    ("journal/+driving_aware", 3, {"train_decoder": False}, "driving_aware", "query_xattn", "kl"),
    ("journal/+distillation", 16, {}, "driving_aware", "query_xattn", "kl"),
]


@pytest.fixture(scope="module")
def tiny_llm_dir(synth_small, tmp_path_factory):
    samples, _ = load_samples(GSQADataset(synth_small), "train", {}, need_gaussians=False)
    llm = registry.build(
        "llm", "qwen3_vl", LLMConfig(tiny=True, hidden_size=32, intermediate_size=64), corpus=training_corpus(samples)
    )
    path = tmp_path_factory.mktemp("llm")
    llm.save(path)
    return path


def components(world: dict, selector: str, fine: str, align: str) -> Components:
    identity = fine == "identity"
    return Components(
        WorldConfig(**world),
        SelectorConfig(name=selector, k_c=K_F if identity else 32, voxel_size=4.0),
        ProjectionConfig(fourier_features=4),
        FineAdapterConfig(name=fine, k_f=K_F, heads=2),
        AlignmentConfig(name=align, warmup_steps=2),
        LLMConfig(tiny=True, hidden_size=32, intermediate_size=64),
    )


def two_steps(model, samples, store) -> list[float]:
    opt = torch.optim.AdamW(model.trainable_parameters(), lr=1e-2)
    losses = []
    for step in range(2):
        loss, parts = model(samples[2 * step : 2 * step + 2], store, step)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(parts["loss"])
    return losses


@pytest.mark.parametrize("row", ROWS, ids=[r[0] for r in ROWS])
def test_every_ablation_row_trains_two_steps_per_stage(row, synth_small, distilled16, distilled3, tiny_llm_dir):
    _label, d_z, world, selector, fine, align = row
    dirs = distilled16 if d_z == 16 else distilled3
    comp = components(world, selector, fine, align)
    model = build_world_model(comp, WorldLLM.from_pretrained(tiny_llm_dir), dirs, seed=0)
    ds = GSQADataset(synth_small)
    samples, _ = load_samples(ds, "train", dirs, need_gaussians=comp.world.gaussian_tokens)
    store = FrameStore(ds, dirs, "clear", 3)

    # Stage 1: LLM frozen.
    model.freeze_llm()
    assert all(not p.requires_grad for p in model.lm.parameters())
    before = {n: p.detach().clone() for n, p in model.named_parameters() if p.requires_grad}
    if comp.world.gaussian_tokens:
        losses = two_steps(model, samples, store)
        assert all(torch.isfinite(torch.tensor(losses)))
        changed = {n for n, p in model.named_parameters() if n in before and not torch.equal(before[n], p)}
        assert any(n.startswith("projection.") for n in changed)
        assert any(n.startswith("feature_head.") for n in changed) == comp.world.train_decoder
        assert not any(n.startswith("decoders.") for n in changed)  # per-scene D_F stay as distilled
    else:
        assert before == {}  # image-only: nothing to train in stage 1

    # Stage 2: LoRA; only LoRA and adapter parameters receive gradients.
    model.add_lora(LoraStageConfig(rank=4, alpha=8, dropout=0.0))
    model.freeze_llm()
    loss, _ = model(samples[:2], store, 5)
    loss.backward()
    with_grad = {n for n, p in model.named_parameters() if p.grad is not None and p.grad.abs().sum() > 0}
    assert with_grad and all("lora_" in n or not n.startswith("lm.") for n in with_grad)
    assert any("lora_" in n for n in with_grad)
    assert not any(n.startswith("decoders.") for n in with_grad)
    assert any(n.startswith("feature_head.") for n in with_grad) == (
        comp.world.train_decoder and comp.world.gaussian_tokens
    )
    model.zero_grad()
    assert all(torch.isfinite(torch.tensor(two_steps(model, samples[4:], store))))


def test_saved_world_model_answers_the_same_after_reload(synth_small, distilled16, tiny_llm_dir, tmp_path):
    comp = components({}, "driving_aware", "query_xattn", "kl")
    model = build_world_model(comp, WorldLLM.from_pretrained(tiny_llm_dir), distilled16, seed=0)
    model.add_lora(LoraStageConfig(rank=4, alpha=8, dropout=0.0))
    with torch.no_grad():
        for n, p in model.lm.named_parameters():
            if "lora_B" in n:
                p.normal_(0, 0.5)  # a LoRA that changes the outputs
    ds = GSQADataset(synth_small)
    samples, _ = load_samples(ds, "val" if ds.qa(split="val").num_rows else "train", distilled16, need_gaussians=True)
    store = FrameStore(ds, distilled16, "clear", 3)
    model.eval()
    model.save(tmp_path / "m", save_llm=True)
    again = load_world_model(tmp_path / "m")
    again.eval()
    assert sorted(p.name for p in (tmp_path / "m").iterdir()) == ["adapter.pt", "llm", "lora", "world.json"]
    assert again.comp == comp
    with torch.no_grad():
        a, _ = model(samples[:2], store, 0)
        b, _ = again(samples[:2], store, 0)
    assert float(a) == pytest.approx(float(b), rel=1e-5)
    assert model.answer(samples[:2], store, 6) == again.answer(samples[:2], store, 6)


def test_zero_shot_and_no_gaussian_models_answer_without_world_tokens(synth_small, distilled16, tiny_llm_dir):
    comp = components({"gaussian_tokens": False}, "random", "identity", "none")
    model = build_world_model(comp, WorldLLM.from_pretrained(tiny_llm_dir), distilled16, seed=0)
    assert len(model.decoders) == 0
    ds = GSQADataset(synth_small)
    samples, _ = load_samples(ds, "train", {}, need_gaussians=False)
    store = FrameStore(ds, {}, "clear", 3)
    enc = model.encode(samples[:3], store, with_answer=False, gaussian=False)
    assert int((enc["batch"]["input_ids"] == model.llm.gauss_token_id).sum()) == 0
    answers = model.answer(samples[:3], store, 5)
    assert len(answers) == 3 and all(isinstance(a, str) for a in answers)


def test_an_empty_frame_gives_padding_tokens_and_a_finite_loss(synth_small, distilled16, tiny_llm_dir, tmp_path):
    import shutil

    import numpy as np

    from pipelines.data.layout import gaussians_table, write_arrow

    ds = GSQADataset(synth_small)
    samples, _ = load_samples(ds, "train", distilled16, need_gaussians=True)
    s = samples[0]
    dirs = dict(distilled16)
    dirs[s.scene] = tmp_path / s.scene
    shutil.copytree(distilled16[s.scene], dirs[s.scene])
    empty = {k: np.zeros((0, w), np.float32) for k, w in (("xyz", 3), ("scale", 3), ("rotation", 4), ("color", 3))}
    empty |= {"opacity": np.zeros(0, np.float32), "feature": np.zeros((0, 16), np.float32)}
    write_arrow(gaussians_table(empty, where="empty"), dirs[s.scene] / "gaussians" / f"{s.frame:05d}.arrow")
    comp = components({}, "driving_aware", "query_xattn", "kl")
    model = build_world_model(comp, WorldLLM.from_pretrained(tiny_llm_dir), dirs, seed=0)
    store = FrameStore(ds, dirs, "clear", 3)
    enc = model.encode([s], store, with_answer=True)
    z, z_mask = model.world_tokens([s], store, enc)
    assert z.shape == (1, K_F, 32) and not z_mask.any() and torch.equal(z, torch.zeros_like(z))
    loss, parts = model([s], store, 0)
    assert torch.isfinite(loss) and parts["loss_kl"] == 0.0  # nothing to align: no valid world token


def test_condition_gives_the_prompt_hidden_states_that_depend_on_the_scene(synth_small, distilled16, tiny_llm_dir):
    comp = components({}, "driving_aware", "query_xattn", "kl")
    model = build_world_model(comp, WorldLLM.from_pretrained(tiny_llm_dir), distilled16, seed=0)
    model.eval()
    ds = GSQADataset(synth_small)
    samples, _ = load_samples(ds, "train", distilled16, need_gaussians=True)
    store = FrameStore(ds, distilled16, "clear", 3)
    a, b = samples[0], samples[-1]
    assert (a.scene, a.frame) != (b.scene, b.frame)
    h, mask = model.condition([a, b], store)
    enc = model.encode([a, b], store, with_answer=False)
    assert h.shape == (*enc["batch"]["input_ids"].shape, 32) and torch.equal(
        mask, enc["batch"]["attention_mask"].bool()
    )
    assert not torch.allclose(h[0, mask[0]][-1], h[1, mask[1]][-1])  # different frame: different Z_G and images


def test_a_held_out_scene_decodes_through_the_parameters_training_trained(synth_small, distilled16, tiny_llm_dir):
    comp = components({}, "driving_aware", "query_xattn", "kl")
    model = build_world_model(comp, WorldLLM.from_pretrained(tiny_llm_dir), distilled16, seed=0)
    model.freeze_llm()
    ds = GSQADataset(synth_small)
    train, _ = load_samples(ds, "train", distilled16, need_gaussians=True)
    val, _ = load_samples(ds, "val", distilled16, need_gaussians=True)
    train_scenes = {s.scene for s in train}
    held = val[0].scene
    assert held not in train_scenes and held in distilled16  # a scene training never sees
    store = FrameStore(ds, distilled16, "clear", 3)
    codes = store.gaussians(held, val[0].frame)["code"]
    chain = model.feature_decoder(held)
    init = {n: p.detach().clone() for n, p in chain.named_parameters()}
    with torch.no_grad():
        before = chain(codes)

    two_steps(model, train, store)  # batches of training scenes only

    def trainable(scene: str) -> list[int]:
        return [id(p) for p in model.feature_decoder(scene).parameters() if p.requires_grad]

    assert trainable(held) and all(trainable(held) == trainable(s) for s in train_scenes)
    moved = [n for n, p in model.feature_decoder(held).named_parameters() if not torch.equal(init[n], p)]
    assert moved and all(n.startswith("1.") for n in moved)  # the shared head trained; the scene's D_F did not
    with torch.no_grad():
        after = model.feature_decoder(held)(codes)
    assert (after - before).abs().max() > 1e-4  # the held-out scene's features moved with training


def test_frozen_features_decode_exactly_as_distilled(synth_small, distilled16, tiny_llm_dir):
    from pipelines.understanding.model import load_decoders

    comp = components({"train_decoder": False}, "voxel_topk", "similarity", "none")
    model = build_world_model(comp, WorldLLM.from_pretrained(tiny_llm_dir), distilled16, seed=0)
    scene = sorted(distilled16)[-1]
    codes = torch.randn(5, 16)
    assert not [p for p in model.feature_decoder(scene).parameters() if p.requires_grad]
    distilled = load_decoders({scene: distilled16[scene]})[scene][1]
    with torch.no_grad():
        assert torch.equal(model.feature_decoder(scene)(codes), distilled(codes))


def test_one_pass_of_the_vision_tower_serves_the_lm_loss_and_the_kl_targets(synth_small, distilled16, tiny_llm_dir):
    """With L_KL on, a training step runs the vision tower once: the loss and every gradient equal, bit for bit,
    those of the tower run twice (once inside the LLM's forward, once for the KL targets)."""
    comp = components({}, "driving_aware", "query_xattn", "kl")
    ds = GSQADataset(synth_small)
    samples, _ = load_samples(ds, "train", distilled16, need_gaussians=True)
    store = FrameStore(ds, distilled16, "clear", 3)

    def step(shared: bool) -> tuple[torch.Tensor, dict[str, torch.Tensor], int]:
        torch.manual_seed(3)  # the LoRA's init and dropout draw the same numbers in both
        model = build_world_model(comp, WorldLLM.from_pretrained(tiny_llm_dir), distilled16, seed=0)
        model.add_lora(LoraStageConfig(rank=4, alpha=8, dropout=0.1))
        model.freeze_llm()
        model.train()
        passes = []
        model.llm.model.model.visual.register_forward_hook(lambda *_: passes.append(1))
        if shared:
            loss, _ = model(samples[:2], store, 5)
        else:  # the two-pass composition: the LLM's forward computes the tower itself, then the KL targets again
            enc = model.encode(samples[:2], store, with_answer=True)
            z, z_mask = model.world_tokens(samples[:2], store, enc)
            loss = model.llm.loss(enc["batch"], z, enc["pixel_values"], enc["image_grid_thw"])
            img, img_mask = model.image_tokens(enc)
            loss = loss + model.align(z, z_mask, img.detach(), img_mask, 5)[0]
        loss.backward()
        grads = {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}
        return loss.detach(), grads, len(passes)

    loss1, grads1, passes1 = step(shared=True)
    loss2, grads2, passes2 = step(shared=False)
    assert (passes1, passes2) == (1, 2)
    assert torch.equal(loss1, loss2)
    assert sorted(grads1) == sorted(grads2) and any("lora_" in n for n in grads1)
    assert [n for n in grads1 if not torch.equal(grads1[n], grads2[n])] == []


def test_a_frame_only_selector_selects_once_per_frame_and_store(synth_small, distilled16, tiny_llm_dir):
    comp = components({}, "driving_aware", "query_xattn", "kl")
    model = build_world_model(comp, WorldLLM.from_pretrained(tiny_llm_dir), distilled16, seed=0)
    ds = GSQADataset(synth_small)
    samples, _ = load_samples(ds, "train", distilled16, need_gaussians=True)
    calls = []
    selector = model.selector
    model.selector = type("Counting", (), {
        "needs_trajectory": True, "needs_similarity": False,
        "__call__": lambda self, g, generator=None: calls.append(1) or selector(g, generator=generator),
    })()  # fmt: skip
    e = torch.zeros(4, model.llm.hidden_size)
    store = FrameStore(ds, distilled16, "clear", 3)
    with torch.no_grad():
        first = model.candidates(samples[:4], store, e)
        again = model.candidates(samples[:4], store, e)
        fresh = model.candidates(samples[:4], FrameStore(ds, distilled16, "clear", 3), e)
    frames = len({(s.scene, s.frame) for s in samples[:4]})
    assert len(calls) == 2 * frames  # once per frame in each store, not once per sample and step
    assert first.keys() == fresh.keys() and all(torch.equal(first[k], again[k]) for k in first)
    assert all(torch.equal(first[k], fresh[k]) for k in first)
