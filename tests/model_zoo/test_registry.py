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
