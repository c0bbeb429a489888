"""Every config shipped under config/ is accepted by the command that documents it (issue 40,
item 5: `up --params-file config/fleet/fleet.yaml`, the file `up --help` points to, was refused
in both modes). One test per file, through the code that refuses a config when the command
reads it, without running the command's work:
- config/fleet/fleet.yaml: `up --params-file` (simulated and --real-robots: `launcher.prepare`,
  everything `up` checks before it starts a process);
- config/fleet/instance_small.yaml: `up --instance F --real-robots` (docs/fleet.md);
- config/training/dagger*.yaml (and experiments/dagger*): `mapf-fleet dagger --config`;
- every other config/training YAML: `mapf-fleet train --config`;
- config/evaluation/*.yaml: `mapf-fleet evaluate --config`."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

CONFIG = Path(__file__).resolve().parents[1] / "config"
TRAINING = sorted((CONFIG / "training").rglob("*.yaml"))
EVALUATION = sorted((CONFIG / "evaluation").rglob("*.yaml"))
FLEET = sorted((CONFIG / "fleet").rglob("*.yaml"))


def _id(path: Path) -> str:
    return str(path.relative_to(CONFIG))


def test_every_shipped_config_has_a_test_here():
    """A new folder or file kind under config/ needs its command in this file."""
    every = sorted(CONFIG.rglob("*"))
    files = [p for p in every if p.is_file()]
    assert set(files) == set(TRAINING + EVALUATION + FLEET), [
        _id(p) for p in set(files) - set(TRAINING + EVALUATION + FLEET)]
    assert {p.name for p in FLEET} == {"fleet.yaml", "instance_small.yaml"}


@pytest.mark.parametrize("mode", [[], ["--real-robots"]], ids=["simulated", "real-robots"])
def test_the_fleet_params_file_is_accepted_by_up(mode):
    from mapf_fleet.ros import launcher

    path = CONFIG / "fleet" / "fleet.yaml"
    args, plan, num_robots = launcher.prepare(["--params-file", str(path), *mode])
    node = "mapf_aggregator" if mode else "mapf_simulator"
    assert plan.sim_name == node
    # the file's own values reached the node that runs (not only the defaults)
    assert plan.origin[node]["max_steps"].startswith(f"params file {path}")
    assert num_robots == 8


def test_the_small_instance_is_accepted_by_up_real_robots():
    from mapf_fleet.ros import launcher

    path = CONFIG / "fleet" / "instance_small.yaml"
    _, plan, num_robots = launcher.prepare(["--instance", str(path), "--real-robots"])
    assert num_robots == 4 and plan.sim["instance_file"] == str(path)


@pytest.mark.parametrize("path", [p for p in TRAINING if p.name.startswith("dagger")], ids=_id)
def test_a_dagger_config_is_accepted_by_dagger(path):
    """As `mapf-fleet dagger --config F` reads it (dagger/cli.py)."""
    from mapf_fleet.aliases import renamed_keys
    from mapf_fleet.training.dagger.config import config_from_dict

    data = yaml.safe_load(path.read_text()) or {}
    config_from_dict(renamed_keys(data, str(path)), source=str(path))


@pytest.mark.parametrize("path", [p for p in TRAINING if not p.name.startswith("dagger")],
                         ids=_id)
def test_a_training_config_is_accepted_by_train(path):
    """As `mapf-fleet train --config F` reads it (trainer.train -> config.load_config)."""
    from mapf_fleet.training.config import load_config

    load_config(path)


@pytest.mark.parametrize("path", EVALUATION, ids=_id)
def test_an_evaluation_config_is_accepted_by_evaluate(path):
    from mapf_fleet.evaluation.protocol import ProtocolConfig

    ProtocolConfig.from_yaml(path)


def test_the_other_modes_section_is_still_checked(tmp_path):
    """The section of the node that does not run in this mode is checked against its own
    table: a typo there is still refused, with file, section and name."""
    from mapf_fleet.ros import launcher

    bad = tmp_path / "bad.yaml"
    bad.write_text("mapf_aggregator:\n  ros__parameters:\n    arival_timeout: 3.0\n")
    with pytest.raises(launcher.UpError, match=r"mapf_aggregator: unknown parameter "
                                               r"'arival_timeout'"):
        launcher.prepare(["--params-file", str(bad)])
