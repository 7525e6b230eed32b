import pytest

from model_zoo import registry


def test_register_build_and_unknown_variant():
    @registry.register("test_component", "double")
    def double(x: int) -> int:
        return 2 * x

    assert registry.build("test_component", "double", 21) == 42
    assert ("test_component", "double") in registry.variants("test_component")
    with pytest.raises(registry.UnknownVariant) as e:
        registry.get("test_component", "triple")
    assert str(e.value) == "no variant 'triple' of component 'test_component' (registered: ['double'])"
    with pytest.raises(ValueError, match=r"variant test_component/double is registered twice"):
        registry.register("test_component", "double")(lambda x: x)


def test_the_shipped_variants_are_found_by_their_modules_not_a_list():
    """Every module of model_zoo that registers a variant is found from its source (no hand-kept list)."""
    assert registry.shipped_modules() == [
        "model_zoo.adapter",
        "model_zoo.alignment",
        "model_zoo.diffusion.rgbd_dual",
        "model_zoo.encoders.daisy",
        "model_zoo.encoders.langsplat_proxy",
        "model_zoo.encoders.qwen3_vl_vision",
        "model_zoo.feature_ae",
        "model_zoo.llm.qwen3_vl",
        "model_zoo.selectors",
    ]
    shipped = [v for v in registry.variants() if v[0] != "test_component"]
    assert sorted({c for c, _ in shipped}) == [
        "alignment",
        "diffusion",
        "encoder",
        "feature_tokenizer",
        "fine_adapter",
        "llm",
        "selector",
    ]
    assert len(shipped) == 17
