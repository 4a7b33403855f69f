"""The one registry behind backbones, losses, noise models and data sources."""

from __future__ import annotations

import pytest

from tofdenoise.registry import Registry


def _registry() -> Registry:
    reg: Registry = Registry("widget")

    @reg.register("box")
    class Box:
        def __init__(self, width: int = 1, *, depth: int = 2) -> None:
            self.width, self.depth = width, depth

    @reg.register("Bag")
    def bag(**options):
        return dict(options)

    return reg


def test_register_names_and_build():
    reg = _registry()
    assert reg.names() == ["box", "bag"]  # registration order, lower case
    box = reg.build("box", width=3, depth=4)
    assert (box.width, box.depth) == (3, 4)
    assert reg.build("BOX").width == 1  # names match without regard to case
    assert "Box" in reg and "crate" not in reg and None not in reg
    assert reg.accepted_kwargs("box") == (["width", "depth"], False)


def test_duplicate_name_is_an_error_but_reregistering_the_same_factory_is_not():
    reg = _registry()
    factory = reg.get("box")
    assert reg.register("box")(factory) is factory
    with pytest.raises(ValueError, match="widget name 'box' is already registered"):
        reg.register("BOX")(lambda: None)
    assert reg.get("box") is factory


def test_unknown_name_names_the_kind_and_lists_the_valid_names():
    reg = _registry()
    with pytest.raises(ValueError, match=r"^unknown widget 'crate'; valid names: bag, box$"):
        reg.build("crate")
    with pytest.raises(ValueError, match=r"widget name must be a non-empty string, got None"):
        reg.build(None)


def test_bad_keyword_is_named_and_the_accepted_ones_listed():
    reg = _registry()
    with pytest.raises(
        ValueError,
        match=r"^widget 'box' got unexpected keyword argument\(s\) 'hight', 'lenght'; "
        r"accepted: width, depth$",
    ):
        reg.build("box", lenght=1, hight=2, width=3)
    empty: Registry = Registry("gadget")
    empty.register("plain")(lambda: "built")
    with pytest.raises(ValueError, match=r"gadget 'plain' got unexpected keyword argument\(s\) 'x'; accepted: none"):
        empty.build("plain", x=1)
    assert empty.build("plain") == "built"


def test_var_keyword_factory_accepts_any_keyword():
    reg = _registry()
    assert reg.build("bag", colour="red", size=3) == {"colour": "red", "size": 3}
    assert reg.accepted_kwargs("bag") == ([], True)


@pytest.mark.parametrize(
    "module, attr, kind",
    [
        ("tofdenoise.models.registry", "BACKBONES", "backbone"),
        ("tofdenoise.training.losses", "LOSSES", "loss"),
        ("tofdenoise.physics.noise_models", "NOISE_MODELS", "noise model"),
        ("tofdenoise.data_modules.sources", "DATA_SOURCES", "data source"),
    ],
)
def test_the_four_kinds_use_it(module, attr, kind):
    import importlib

    import tofdenoise.models  # noqa: F401  (registers the backbones)

    reg = getattr(importlib.import_module(module), attr)
    assert isinstance(reg, Registry) and reg.kind == kind and reg.names()
    with pytest.raises(ValueError, match=rf"^unknown {kind} 'nope'; valid names: "):
        reg.build("nope")
