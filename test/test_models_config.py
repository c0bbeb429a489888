"""Model configs: presets, validation, parameter counts of the paper sizes."""

from __future__ import annotations

import pytest

from mapf_fleet.models import DCCNetwork, DHCNetwork, ModelConfig


def count(net):
    return sum(p.numel() for p in net.parameters())


def test_paper_parameter_counts_match_the_reference():
    # DESIGN.md section 4: DHC about 2.05 M, DCC about 1.98 M parameters.
    assert count(DHCNetwork(ModelConfig.preset("dhc", "paper"))) == pytest.approx(2.05e6, rel=0.01)
    assert count(DCCNetwork(ModelConfig.preset("dcc", "paper"))) == pytest.approx(1.98e6, rel=0.01)


def test_small_presets_are_much_smaller():
    assert count(DHCNetwork(ModelConfig.preset("dhc", "small"))) < 0.3e6
    assert count(DCCNetwork(ModelConfig.preset("dcc", "small"))) < 0.2e6


def test_round_trip_through_a_dict():
    config = ModelConfig.preset("dcc", "small", attend_self=False)
    assert ModelConfig.from_dict(config.to_dict()) == config


@pytest.mark.parametrize("field, value, message", [
    ("algo", "ppo", "algo"),
    ("conv_channels", (64, 128), "conv_channels"),
    ("hidden_dim", 0, "hidden_dim"),
    ("num_heads", 2.5, "num_heads"),
    ("obs_radius", 3, "obs_radius"),
    ("attend_self", 1, "attend_self"),
])
def test_bad_values_name_the_field(field, value, message):
    with pytest.raises(ValueError, match=message):
        ModelConfig(**{**ModelConfig.preset("dcc", "paper").to_dict(), field: value})


def test_unknown_preset_and_fields_are_rejected():
    with pytest.raises(ValueError, match="preset"):
        ModelConfig.preset("dhc", "huge")
    with pytest.raises(ValueError, match="unknown field"):
        ModelConfig.from_dict({"algo": "dhc", "width": 3})
    with pytest.raises(ValueError, match="config.algo"):
        DHCNetwork(ModelConfig.preset("dcc", "small"))
