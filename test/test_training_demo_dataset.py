"""The resumable demonstration dataset (mapf-fleet demos): shards, manifest, resume, fallback."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from mapf_fleet.grid.env import EnvConfig, MAPFEnv
from mapf_fleet.grid.instance import Instance
from mapf_fleet.grid.maps import generate_kind_instance
from mapf_fleet.training import demo_dataset as dd

TINY = dict(kinds=("random", "maze"), sizes=(10,), agents=(4,), count=2, time_limit=2.0,
            shard_size=1)


class Interrupt(Exception):
    pass


def shard_files(out):
    return sorted(p.name for p in out.glob("*.npz"))


def test_tiny_dataset_shards_and_manifest(tmp_path):
    spec = dd.DemoSpec(**TINY)
    manifest = dd.generate_dataset(tmp_path, spec, progress=False)
    assert manifest == dd.load_manifest(tmp_path)
    assert manifest["spec"] == spec.to_dict()
    assert len(manifest["shards"]) == 4 and len(shard_files(tmp_path)) == 4
    instances = dd.manifest_instances(manifest)
    assert len(instances) == 4
    for entry in manifest["shards"].values():
        shard = dd.read_shard(tmp_path / entry["file"])
        assert shard["meta"] == entry
        assert shard["grids"].shape == (1, 10, 10) and shard["starts"].shape == (1, 4, 2)
        for k, inst in enumerate(entry["instances"]):
            assert set(inst) >= {"kind", "size", "agents", "seed", "planner", "time_limit",
                                 "solved", "steps"}
            assert inst["planner"] in ("lacam", "pibt") and inst["time_limit"] == 2.0
            # the recorded seed regenerates the stored instance
            again = generate_kind_instance(inst["kind"], inst["size"], inst["agents"],
                                           inst["seed"])
            stored = Instance(shard["grids"][k], shard["starts"][k], shard["goals"][k])
            assert again == stored
            # replaying the stored actions reaches every goal exactly when marked solved
            env = MAPFEnv(stored, EnvConfig(max_steps=256))
            env.reset()
            info = {"success": False}
            for t in range(shard["steps"][k]):
                _, _, done, info = env.step(shard["actions"][k, t].astype(np.int64))
            assert info["success"] == inst["solved"] == bool(shard["solved"][k])
    assert all(i["solved"] for i in instances)  # 4 agents on 10x10: LaCAM solves them


def test_resume_after_interrupt_plans_only_the_rest(tmp_path):
    spec = dd.DemoSpec(**TINY)
    seen = []

    def stop_after_two(name):
        seen.append(name)
        if len(seen) == 2:
            raise Interrupt

    with pytest.raises(Interrupt):
        dd.generate_dataset(tmp_path, spec, progress=False, on_shard=stop_after_two)
    first = dd.load_manifest(tmp_path)
    assert sorted(first["shards"]) == sorted(seen)
    stamps = {n: os.stat(tmp_path / f"{n}.npz").st_mtime_ns for n in seen}
    planned = []
    manifest = dd.generate_dataset(tmp_path, spec, progress=False, on_shard=planned.append)
    assert len(planned) == 2 and not set(planned) & set(seen)
    assert len(manifest["shards"]) == 4
    assert {n: os.stat(tmp_path / f"{n}.npz").st_mtime_ns for n in seen} == stamps
    # a third run has nothing left to do
    again = []
    assert dd.generate_dataset(tmp_path, spec, progress=False, on_shard=again.append) == manifest
    assert again == []


def test_shard_missing_from_manifest_is_adopted_and_tmp_files_removed(tmp_path):
    spec = dd.DemoSpec(**TINY)
    full = dd.generate_dataset(tmp_path, spec, progress=False)
    # killed after the shard's os.replace and before the manifest's: the manifest lacks it
    dropped = sorted(full["shards"])[0]
    partial = json.loads(json.dumps(full))
    del partial["shards"][dropped]
    dd.write_manifest(tmp_path, partial)
    (tmp_path / f"{dropped}.npz{dd.TMP_MARK}999").write_bytes(b"half a shard")
    planned = []
    manifest = dd.generate_dataset(tmp_path, spec, progress=False, on_shard=planned.append)
    assert planned == [] and manifest == full
    assert not list(tmp_path.glob(f"*{dd.TMP_MARK}*"))
    # a shard listed in the manifest whose file is gone is planned again
    (tmp_path / f"{dropped}.npz").unlink()
    manifest = dd.generate_dataset(tmp_path, spec, progress=False, on_shard=planned.append)
    assert planned == [dropped] and (tmp_path / f"{dropped}.npz").exists()


def test_other_spec_in_the_same_directory_is_refused(tmp_path, capsys):
    dd.generate_dataset(tmp_path, dd.DemoSpec(**TINY), progress=False)
    with pytest.raises(ValueError, match=r"made with time_limit = 2.0, this run asks for 3.0"):
        dd.generate_dataset(tmp_path, dd.DemoSpec(**{**TINY, "time_limit": 3.0}), progress=False)
    code = dd.main(["--out", str(tmp_path), "--kinds", "random", "maze", "--sizes", "10",
                    "--agents", "4", "--count", "3", "--time-limit", "2", "--shard-size", "1",
                    "--no-progress"])
    assert code == 2 and "made with count = 2, this run asks for 3" in capsys.readouterr().err


@pytest.mark.parametrize("changes,words", [
    ({"kinds": ("forest",)}, "unknown kind 'forest'"),
    ({"count": 0}, "count = 0"),
    ({"time_limit": 0}, "time_limit = 0"),
    ({"agents": (200,)}, "200 agents do not fit every random map of size 10"),
])
def test_bad_spec_names_field_and_value(changes, words):
    with pytest.raises(ValueError, match=words):
        dd.DemoSpec(**{**TINY, **changes})


def test_pibt_fallback_when_lacam_leaves_agents_unplanned(monkeypatch):
    from mapf_fleet.coordination import planners

    original = planners.ClassicalPlanner.plan

    def lacam_times_out(self, grid, starts, goals):
        result = original(self, grid, starts, goals)
        if self.algorithm == "lacam":
            return planners.PlanResult(np.asarray(starts)[None], result.runtime, len(starts),
                                       "time limit")
        return result

    monkeypatch.setattr(planners.ClassicalPlanner, "plan", lacam_times_out)
    instance = generate_kind_instance("rooms", 12, 3, 7)
    result = dd.plan_instance(instance, time_limit=2.0, max_steps=256)
    assert result["planner"] == "pibt" and result["unplanned_agents"] == 0 and result["solved"]


def test_instance_seeds_are_independent_of_shard_layout():
    a = dd.DemoSpec(**TINY)
    b = dd.DemoSpec(**{**TINY, "shard_size": 2, "kinds": ("maze", "random")})
    names_a = [j for j in dd.shard_jobs(a)]
    assert len(names_a) == 4 and len(dd.shard_jobs(b)) == 2
    assert dd.instance_seed(0, "maze", 10, 4, 1) != dd.instance_seed(0, "random", 10, 4, 1)
    assert dd.instance_seed(0, "maze", 10, 4, 1) == dd.instance_seed(0, "maze", 10, 4, 1)


def test_cli_registered():
    from mapf_fleet.cli import COMMANDS, main

    assert COMMANDS["demos"][0] == "mapf_fleet.training.demo_dataset"
    with pytest.raises(SystemExit) as exit_info:
        main(["demos", "--help"])
    assert exit_info.value.code == 0


def test_resume_after_kill_9(tmp_path):
    out = tmp_path / "demos"
    args = ["--out", str(out), "--kinds", "random", "--sizes", "10", "--agents", "4",
            "--count", "60", "--time-limit", "2", "--shard-size", "2", "--no-progress"]
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    proc = subprocess.Popen([sys.executable, "-m", "mapf_fleet.training.demo_dataset", *args],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                if len(dd.load_manifest(out)["shards"]) >= 1:
                    break
            except (FileNotFoundError, json.JSONDecodeError):
                pass
            time.sleep(0.005)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL, "the run finished before it could be killed"
    before = dd.load_manifest(out)  # the manifest is never half-written
    assert 1 <= len(before["shards"]) < 30
    assert dd.main(args) == 0
    manifest = dd.load_manifest(out)
    assert len(manifest["shards"]) == 30 and len(dd.manifest_instances(manifest)) == 60
    for name, entry in before["shards"].items():
        assert manifest["shards"][name] == entry
    assert not list(out.glob(f"*{dd.TMP_MARK}*"))
