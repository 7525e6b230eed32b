import logging
import re

import numpy as np
import pytest
import torch

from model_zoo import registry
from model_zoo.llm import GAUSS_PAD, IGNORE_INDEX, LLMConfig, WorldLLM, add_gauss_token, collate, encode_sample
from model_zoo.llm.qwen3_vl import EXPECTED_FILES, _tiny_model
from model_zoo.llm.text import IM_END, IM_START, QWEN_SPECIAL_TOKENS, VISION_END, train_tiny_tokenizer

K = 4
INSTRUCTION = "Based on <gauss>, please locate the {obj} in the front view."
OBJECTS = ["car", "truck", "pedestrian", "bus", "traffic cone", "barrier", "bicycle"]


def _corpus() -> list[str]:
    out = []
    for i in range(50):
        obj = OBJECTS[i % len(OBJECTS)]
        out.append(INSTRUCTION.format(obj=obj) + f" The {obj} is at ({i % 13}, {(3 * i) % 17}) m, size {i % 5} m.")
    return out


def _build(seed: int = 0, **kw) -> WorldLLM:
    return registry.build("llm", "qwen3_vl", LLMConfig(seed=seed, **kw), corpus=_corpus())


def _images(seed: int) -> list[list[np.ndarray]]:
    """Sample 0: two views (6 tokens each); sample 1: one view (4 tokens); 2 and 3 repeat with other pixels."""
    rng = np.random.default_rng(seed)
    shapes = [[(32, 48), (48, 32)], [(32, 32)], [(32, 48), (48, 32)], [(32, 32)]]
    return [[rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for h, w in views] for views in shapes]


ANSWERS = ["The car is at (3, 9) m.", "The bus is at (1, 4) m.", "The truck is at (7, 2) m.", "No bicycle."]


