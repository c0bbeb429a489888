"""`mapf-fleet card` and the paper's tables as data.

The card is built from a synthetic run directory (TensorBoard scalars written with
SummaryWriter), random small checkpoints and an evaluation JSON made by the real evaluator on 2
instances per scenario."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest
import yaml

from mapf_fleet.evaluation import paper_results
from mapf_fleet.evaluation.model_card import CardError, build_card, main

REPO = Path(__file__).resolve().parents[1]
PAPER_TEXT = Path("/work/shared/paper/cooperative-mapf-paper.txt")
NUMBER = re.compile(r"^\d+\.\d+$")  # values have decimals; agent counts do not


# ---- the paper's numbers ---------------------------------------------------------------------


def _numeric_rows(lines: list[str]) -> list[list[float]]:
    """The numbers of each line that has any (tab-separated cells of the text export)."""
    rows = []
    for line in lines:
        numbers = [float(c) for c in line.split("\t") if NUMBER.match(c.strip())]
        if numbers:
            rows.append(numbers)
    return rows


def _block_after(text: list[str], heading: str, count: int, start: int = 0) -> list[list[float]]:
    """The first `count` numeric rows after the first line at or after `start` containing `heading`."""
    index = next(i for i in range(start, len(text)) if heading in text[i])
    rows = []
    for line in text[index + 1:]:
        found = _numeric_rows([line])
        if found:
            rows.append(found[0])
            if len(rows) == count:
                return rows
    raise AssertionError(f"fewer than {count} rows after {heading!r}")


@pytest.fixture(scope="module")
def paper_lines() -> list[str]:
    if not PAPER_TEXT.is_file():
        pytest.skip(f"{PAPER_TEXT} not present")
    return PAPER_TEXT.read_text().splitlines()


def _as_rows(rows: list[paper_results.PaperRow], metric: str) -> list[list[float]]:
    return [[getattr(r, metric)[n] for n in sorted(getattr(r, metric))] for r in rows]


def test_table_4_matches_the_paper_text(paper_lines):
    parsed = _block_after(paper_lines, "Table 4:", 9)
    # Each line of Table 4 holds the 5 success rates, then the 5 average steps.
    mine = paper_results.paper_rows(map_size=40)
    assert [r.label for r in mine][:2] == ["DHC baseline", "DHC α=0.1"]
    assert [s + t for s, t in zip(_as_rows(mine, "success_rate"), _as_rows(mine, "average_steps"))] == parsed


def test_table_1_matches_the_paper_text(paper_lines):
    start = next(i for i, line in enumerate(paper_lines) if line.startswith("Table 1:"))
    success = _block_after(paper_lines, "Success Rate", 9, start)
    steps = _block_after(paper_lines, "Average Time Steps", 9, start)
    mine = paper_results.paper_rows(map_size=80, methods=(paper_results.BASELINE, paper_results.CURRICULUM))
    assert _as_rows(mine, "success_rate") == success
    assert _as_rows(mine, "average_steps") == steps
    assert paper_results.paper_row("dcc", 80, 0.2).success_rate[128] == 0.865


def test_table_2_rows_are_identified_by_their_values(paper_lines):
    """The text's Table 2 alternates w/o CL and Proposed rows (labels shifted, the last Proposed
    row missing): Proposed rows must equal Table 1, the others are our w/o CL rows."""
    start = next(i for i, line in enumerate(paper_lines) if line.startswith("Table 2:"))
    for metric, heading in (("success_rate", "Success Rate"), ("average_steps", "Average Time Steps")):
        # the alpha label (0.2, 0.3...) shares some lines: the values are the last 6 numbers
        parsed = [row[-6:] for row in _block_after(paper_lines, heading, 9, start)]
        fixed = [r for r in paper_results.paper_rows(map_size=80, methods=(paper_results.FIXED,))]
        proposed = [paper_results.paper_row(r.algorithm, 80, r.alpha) for r in fixed[:4]]
        assert parsed[0::2] == _as_rows(fixed, metric)
        assert parsed[1::2] == _as_rows(proposed, metric)


def test_paper_row_lookup():
    assert paper_results.paper_row("dhc", 40, 0.3).success_rate[64] == 0.645
    assert paper_results.paper_row("dhc", 40, 0.0).method == paper_results.BASELINE
    assert paper_results.paper_row("dcc", 40, 0.4) is None  # DCC stops at 0.3
    assert paper_results.paper_row("dhc", 80, 0.3, paper_results.FIXED).success_rate[128] == 0.535
    with pytest.raises(ValueError, match="algorithm"):
        paper_results.paper_rows("ppo")


# ---- the card ----------------------------------------------------------------------------------


def _trainer_like_checkpoint(path: Path, algo: str = "dhc") -> Path:
    """A random small network with the metadata the trainer writes after stage 2."""
    import torch

    from mapf_fleet.models.checkpoint import build_model, save_checkpoint
    from mapf_fleet.models.config import ModelConfig
    from mapf_fleet.training.config import load_config

    torch.manual_seed(1)
    config = load_config(Path(__file__).resolve().parents[1] / "config" / "training" / f"{algo}_cpu.yaml")
    config = config.replace(max_wall_seconds=7200.0)
    metadata = {
        "alpha": 0.2,
        "curriculum": {"stage": "done", "setting": [12, 40], "alpha_passed": [0.0, 0.1, 0.2], "alpha_star": 0.2},
        "learner_steps": 4321,
        "training_config": config.to_dict(),
        "extra": {"trained_with_code": [
            {"package": "0.1.0", "git_commit": "a" * 40, "from_update": 0},
            {"package": "0.1.0", "git_commit": "b" * 40, "from_update": 2000,
             "overrides": {"explore_all_agents": False}}]},
    }
    return save_checkpoint(path, build_model(ModelConfig.preset(algo, "small")), metadata)


def _run_dir(root: Path, checkpoint: Path, config: dict) -> Path:
    from torch.utils.tensorboard import SummaryWriter

    run = root / "run"
    (run / "checkpoints").mkdir(parents=True)
    shutil.copy(checkpoint, run / "checkpoints" / "alpha_0.2.pt")
    (run / "config.yaml").write_text(yaml.safe_dump(config))
    (run / "result.json").write_text(json.dumps({
        "stage": "done", "alpha_star": 0.2, "stop_reason": "alpha 0.3 did not pass",
        "counters": {"episodes": 900, "env_steps": 55000, "agent_steps": 400000, "elapsed_seconds": 5400.0,
                     "cpu_seconds": 9000.0, "cpu_measured_from_elapsed_seconds": 0.0},
    }))
    writer = SummaryWriter(str(run / "tb"))
    for step in range(0, 500, 100):
        writer.add_scalar("curriculum/gate_success_rate", 0.5 + step / 1000, step)
        writer.add_scalar("curriculum/num_agents", 1 + step // 100, step)
        writer.add_scalar("curriculum/map_size", 10 + 5 * (step // 200), step)
        writer.add_scalar("curriculum/alpha", 0.0 if step < 300 else 0.1, step)
        writer.add_scalar("learner/loss", 1.0 / (step + 1), step)
    writer.close()
    return run


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    """Two checkpoints and one evaluation JSON of the first (2 instances, 40x40 and 80x80)."""
    import torch

    from mapf_fleet.evaluation.cli import main as evaluate_main
    from mapf_fleet.evaluation.random_checkpoint import save_random_checkpoint

    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("card")
    trained = _trainer_like_checkpoint(root / "dhc_coop.pt")
    other = save_random_checkpoint(root / "other.pt", "dhc", "small", seed=3)
    eval_json = root / "dhc_coop_eval.json"
    code = evaluate_main(["--conflict-rule", "revert", "--checkpoint", str(trained), "--sizes", "40", "80", "--agents", "4",
                          "--instances", "2", "--cache-dir", str(root / "cache"),
                          "--json", str(eval_json), "--quiet"])
    assert code == 0
    return root, trained, other, eval_json


def test_card_holds_the_measured_and_the_paper_values(evaluated, tmp_path):
    root, checkpoint, _, eval_json = evaluated
    from mapf_fleet.training.config import load_config

    config = load_config(Path(__file__).resolve().parents[1] / "config" / "training" / "dhc_cpu.yaml").to_dict()
    run = _run_dir(tmp_path, checkpoint, config)
    out, curves = tmp_path / "models" / "dhc_coop.md", tmp_path / "models" / "dhc_coop_curves.png"
    assert main(["--checkpoint", str(checkpoint), "--eval", str(eval_json), "--run-dir", str(run),
                 "--out", str(out), "--curves", str(curves)]) == 0
    card = out.read_text()
    data = json.loads(eval_json.read_text())

    # Every measured cell of the JSON (this checkpoint and the references) appears in its row.
    for row in data["results"]:
        name = "**dhc_coop** (this checkpoint)" if row["policy"] == "dhc_coop" else f"{row['policy']} (reference)"
        table_rows = [line for line in card.splitlines() if line.startswith(f"| {name} |")]
        assert f"{row['success_rate']:.3f}" in table_rows[0] or f"{row['success_rate']:.3f}" in table_rows[2]
        assert any(f"{row['average_steps']:.2f}" in line for line in table_rows)
    assert "LaCAM (reference)" in card and "heuristic (reference)" in card
    # The first target, judged on the JSON's rows: 40x40 and 80x80 at 4 agents each.
    by = {(r["policy"], r["map"]): r["success_rate"] for r in data["results"]}
    expected = [f"Success rate above the non-learned heuristic: "
                f"{'at every agent count' if by[('dhc_coop', m)] > by[('heuristic', m)] else 'at no agent count'} (of 4)."
                for m in ("40x40", "80x80")]
    assert [line for line in card.splitlines() if line.startswith("Success rate above")] == expected
    # The paper's rows of the same algorithm, at the measured agent count (4).
    assert "| paper Table 4: DHC α=0.2 ◀ same α | 1.000 |" in card
    assert "| paper Table 1: DHC baseline | 0.990 |" in card
    assert "| paper Table 4: DHC baseline | 52.33 |" in card
    assert "DCC" not in "".join(line for line in card.splitlines() if line.startswith("| paper"))
    # The evaluate command recorded by the evaluator, to re-run it.
    assert data["metadata"]["command"] in card
    # What the checkpoint is.
    assert "12 agents on 40x40" in card and "| alpha* (stage 2) | 0.2 |" in card
    assert "| learner steps | 4,321 |" in card and "preset `small`" in card
    # Compute: 5400 s x num_cpus 2 = 3.00 CPU-hours, from result.json.
    assert "**3.00 CPU-hours**" in card and "result.json counters.elapsed_seconds" in card
    assert "Measured: **2.50 CPU-hours** of process CPU time" in card and "over the last" not in card
    assert ("| code that trained it (per training session) | mapf_fleet 0.1.0, git aaaaaaaaaaaa from "
            "update 0; mapf_fleet 0.1.0, git bbbbbbbbbbbb from update 2000 (resumed with "
            "`explore_all_agents=False`) |") in card
    # Training config: closest file and the fields that differ from the paper's recipe.
    assert "`config/training/dhc_cpu.yaml` (differs in `max_wall_seconds`)" in card
    from mapf_fleet.training.config import config_from_dict

    paper_batch = config_from_dict({"preset": "dhc"}).batch_size
    assert config["batch_size"] != paper_batch  # the CPU config is smaller than the paper's
    assert f"| `batch_size` | `{config['batch_size']!r}` | `{paper_batch!r}` |" in card
    assert "`checkpoints/alpha_0.2.pt` (same bytes)" in card
    # Curves: PNG written, linked relative to the card, last values from TensorBoard.
    assert curves.is_file() and curves.stat().st_size > 1000
    assert "![training curves](dhc_coop_curves.png)" in card
    assert "| `curriculum/gate_success_rate` | 0.9 | 400 |" in card


def test_card_of_a_random_checkpoint_without_run_dir(tmp_path):
    import torch

    from mapf_fleet.evaluation.cli import main as evaluate_main
    from mapf_fleet.evaluation.random_checkpoint import save_random_checkpoint

    torch.set_num_threads(1)
    checkpoint = save_random_checkpoint(tmp_path / "rand.pt", "dcc", "small")
    eval_json = tmp_path / "rand.json"
    assert evaluate_main(["--conflict-rule", "revert", "--checkpoint", str(checkpoint), "--sizes", "40", "--agents", "4",
                          "--instances", "2", "--no-references", "--json", str(eval_json), "--quiet"]) == 0
    card = build_card(checkpoint, eval_json)
    value = json.loads(eval_json.read_text())["results"][0]["success_rate"]
    assert f"| **rand** (this checkpoint) | {value:.3f} |" in card
    assert "| paper Table 4: DCC baseline ◀ same α | 1.000 |" in card
    assert "untrained: random weights" in card and "Compute" in card and "Not recorded" in card


def test_eval_json_of_another_checkpoint_is_refused(evaluated, tmp_path):
    _, _, other, eval_json = evaluated
    with pytest.raises(CardError, match=r"evaluates checkpoint\(s\) .*dhc_coop\.pt, not .*other\.pt"):
        build_card(other, eval_json)
    # The command reports it and exits 2 without writing.
    out = tmp_path / "x.md"
    assert main(["--checkpoint", str(other), "--eval", str(eval_json), "--out", str(out)]) == 2
    assert not out.exists()


def test_run_dir_of_another_algorithm_is_refused(evaluated, tmp_path):
    _, checkpoint, _, eval_json = evaluated
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text(yaml.safe_dump({"algo": "dcc", "model_preset": "small"}))
    with pytest.raises(CardError, match=r"config.yaml: algo 'dcc', but the checkpoint is 'dhc'"):
        build_card(checkpoint, eval_json, run_dir=run)


def test_missing_inputs_are_named(evaluated, tmp_path):
    _, checkpoint, _, eval_json = evaluated
    with pytest.raises(CardError, match=r"--eval .*nope\.json: no such file"):
        build_card(checkpoint, tmp_path / "nope.json")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"results": []}))
    with pytest.raises(CardError, match="keys 'metadata' and 'results'"):
        build_card(checkpoint, bad)
    with pytest.raises(CardError, match="--curves .*needs --run-dir"):
        build_card(checkpoint, eval_json, curves=tmp_path / "c.png")
    with pytest.raises(CardError, match="--checkpoint: .*no such checkpoint file"):
        build_card(tmp_path / "missing.pt", eval_json)


def test_warm_start_time_not_yet_counted_by_the_trainer_is_read_from_tb(tmp_path):
    import time

    from torch.utils.tensorboard import SummaryWriter

    from mapf_fleet.evaluation.model_card import RunInfo, uncounted_warm_start_seconds

    writer = SummaryWriter(str(tmp_path / "tb"))
    start = time.time()
    for step in (10, 20, 30, 40, 50):  # 40 and 50: interleaved demo updates after the warm start
        writer.add_scalar("demo/loss", 1.0 / step, step, walltime=start + 4 * step)
    writer.close()
    run = RunInfo(tmp_path, tb_dir=tmp_path / "tb", state_counters={"demo_pretrained": 1},
                  config={"demo_pretrain_updates": 30})
    assert uncounted_warm_start_seconds(run) == pytest.approx(120.0, abs=5.0)
    # counted by the trainer (demo_seconds), or no warm start: nothing to add
    run.state_counters["demo_seconds"] = 130.0
    assert uncounted_warm_start_seconds(run) == 0.0
    # demo_seconds began in a later session: only demonstration refreshes in it, the first warm
    # start still uncounted
    run.state_counters["demo_seconds"] = 40.0
    assert uncounted_warm_start_seconds(run) == pytest.approx(120.0, abs=5.0)
    assert uncounted_warm_start_seconds(RunInfo(tmp_path, tb_dir=tmp_path / "tb",
                                                state_counters={})) == 0.0


def test_compute_reports_measured_cpu_time_and_what_it_covers(tmp_path):
    from mapf_fleet.evaluation.model_card import RunInfo, compute_spent

    config = {"use_ray": True, "num_cpus": 2}
    counters = {"elapsed_seconds": 7200.0, "cpu_seconds": 5400.0,
                "cpu_measured_from_elapsed_seconds": 3600.0}
    run = RunInfo(tmp_path, config=config, state_counters=counters)
    compute = compute_spent(run, {})
    assert compute.cpu_hours == pytest.approx(4.0)  # reserved: 2 h x 2 CPUs
    assert compute.measured_cpu_seconds == 5400.0 and compute.measured_from_elapsed == 3600.0
    # runs from before the measurement: nothing measured, nothing claimed
    old = compute_spent(RunInfo(tmp_path, config=config, state_counters={"elapsed_seconds": 60.0}), {})
    assert old.measured_cpu_seconds is None


def test_checkpoint_counters_give_the_compute_up_to_that_checkpoint(tmp_path):
    """A checkpoint that carries the run's counters of its moment is measured up to itself, not
    with the totals of a run that went on training after it."""
    from mapf_fleet.evaluation.model_card import CHECKPOINT_POINT, RunInfo, compute_spent

    config = {"use_ray": True, "num_cpus": 2}
    later = RunInfo(tmp_path, config=config, state_counters={"elapsed_seconds": 9000.0, "cpu_seconds": 15000.0})
    meta = {"extra": {"counters": {"elapsed_seconds": 1800.0, "cpu_seconds": 3000.0}}}
    compute = compute_spent(later, meta)
    assert compute.source.startswith(CHECKPOINT_POINT)
    assert compute.cpu_hours == pytest.approx(1.0) and compute.measured_cpu_seconds == 3000.0
    # without them: the whole run, as before
    assert compute_spent(later, {}).cpu_hours == pytest.approx(5.0)


def test_compare_puts_other_checkpoints_of_the_same_evaluation_side_by_side(tmp_path):
    import torch

    from mapf_fleet.evaluation.cli import main as evaluate_main
    from mapf_fleet.models.checkpoint import load_checkpoint, save_checkpoint

    torch.set_num_threads(1)
    warm = _trainer_like_checkpoint(tmp_path / "warm.pt")
    model, loaded = load_checkpoint(warm)
    meta = {k: loaded[k] for k in ("alpha", "curriculum", "learner_steps", "training_config", "extra")}
    meta["training_config"]["demo_source"] = "planner"
    meta["extra"]["counters"] = {"elapsed_seconds": 3600.0, "cpu_seconds": 5400.0}
    save_checkpoint(warm, model, meta)
    meta = dict(meta, learner_steps=777, curriculum={"stage": "scale", "setting": [3, 20]})
    meta["training_config"] = dict(meta["training_config"], demo_source="none")
    meta["extra"] = {"counters": {"elapsed_seconds": 7200.0, "cpu_seconds": 1800.0,
                                  "cpu_measured_from_elapsed_seconds": 5400.0}}
    scratch = save_checkpoint(tmp_path / "scratch.pt", model, meta)
    unrelated = _trainer_like_checkpoint(tmp_path / "unrelated.pt")
    eval_json = tmp_path / "both.json"
    assert evaluate_main(["--conflict-rule", "revert", "--checkpoint", str(warm), str(scratch), "--sizes", "40", "--agents", "4",
                          "--instances", "2", "--no-references", "--json", str(eval_json), "--quiet"]) == 0
    card = build_card(warm, eval_json, compare=[scratch])
    rows = {r["policy"]: r["success_rate"] for r in json.loads(eval_json.read_text())["results"]}
    assert "## Side by side" in card
    assert ("| **warm** (this checkpoint) | DHC | DQfD warm start on LaCAM plans | 12 agents on 40x40 "
            "| 0.2 | 4,321 | 1.50 | 2.00 |") in card
    assert ("| scratch | DHC | paper recipe (no demonstrations) | 3 agents on 20x20 | 0.2 | 777 "
            "| 0.50 (last 0.50 h of wall time) | 4.00 |") in card
    assert f"| scratch | {rows['scratch']:.3f} |" in card and f"| warm | {rows['warm']:.3f} |" in card
    # CHECKPOINT=RUN_DIR: the run directory is read (and must exist)
    (tmp_path / "scratch_run").mkdir()
    (tmp_path / "scratch_run" / "result.json").write_text(json.dumps({"counters": {"episodes": 5}}))
    assert build_card(warm, eval_json, compare=[f"{scratch}={tmp_path / 'scratch_run'}"]).count("| scratch |") == 2
    with pytest.raises(CardError, match="no_run.*no such directory"):
        build_card(warm, eval_json, compare=[f"{scratch}={tmp_path / 'no_run'}"])
    with pytest.raises(CardError, match="unrelated.pt"):  # not in that evaluation
        build_card(warm, eval_json, compare=[unrelated])
    with pytest.raises(CardError, match="--compare .*missing.pt"):
        build_card(warm, eval_json, compare=[tmp_path / "missing.pt"])


def test_several_evaluation_files_are_read_as_one(tmp_path):
    """`--eval A.json B.json`: rows of both (a row in both taken from the first), both re-run
    commands printed; one name for two different checkpoint files is refused."""
    import torch

    from mapf_fleet.evaluation.cli import main as evaluate_main
    from mapf_fleet.evaluation.random_checkpoint import save_random_checkpoint

    torch.set_num_threads(1)
    mine = save_random_checkpoint(tmp_path / "mine.pt", "dhc", "small", seed=1)
    other = save_random_checkpoint(tmp_path / "other.pt", "dhc", "small", seed=2)
    first, second = tmp_path / "first.json", tmp_path / "second.json"
    common = ["--sizes", "40", "--agents", "4", "--instances", "2", "--quiet"]
    assert evaluate_main(["--conflict-rule", "revert", "--checkpoint", str(mine), "heuristic", "--no-references", *common,
                          "--json", str(first)]) == 0
    assert evaluate_main(["--conflict-rule", "revert", "--checkpoint", str(other), "heuristic", "--no-references", *common,
                          "--json", str(second)]) == 0
    card = build_card(mine, [first, second], compare=[other])
    rows = {(r["policy"], json_name): r["success_rate"]
            for json_name in ("first", "second")
            for r in json.loads((tmp_path / f"{json_name}.json").read_text())["results"]}
    assert f"| other | {rows[('other', 'second')]:.3f} |" in card
    assert f"| heuristic (reference) | {rows[('heuristic', 'first')]:.3f} |" in card
    for path in (first, second):
        assert json.loads(path.read_text())["metadata"]["command"] in card
    assert "`first.json, second.json`" in card
    # the same policy name for another file
    clash = tmp_path / "clash"
    clash.mkdir()
    save_random_checkpoint(clash / "other.pt", "dhc", "small", seed=3)
    third = tmp_path / "third.json"
    assert evaluate_main(["--conflict-rule", "revert", "--checkpoint", str(clash / "other.pt"), "--no-references", *common,
                          "--json", str(third)]) == 0
    with pytest.raises(CardError, match="policy 'other' is .*other.pt in .*second.json but .*clash"):
        build_card(mine, [first, second, third])


def test_alpha_star_of_a_fixed_budget_run_says_the_gate_was_off():
    from mapf_fleet.evaluation.model_card import _alpha_star_text

    assert _alpha_star_text(0.2, {"alpha_mode": "curriculum"}) == "0.2"
    # Stage 2 still running (or stopped) with the paper's gate: alpha* is unknown.
    assert _alpha_star_text(None, {"alpha_mode": "fixed", "fixed_alpha": 0.3,
                                   "success_threshold": 0.9}) == "stage 2 did not finish"
    # An A/B arm at matched compute: the gate cannot pass, so there is no alpha* by design.
    text = _alpha_star_text(None, {"alpha_mode": "fixed", "fixed_alpha": 0.3, "success_threshold": 1.0})
    assert text.startswith("none by design: fixed alpha 0.3 with the gate off")
    assert _alpha_star_text(None, {"alpha_mode": "curriculum", "success_threshold": 1.0}) == \
        "stage 2 did not finish"


def test_card_of_an_intermediate_checkpoint_stops_its_curves_at_it(evaluated, tmp_path):
    """A warm-start or stage-2 alpha checkpoint of a run that trained on: the curves and their last
    values end at the checkpoint's update, and the run's stop reason says it came later."""
    from torch.utils.tensorboard import SummaryWriter

    from mapf_fleet.training.config import load_config

    root, checkpoint, _, eval_json = evaluated  # learner_steps 4321
    config = load_config(Path(__file__).resolve().parents[1] / "config" / "training" / "dhc_cpu.yaml").to_dict()
    run = _run_dir(tmp_path, checkpoint, config)
    result = json.loads((run / "result.json").read_text())
    result.update(learner_updates=6000, stop_reason="stopped by SIGINT (resume with --resume)")
    (run / "result.json").write_text(json.dumps(result))
    writer = SummaryWriter(str(run / "tb"))
    for step in (4000, 4321, 5000, 6000):
        writer.add_scalar("curriculum/gate_success_rate", step / 10000, step)
        writer.add_scalar("learner/loss", 0.5, step)
    writer.close()
    out, curves = tmp_path / "card.md", tmp_path / "curves.png"
    assert main(["--checkpoint", str(checkpoint), "--eval", str(eval_json), "--run-dir", str(run),
                 "--out", str(out), "--curves", str(curves)]) == 0
    card = out.read_text()
    assert "| `curriculum/gate_success_rate` | 0.4321 | 4,321 |" in card
    assert "| `curriculum/num_agents` | 5 | 400 |" in card  # only logged before the checkpoint
    assert "up to this checkpoint's update 4,321, the run logged on to update 6,000" in card
    assert "| run stop reason | stopped by SIGINT (resume with --resume) (at update 6,000, after this checkpoint) |" in card
    assert "6,000 |" not in card.split("### Training curves")[1].split("## Versions")[0]
    # Its metadata holds no counters of its own moment: the run's compute is only an upper bound.
    assert ("This checkpoint is an intermediate point (update 4,321) of a run that went on to update 6,000: "
            "the figures here are the whole run's") in card


def test_scalars_up_to_keeps_the_checkpoints_part():
    from mapf_fleet.evaluation.model_card import scalars_up_to

    scalars = {"a": [(0, 1.0), (10, 2.0), (20, 3.0)], "b": [(15, 1.0)]}
    assert scalars_up_to(scalars, 10) == ({"a": [(0, 1.0), (10, 2.0)]}, 20)
    assert scalars_up_to(scalars, 20) == (scalars, None)


def test_append_adds_the_shielded_rows_to_an_existing_card(tmp_path):
    """`mapf-fleet card --append TITLE`: the checkpoint's shielded rows beside its own, added to
    its existing card; a card of another checkpoint is refused."""
    import torch

    from mapf_fleet.evaluation.cli import main as evaluate_main
    from mapf_fleet.evaluation.model_card import main as card_main
    from mapf_fleet.evaluation.random_checkpoint import save_random_checkpoint

    torch.set_num_threads(1)
    checkpoint = save_random_checkpoint(tmp_path / "rand.pt", "dcc", "small")
    plain, shielded = tmp_path / "plain.json", tmp_path / "shielded.json"
    common = ["--sizes", "40", "--agents", "4", "--instances", "2", "--quiet"]
    assert evaluate_main(["--conflict-rule", "revert", "--checkpoint", str(checkpoint), "--no-references", "--json", str(plain), *common]) == 0
    assert evaluate_main(["--checkpoint", str(checkpoint), "heuristic", "--no-references", "--conflict-rule", "pibt",
                          "--guidance", "none", "--json", str(shielded), *common]) == 0
    card = tmp_path / "rand.md"
    assert card_main(["--checkpoint", str(checkpoint), "--eval", str(plain), "--out", str(card)]) == 0
    before = card.read_text()
    assert card_main(["--checkpoint", str(checkpoint), "--eval", str(plain), str(shielded),
                      "--out", str(card), "--append", "Under the coordination layer"]) == 0
    after = card.read_text()
    # with the card's other results, before its training part; nothing else changed
    head, tail = before.split("\n## How it was trained and what it cost\n")
    assert after.startswith(head.rstrip("\n")) and after.endswith("## How it was trained and what it cost\n" + tail)
    added = after[len(head.rstrip("\n")):-len("## How it was trained and what it cost\n" + tail)]
    assert "### Under the coordination layer" in added and "--conflict-rule pibt" in added
    assert after.index("## Results") < after.index("### Under the coordination layer") \
        < after.index("## How it was trained")
    assert "**rand +PIBT** (this checkpoint under the PIBT shield)" in added
    assert "heuristic +PIBT (reference)" in added
    other = save_random_checkpoint(tmp_path / "other.pt", "dcc", "small", seed=5)
    assert card_main(["--checkpoint", str(other), "--eval", str(shielded), "--out", str(card),
                      "--append", "x"]) == 2


def test_the_card_reads_in_the_readers_order(evaluated, tmp_path):
    """What it is, how to run it, the results, then how it was trained and what it cost."""
    _, checkpoint, _, eval_json = evaluated
    card = build_card(checkpoint, eval_json)
    headings = [line for line in card.splitlines() if line.startswith("## ")]
    assert headings == ["## What it is", "## How to run it", "## Results",
                        "## How it was trained and what it cost", "## Versions"]
    assert f"mapf-fleet up --checkpoint {checkpoint}" in card  # outside a checkout: as given
    assert card.index("### Evaluation (the paper's protocol)") < card.index("### Training configuration")


def test_add_section_to_an_older_card_appends_it():
    from mapf_fleet.evaluation.model_card import add_section

    assert add_section("# card\n\n## Versions\n", "\n## New\n") == "# card\n\n## Versions\n\n## New\n"
    new = add_section("## Results\n\nr\n\n## How it was trained and what it cost\n\nt\n", "\n### New\n")
    assert new == "## Results\n\nr\n\n### New\n\n## How it was trained and what it cost\n\nt\n"


def test_shielded_rows_are_compared_with_plain_pibt_in_success_and_steps():
    from mapf_fleet.evaluation.model_card import PLAIN_PIBT, _against_plain_pibt

    def row(policy, agents, success, steps):
        return {"policy": policy, "agents": agents, "success_rate": success, "average_steps": steps}

    rows = [row("m +PIBT", 16, 0.97, 70.0), row(PLAIN_PIBT, 16, 0.95, 72.0),
            row("m +PIBT", 32, 0.93, 90.0), row(PLAIN_PIBT, 32, 0.93, 83.0),
            row("m +PIBT", 64, 0.40, 200.0), row(PLAIN_PIBT, 64, 0.70, 130.0)]
    (text, _) = _against_plain_pibt(rows, "m +PIBT", [16, 32, 64])
    assert "success rate at least PIBT's at 16, 32 agents only" in text
    assert "average steps at most PIBT's at 16 agents only" in text
    better = [row("m +PIBT", 16, 1.0, 60.0), row(PLAIN_PIBT, 16, 0.9, 70.0)]
    assert "at every agent count" in _against_plain_pibt(better, "m +PIBT", [16])[0]
    assert _against_plain_pibt(rows[:1], "m +PIBT", [16]) == []  # no PIBT row: nothing said
    # under a guidance graph the bar is plain PIBT under the same graph
    guided = [row("m +PIBT +highways", 16, 1.0, 60.0), row(PLAIN_PIBT, 16, 0.5, 90.0),
              row(PLAIN_PIBT + " +highways", 16, 1.0, 59.0)]
    text = _against_plain_pibt(guided, "m +PIBT +highways", [16])[0]
    assert text.startswith(f"m +PIBT +highways against plain PIBT ({PLAIN_PIBT} +highways, ")
    assert "average steps at most PIBT's at no agent count" in text


def test_card_of_a_dagger_round_states_its_dagger_record(tmp_path):
    """A DAgger checkpoint's card gives its own rows (training, init, labels, unlabelled states,
    measured CPU time, the recorded ranking) instead of the Ape-X curriculum's stage-1 setting,
    alpha gate and alpha*, and the side-by-side table names its training and compute."""
    models = REPO / "models"
    text = build_card(models / "dcc_4x25_cl_alpha1.0_dagger_r7.pt",
                      [models / "eval" / "dagger_r7_anchor_40.json",
                       models / "eval" / "dagger_r7_anchor_80.json",
                       models / "eval" / "dcc_4x25_cl_alpha1.0_pibt.json"],
                      compare=[models / "archive" / "dcc_4x25_cl_alpha1.0.pt"])
    what = text.split("## What it is", 1)[1].split("## How to run it", 1)[0]
    rows = dict(line.strip("|").split(" | ", 1) for line in what.splitlines()
                if line.startswith("| ") and " | " in line)
    rows = {k.strip(): v.strip(" |") for k, v in rows.items()}
    assert "alphas that passed the gate (stage 2)" not in rows
    assert "curriculum setting reached (stage 1)" not in rows
    assert rows["training"].startswith("DAgger round 7 of 8 behind `pibt_anchor`")
    assert rows["labels"].startswith("123,170 (every agent of 3,005 labelled states")
    assert rows["states LaCAM left unlabelled"].startswith("177 unsolved")
    assert rows["DAgger compute to this checkpoint"].startswith("0.48 CPU-hours measured")
    assert rows["ranking it runs with unless told otherwise (recorded)"] == \
        "`q_then_distance` under `pibt_anchor`"
    assert "**0.48 CPU-hours** measured to this checkpoint" in text
    # 80x80 holds only its shielded rows: their instance count is still stated
    assert "Measured on 200 instances per scenario, limit 386 steps" in text
    assert "Measured on  instances" not in text
    side = text.split("### Side by side", 1)[1]
    mine = next(line for line in side.splitlines() if "(this checkpoint)" in line)
    assert "DAgger round 7 of 8" in mine and "DAgger task mix" in mine and "| 0.48 |" in mine


def test_hand_written_notes_are_included_verbatim_and_survive_regeneration(tmp_path):
    import torch

    from mapf_fleet.evaluation.cli import main as evaluate_main
    from mapf_fleet.evaluation.model_card.command import main as card_main
    from mapf_fleet.evaluation.random_checkpoint import save_random_checkpoint

    torch.set_num_threads(1)
    checkpoint = save_random_checkpoint(tmp_path / "rand.pt", "dcc", "small")
    eval_json = tmp_path / "rand.json"
    assert evaluate_main(["--conflict-rule", "revert", "--checkpoint", str(checkpoint), "--sizes", "40", "--agents", "4",
                          "--instances", "1", "--no-references", "--json", str(eval_json), "--quiet"]) == 0
    out = tmp_path / "cards" / "rand.md"
    args = ["--checkpoint", str(checkpoint), "--eval", str(eval_json), "--out", str(out)]
    assert card_main(args) == 0  # no notes file: no assessment section
    assert "## Assessment" not in out.read_text()
    notes = tmp_path / "cards" / "rand.notes.md"
    notes.write_text("**Where it stands**: a random network.\n\n| a | b |\n|---|---|\n| 1 | 2 |\n")
    for _ in range(2):  # the X.notes.md beside the card is picked up, and again on regeneration
        assert card_main(args) == 0
        text = out.read_text()
        assert text.count("## Assessment") == 1
        assert notes.read_text().strip() in text
        assert text.index("## Assessment") < text.index("## What it is")
    assert card_main(args + ["--notes", str(tmp_path / "missing.md")]) == 2
