"""Protocol file, scenario selection, instance sources and the cache."""


import numpy as np
import pytest

from mapf_fleet.evaluation.protocol import (
    DEFAULT_CONFIG,
    DEFAULT_TESTSETS,
    ProtocolConfig,
    ProtocolError,
    Scenario,
    protocol_scenarios,
    scenario_instances,
)


def test_paper_protocol_has_the_eleven_scenarios():
    config = ProtocolConfig.from_yaml(DEFAULT_CONFIG)
    scenarios = protocol_scenarios(config)
    assert [(s.size, s.num_agents, s.max_steps) for s in scenarios] == [
        (40, 4, 256), (40, 8, 256), (40, 16, 256), (40, 32, 256), (40, 64, 256),
        (80, 4, 386), (80, 8, 386), (80, 16, 386), (80, 32, 386), (80, 64, 386), (80, 128, 386),
    ]
    assert config.instances == 200 and config.density == 0.3
    assert [s.key for s in protocol_scenarios(config, [80], [4, 128])] == ["80x80/4", "80x80/128"]
    with pytest.raises(ProtocolError, match="--sizes"):
        protocol_scenarios(config, [60])
    with pytest.raises(ProtocolError, match="no scenario"):
        protocol_scenarios(config, [40], [128])


@pytest.mark.parametrize("text, message", [
    ("maps: []\n", "at least one"),
    ("maps: [{size: 40, agents: [4], max_steps: 0}]\n", "max_steps"),
    ("maps: [{size: 40, agents: [4], max_steps: 9}]\ndensity: 1.5\n", "density"),
    ("maps: [{size: 40, agents: [4], max_steps: 9}]\ninstance: 3\n", "unknown field"),
    ("maps: [{size: 40, max_steps: 9}]\n", "malformed"),
])
def test_bad_protocol_files_name_the_problem(tmp_path, text, message):
    path = tmp_path / "p.yaml"
    path.write_text(text)
    with pytest.raises(ProtocolError, match=message) as info:
        ProtocolConfig.from_yaml(path)
    assert str(path) in str(info.value)


def test_generated_instances_are_cached_and_prefix_stable(tmp_path):
    scenario = Scenario("12x12", 3, 50, size=12)
    five = scenario_instances(scenario, 5, seed=7, cache_dir=tmp_path)
    assert len(list(tmp_path.glob("12x12_3agents_d0.3_seed7_*.npz"))) == 1
    two = scenario_instances(scenario, 2, seed=7, cache_dir=tmp_path)
    assert "cached" in two.source
    assert np.array_equal(two.maps, five.maps[:2]) and np.array_equal(two.starts, five.starts[:2])
    fresh = scenario_instances(scenario, 2, seed=7, cache_dir=None)
    assert np.array_equal(fresh.goals, two.goals)
    other = scenario_instances(scenario, 2, seed=8, cache_dir=None)
    assert not np.array_equal(other.maps, two.maps)


@pytest.mark.skipif(not (DEFAULT_TESTSETS / "40length_4agents.npz").is_file(), reason="published test sets absent")
def test_published_testset_is_used_for_40x40(tmp_path):
    config = ProtocolConfig.from_yaml(DEFAULT_CONFIG)
    scenario = protocol_scenarios(config, [40], [4])[0]
    got = scenario_instances(scenario, 3, cache_dir=tmp_path)
    with np.load(DEFAULT_TESTSETS / "40length_4agents.npz") as data:
        assert np.array_equal(got.maps, data["maps"][:3])
        assert np.array_equal(got.starts, data["starts"][:3])
    assert "published" in got.source
    assert not list(tmp_path.iterdir())  # nothing generated


def test_missing_testset_falls_back_to_generation(tmp_path):
    config = ProtocolConfig.from_yaml(DEFAULT_CONFIG)
    scenario = protocol_scenarios(config, [40], [4])[0]
    got = scenario_instances(scenario, 2, testsets_dir=tmp_path / "none", cache_dir=tmp_path)
    assert got.source.startswith("generated") and got.maps.shape == (2, 40, 40)
    # the report says the published set is absent, generated or read back from the cache
    assert f"{tmp_path / 'none' / '40length_4agents.npz'} is absent" in got.source
    again = scenario_instances(scenario, 2, testsets_dir=tmp_path / "none", cache_dir=tmp_path)
    assert "cached" in again.source and "is absent" in again.source
    # an 80x80 scenario names no published set: nothing to say
    big = protocol_scenarios(config, [80], [4])[0]
    assert "absent" not in scenario_instances(big, 1, testsets_dir=tmp_path / "none", cache_dir=None).source


def test_evaluate_says_when_the_published_sets_are_absent(tmp_path, capsys):
    from mapf_fleet.evaluation.cli import main

    code = main(["--checkpoint", "heuristic", "--no-references", "--sizes", "40", "--agents", "4",
                 "--instances", "1", "--testsets", str(tmp_path / "none"), "--cache-dir",
                 str(tmp_path / "cache"), "--quiet"])
    assert code == 0
    err = capsys.readouterr().err
    assert "40x40/4: the published set" in err and "using generated instances" in err