def _batch(llm: WorldLLM, n: int, *, answers: bool = True, padding_side: str = "right"):
    pv, grid, counts = llm.image_inputs(_images(0)[:n])
    enc = [
        llm.encode(
            sample_id=f"s{b}",
            instruction=INSTRUCTION.format(obj=OBJECTS[b]),
            answer=ANSWERS[b] if answers else None,
            image_tokens=counts[b],
            k_f=K,
            gaussian=True,
        )
        for b in range(n)
    ]
    return collate(enc, llm.pad_token_id, padding_side), pv, grid, enc


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    """Tiny kernels gain nothing from 2 threads and stall badly when other jobs share the cores."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def llm() -> WorldLLM:
    return _build()


# ---------------------------------------------------------------- prompt construction


def test_encode_puts_k_f_slots_between_last_image_and_instruction_and_masks_the_prefix(llm):
    tok = llm.tokenizer
    s = encode_sample(
        llm,
        sample_id="scene-1/f3",
        instruction=INSTRUCTION.format(obj="car"),
        answer="The car is at (3, 9) m.",
        image_tokens=[6, 4],
        k_f=K,
        gaussian=True,
        max_length=384,
    )
    ids = s.input_ids
    slots = [i for i, t in enumerate(ids) if t == llm.gauss_token_id]
    last_vision_end = max(i for i, t in enumerate(ids) if t == tok.convert_tokens_to_ids(VISION_END))
    assert s.n_gauss == K and slots == list(range(last_vision_end + 1, last_vision_end + 1 + K))
    assert s.text_positions[0] == slots[-1] + 1
    assert s.text_positions == list(range(s.text_positions[0], s.text_positions[-1] + 1))
    assert tok.decode([ids[p] for p in s.text_positions]) == (
        "Based on the Gaussian scene tokens, please locate the car in the front view."
    )
    assert ids.count(llm.image_token_id) == 10 and ids[0] == tok.convert_tokens_to_ids(IM_START)
    assert tok.decode(ids[s.text_positions[-1] + 1 : s.response_start]) == f"{IM_END}\n{IM_START}assistant\n"
    assert s.labels[: s.response_start] == [IGNORE_INDEX] * s.response_start
    assert s.labels[s.response_start :] == ids[s.response_start :]
    assert tok.decode(ids[s.response_start :]) == f"The car is at (3, 9) m.{IM_END}"


def test_encode_without_gaussian_tokens_has_no_slots_and_names_the_images(llm):
    s = llm.encode(sample_id="a", instruction=INSTRUCTION.format(obj="bus"), answer=None, image_tokens=[6], k_f=K,
                   gaussian=False)  # fmt: skip
    assert s.n_gauss == 0 and llm.gauss_token_id not in s.input_ids
    assert llm.tokenizer.decode([s.input_ids[p] for p in s.text_positions]).startswith("Based on the images, ")
    assert s.labels == [IGNORE_INDEX] * len(s.input_ids) and s.response_start == len(s.input_ids)


def test_encode_errors_name_the_sample(llm):
    kw = {"answer": "x", "image_tokens": [6], "k_f": K, "gaussian": True, "max_length": 384}
    msg = "scene-7/f2: instruction has no <gauss> placeholder but Gaussian tokens are on"
    with pytest.raises(ValueError, match=f"^{re.escape(msg)}$"):
        encode_sample(llm, sample_id="scene-7/f2", instruction="Where is the car?", **kw)
    kw["max_length"] = 20
    with pytest.raises(ValueError, match=r"^scene-7/f3: prompt is \d+ tokens .* longer than max_length 20$"):
        encode_sample(llm, sample_id="scene-7/f3", instruction=INSTRUCTION.format(obj="car"), **kw)


def test_encode_cuts_a_long_answer_with_a_warning(llm, caplog):
    kw = {"instruction": INSTRUCTION.format(obj="car"), "image_tokens": [6], "k_f": K, "gaussian": True}
    full = encode_sample(llm, sample_id="s9", answer=" ".join(ANSWERS * 3), max_length=384, **kw)
    limit = full.response_start + 5
    with caplog.at_level(logging.WARNING, logger="model_zoo.llm.text"):
        cut = encode_sample(llm, sample_id="s9", answer=" ".join(ANSWERS * 3), max_length=limit, **kw)
    assert len(cut.input_ids) == limit and cut.input_ids == full.input_ids[:limit]
    assert cut.labels[cut.response_start :] == full.input_ids[full.response_start : limit]
    assert [r.levelno for r in caplog.records] == [logging.WARNING] and caplog.records[0].getMessage().startswith(
        f"s9: answer cut from {len(full.input_ids) - full.response_start - 1} to 5 tokens"
    )


def test_collate_pads_right_for_training_and_left_for_generation(llm):
    batch, _, _, enc = _batch(llm, 2)
    lens = [len(e.input_ids) for e in enc]
    assert lens[0] > lens[1] and batch["input_ids"].shape == (2, lens[0])
    assert batch["attention_mask"].sum(1).tolist() == lens
    assert batch["input_ids"][1, lens[1] :].eq(llm.pad_token_id).all()
    assert batch["labels"][1, lens[1] :].eq(IGNORE_INDEX).all()
    assert batch["instruction_mask"][1].nonzero().flatten().tolist() == enc[1].text_positions
    left = collate(enc, llm.pad_token_id, "left")
    pad = lens[0] - lens[1]
    assert left["attention_mask"][1, :pad].sum() == 0 and left["input_ids"][1, pad:].tolist() == enc[1].input_ids
    assert left["instruction_mask"][1].nonzero().flatten().tolist() == [p + pad for p in enc[1].text_positions]


# ---------------------------------------------------------------- images, embeddings


def test_image_inputs_count_the_merged_tokens_the_tower_returns(llm):
    pv, grid, counts = llm.image_inputs(_images(0)[:2])
    # 32x48 px with 8 px patches merged 2x2 -> 2x3 tokens; 32x32 -> 2x2
    assert grid.tolist() == [[1, 4, 6], [1, 6, 4], [1, 4, 4]] and counts == [[6, 6], [4]]
    tokens = llm.image_tokens(pv, grid)
    assert [tuple(t.shape) for t in tokens] == [(6, 64), (6, 64), (4, 64)]
    assert llm.image_inputs([[], []]) == (None, None, [[], []])
    with pytest.raises(ValueError, match=r"sample 1 image 0 must be uint8 \[H, W, 3\], got float32 \(8, 8, 3\)"):
        llm.image_inputs([[], [np.zeros((8, 8, 3), np.float32)]])
    ids = torch.tensor([[1, 2, 3]])
    torch.testing.assert_close(llm.text_embeddings(ids)[0, 1], llm.model.get_input_embeddings().weight[2])


def test_image_inputs_equal_the_processors_own_batch_and_process_each_image_once(llm, monkeypatch):
    fresh = _build()
    images = _images(3)
    flat = [img for views in images for img in views]
    ref = fresh.image_processor(images=flat, input_data_format="channels_last", return_tensors="pt")
    calls = []
    processor = fresh.image_processor
    monkeypatch.setattr(fresh, "image_processor", lambda **kw: calls.append(len(kw["images"])) or processor(**kw))
    pv, grid, counts = fresh.image_inputs(images)
    assert torch.equal(pv, ref["pixel_values"]) and torch.equal(grid, ref["image_grid_thw"])
    assert calls == [1] * 6 and counts == [[6, 6], [4], [6, 6], [4]]
    again = fresh.image_inputs([images[2], images[0]])  # the same pixels in another batch: nothing processed
    assert calls == [1] * 6 and torch.equal(again[0], torch.cat([pv[64:112], pv[:48]]))
    other = images[0][0].copy()
    other[0, 0, 0] ^= 1  # one value of one pixel changed: a new image
    fresh.image_inputs([[other]])
    assert calls == [1] * 7


# ---------------------------------------------------------------- Gaussian token injection


def test_injection_equals_a_manual_inputs_embeds_forward_and_reaches_z(llm):
    batch, pv, grid, _ = _batch(llm, 2)
    z = torch.randn(2, K, llm.hidden_size, generator=torch.Generator().manual_seed(0), requires_grad=True)
    logits = llm.forward(batch, z, pv, grid).logits
    other = llm.forward(batch, z.detach() + 1.0, pv, grid).logits
    assert (logits - other).abs().max() > 1e-3

    ids, mask = batch["input_ids"], batch["attention_mask"]
    emb = llm.text_embeddings(ids).detach().clone()
    emb[ids == llm.gauss_token_id] = z.detach().reshape(-1, llm.hidden_size)
    mm = (ids == llm.image_token_id).int()
    pos, _ = llm.model.model.get_rope_index(ids, mm_token_type_ids=mm, image_grid_thw=grid, attention_mask=mask)
    with torch.no_grad():
        ref = llm.model(inputs_embeds=emb, attention_mask=mask, pixel_values=pv, image_grid_thw=grid, position_ids=pos)
    torch.testing.assert_close(logits.detach(), ref.logits, atol=1e-5, rtol=0)

    logits[batch["attention_mask"].bool()].square().mean().backward()
    assert z.grad is not None and (z.grad.abs().sum(-1) > 0).all()


def test_injection_rejects_a_slot_count_mismatch_and_missing_z(llm):
    batch, pv, grid, _ = _batch(llm, 2)
    with pytest.raises(ValueError, match=r"z_BFH is \[2, 3, H\] but the 2 rows hold \[4, 4\] <\|gauss_pad\|> slots"):
        llm.forward(batch, torch.zeros(2, 3, llm.hidden_size), pv, grid)
    with pytest.raises(ValueError, match=r"rows hold \[4, 4\] <\|gauss_pad\|> slots but no Gaussian tokens"):
        llm.forward(batch, None, pv, grid)
    with pytest.raises(ValueError, match=r"the batch holds 16 <\|image_pad\|> slots but the images give 0 tokens"):
        llm.forward(batch, torch.zeros(2, K, llm.hidden_size))
    off = llm.encode(sample_id="o", instruction="Where?", answer="Here.", image_tokens=[], k_f=K, gaussian=False)
    with pytest.raises(ValueError, match=r"Gaussian tokens were given but the batch has no <\|gauss_pad\|> slots"):
        llm.loss(collate([off], llm.pad_token_id), torch.zeros(1, K, llm.hidden_size))


# ---------------------------------------------------------------- training and generation


def test_loss_falls_by_half_in_30_adam_steps_through_images_and_z():
    llm = _build()
    batch, pv, grid, _ = _batch(llm, 4)
    z = torch.nn.Parameter(0.02 * torch.randn(4, K, llm.hidden_size, generator=torch.Generator().manual_seed(1)))
    opt = torch.optim.Adam([*llm.model.parameters(), z], lr=3e-3)
    llm.model.train()
    losses = []
    for _ in range(30):
        loss = llm.loss(batch, z, pv, grid)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert np.isfinite(losses).all() and losses[-1] < 0.5 * losses[0], losses
    assert llm.model.model.visual.patch_embed.proj.weight.grad.abs().sum() > 0


def test_batched_generation_equals_one_by_one(llm):
    batch, pv, grid, enc = _batch(llm, 2, answers=False, padding_side="left")
    z = torch.randn(2, K, llm.hidden_size, generator=torch.Generator().manual_seed(2))
    both = llm.generate(batch, z, pv, grid, max_new_tokens=6)
    assert len(both) == 2 and all(isinstance(s, str) and s for s in both)
    pv0, grid0, _ = llm.image_inputs(_images(0)[:1])
    alone = llm.generate(collate(enc[:1], llm.pad_token_id, "left"), z[:1], pv0, grid0, max_new_tokens=6)
    assert alone == both[:1]
    with pytest.raises(ValueError, match="left-padded"):
        llm.generate(collate(enc, llm.pad_token_id, "right"), z, pv, grid)


def test_overfit_then_greedy_decoding_reproduces_the_answer_that_z_selects():
    # two samples with the same images and instruction, told apart by their Gaussian tokens only
    llm = _build(seed=1)
    pv, grid, counts = llm.image_inputs(_images(0)[:1])
    pv, grid = torch.cat([pv, pv]), torch.cat([grid, grid])
    answers = ["The car is at (3, 9) m.", "No car."]

    def enc(answer):
        return llm.encode(sample_id="s", instruction=INSTRUCTION.format(obj="car"), answer=answer,
                          image_tokens=counts[0], k_f=K, gaussian=True)  # fmt: skip

    batch = collate([enc(a) for a in answers], llm.pad_token_id)
    z = torch.randn(2, K, llm.hidden_size, generator=torch.Generator().manual_seed(3))
    opt = torch.optim.Adam(llm.model.parameters(), lr=3e-3)
    llm.model.train()
    for _ in range(40):
        loss = llm.loss(batch, z, pv, grid)
        opt.zero_grad()
        loss.backward()
        opt.step()
    prompt = collate([enc(None)] * 2, llm.pad_token_id, "left")
    assert llm.generate(prompt, z, pv, grid, max_new_tokens=40) == answers
    assert llm.generate(prompt, z.flip(0), pv, grid, max_new_tokens=40) == answers[::-1]
    assert llm.model.training  # generate restores the mode it found


def test_samples_without_images_train_and_generate(llm):
    s = llm.encode(sample_id="t", instruction=INSTRUCTION.format(obj="car"), answer=ANSWERS[0], image_tokens=[], k_f=K,
                   gaussian=True)  # fmt: skip
    first = s.input_ids.index(llm.gauss_token_id)
    assert llm.tokenizer.decode(s.input_ids[:first]) == f"{IM_START}user\n"
    assert s.input_ids[first : first + K] == [llm.gauss_token_id] * K and s.text_positions[0] == first + K
    z = torch.randn(1, K, llm.hidden_size, generator=torch.Generator().manual_seed(4))
    loss = llm.loss(collate([s], llm.pad_token_id), z)
    assert torch.isfinite(loss) and loss.item() > 0
    p = llm.encode(sample_id="t", instruction="Where is the car?", answer=None, image_tokens=[], k_f=K, gaussian=False)
    q = llm.encode(sample_id="u", instruction="Where is the bus now?", answer=None, image_tokens=[], k_f=K,
                   gaussian=False)  # fmt: skip
    both = llm.generate(collate([p, q], llm.pad_token_id, "left"), None, max_new_tokens=5)
    assert len(both) == 2 and both[1:] == llm.generate(collate([q], llm.pad_token_id, "left"), max_new_tokens=5)


def test_lora_wrapped_model_keeps_injection_and_trains_only_adapters_and_z():
    from peft import LoraConfig, get_peft_model

    llm = _build()
    batch, pv, grid, _ = _batch(llm, 2)
    z = torch.randn(2, K, llm.hidden_size, generator=torch.Generator().manual_seed(6), requires_grad=True)
    with torch.no_grad():
        before = llm.forward(batch, z, pv, grid).logits
    llm.model = get_peft_model(llm.model, LoraConfig(r=4, target_modules=r".*language_model.*\.(q_proj|v_proj)"))
    loss = llm.loss(batch, z, pv, grid)
    loss.backward()
    trained = {n for n, p in llm.model.named_parameters() if p.grad is not None and p.grad.abs().sum() > 0}
    assert trained and all("lora_B" in n for n in trained) and z.grad.abs().sum() > 0  # B = 0 at init: A gets none
    with torch.no_grad():  # LoRA starts as the identity
        torch.testing.assert_close(llm.forward(batch, z, pv, grid).logits, before)
    prompt, pv, grid, _ = _batch(llm, 2, answers=False, padding_side="left")
    assert len(llm.generate(prompt, z.detach(), pv, grid, max_new_tokens=3)) == 2


# ---------------------------------------------------------------- construction, persistence


def test_tiny_build_is_deterministic_and_seeded(llm):
    again = _build()
    assert again.tokenizer.get_vocab() == llm.tokenizer.get_vocab()
    a, b = llm.model.state_dict(), again.model.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    other = _build(seed=5).model.state_dict()
    assert not torch.equal(a["lm_head.weight"], other["lm_head.weight"])
    assert llm.hidden_size == 64 and llm.model.config.vision_config.out_hidden_size == 64
    assert llm.tokenizer.convert_tokens_to_ids(GAUSS_PAD) == llm.gauss_token_id
    assert len(llm.tokenizer) <= 600 and llm.model.get_input_embeddings().num_embeddings == len(llm.tokenizer)
    assert ("llm", "qwen3_vl") in registry.variants("llm")
    with pytest.raises(ValueError, match="a text corpus is required"):
        registry.build("llm", "qwen3_vl", LLMConfig())


def test_save_and_from_pretrained_round_trip(llm, tmp_path):
    llm.save(tmp_path / "ckpt")
    back = WorldLLM.from_pretrained(tmp_path / "ckpt")
    assert back.tokenizer.get_vocab() == llm.tokenizer.get_vocab() and back.gauss_token_id == llm.gauss_token_id
    assert back.cfg.image_max_pixels == 16384 and back.cfg.path == str(tmp_path / "ckpt") and not back.cfg.tiny
    batch, pv, grid, _ = _batch(llm, 2)
    pv2, grid2, _ = back.image_inputs(_images(0)[:2])
    assert torch.equal(pv, pv2) and torch.equal(grid, grid2)
    z = torch.randn(2, K, llm.hidden_size, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        torch.testing.assert_close(back.forward(batch, z, pv, grid).logits, llm.forward(batch, z, pv, grid).logits)


def test_from_pretrained_names_the_missing_directory_and_files(tmp_path):
    missing = tmp_path / "qwen3-vl-4b"
    msg = f"llm/qwen3_vl: checkpoint directory {missing} does not exist; expected {EXPECTED_FILES}"
    with pytest.raises(FileNotFoundError, match=f"^{re.escape(msg)}$"):
        WorldLLM.from_pretrained(missing)
    missing.mkdir()
    (missing / "config.json").write_text("{}")
    with pytest.raises(FileNotFoundError, match=r"lacks model.safetensors .*, tokenizer.json \(or vocab.json"):
        WorldLLM.from_pretrained(missing)
    with pytest.raises(FileNotFoundError, match=r"LLMConfig.path is None"):
        registry.build("llm", "qwen3_vl", LLMConfig(tiny=False))


def test_add_gauss_token_grows_the_table_only_when_needed():
    # a released-style tokenizer: Qwen's special tokens only
    tok = train_tiny_tokenizer(_corpus(), 600, QWEN_SPECIAL_TOKENS)
    n = len(tok)
    assert GAUSS_PAD not in tok.get_vocab()
    model = _tiny_model(LLMConfig(), tok)
    assert add_gauss_token(model, tok) == n and len(tok) == n + 1
    assert model.get_input_embeddings().num_embeddings == n + 1 and model.lm_head.out_features == n + 1
    assert model.config.text_config.vocab_size == n + 1
    assert tok.decode(tok.encode(f"a{GAUSS_PAD}b", add_special_tokens=False), skip_special_tokens=True) == "ab"
    # a table padded past the tokenizer (as released Qwen checkpoints are) keeps its size
    tok = train_tiny_tokenizer(_corpus(), 600, QWEN_SPECIAL_TOKENS)
    model = _tiny_model(LLMConfig(), tok)
    model.resize_token_embeddings(n + 8)
    assert add_gauss_token(model, tok) == n and model.get_input_embeddings().num_embeddings == n + 8


def test_tiny_pretraining_learns_the_corpus_and_is_deterministic():
    from model_zoo.llm.qwen3_vl import pretrain_on_text

    a, b = _build(), _build()
    la = pretrain_on_text(a, _corpus(), steps=25, lr=3e-3, batch_size=8, seed=1)
    lb = pretrain_on_text(b, _corpus(), steps=25, lr=3e-3, batch_size=8, seed=1)
    assert la == lb  # same corpus, same seed: same weights downstream stages start from
    assert sum(la[-5:]) / 5 < 0.6 * sum(la[:5]) / 5
    with pytest.raises(ValueError, match="pre-training corpus has no text"):
        pretrain_on_text(a, ["", ""], steps=1, lr=1e-3, batch_size=2, seed=0)


def test_instruction_warm_up_teaches_each_question_its_answer_format():
    """model.llm.pretrain_on=instructions: text-only (instruction, answer) pairs with the loss on the answer, as an
    instruction-tuned checkpoint knows them. Three question kinds with three answer formats: after the warm-up the
    greedy answer to each kind has its format (the text warm-up, documents without the template, does not)."""
    from pipelines.evaluate.grounding import parse_box, parse_centre_size
    from pipelines.evaluate.planning import parse_decision

    kinds = [
        ("Based on <gauss>, please locate the {c} car in <CAM_FRONT>.", "<CAM_FRONT> <box>({x},40),({y},60)</box>"),
        ("Based on <gauss>, where is the {c} car in 3D?", "center: ({x}.00, 2.00, 0.50), size: (4.00, 1.80, 1.50)"),
        ("Based on <gauss>, how should the ego vehicle adjust its speed near the {c} car?", "Keep speed. Reason: {c}."),
    ]
    colours = ["red", "blue", "white", "black", "green", "orange"]
    pairs = [(q.format(c=c), a.format(c=c, x=10 + i, y=30 + i)) for i, c in enumerate(colours) for q, a in kinds]
    corpus = [t for p in pairs for t in p]
    parses = [parse_box, parse_centre_size, lambda t: parse_decision(t, ["keep speed", "stop"])]

    def formats(pretrain_on: str) -> list[bool]:
        cfg = LLMConfig(seed=0, pretrain_steps=150, pretrain_batch_size=16, pretrain_on=pretrain_on)
        llm = registry.build("llm", "qwen3_vl", cfg, corpus=corpus, instructions=pairs)
        prompts = [q.format(c="green") for q, _ in kinds]  # the formats are checked, not the numbers
        enc = [
            llm.encode(
                sample_id=f"q{i}",
                instruction=p.replace("<gauss>", "the scene"),
                answer=None,
                image_tokens=[],
                k_f=0,
                gaussian=False,
            )
            for i, p in enumerate(prompts)
        ]
        answers = llm.generate(collate(enc, llm.pad_token_id, "left"), max_new_tokens=40)
        return [parse(a) is not None for parse, a in zip(parses, answers, strict=True)]

    assert formats("instructions") == [True, True, True]
    assert formats("text") != [True, True, True]


def test_instruction_warm_up_needs_its_pairs_and_a_known_mode():
    with pytest.raises(
        ValueError, match=r"model.llm.pretrain_on: unknown 'chat' \(one of \['text', 'instructions'\]\)"
    ):
        _build(pretrain_steps=1, pretrain_on="chat")
    with pytest.raises(ValueError, match="pretrain_on=instructions needs the \\(instruction, answer\\) pairs"):
        _build(pretrain_steps=1, pretrain_on="instructions")
