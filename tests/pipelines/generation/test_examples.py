"""The C_L batch of the diffusion stages: unpadded conditions zero-padded with a mask."""

from __future__ import annotations

import torch

from pipelines.generation.examples import pad_tokens


def test_pad_tokens_zero_pads_to_the_longest_and_masks_the_padding():
    a, b = torch.ones(2, 3), torch.full((4, 3), 2.0)
    tokens_BLD, mask_BL = pad_tokens([a, b])
    assert tokens_BLD.shape == (2, 4, 3)
    assert mask_BL.tolist() == [[True, True, False, False], [True, True, True, True]]
    assert torch.equal(tokens_BLD[0, :2], a) and torch.equal(tokens_BLD[1], b)
    assert float(tokens_BLD[0, 2:].abs().sum()) == 0.0


def test_pad_tokens_of_an_off_high_level_condition_is_none():
    assert pad_tokens([None, None]) == (None, None)
