"""The card's results: the evaluator's rows of the checkpoint (unshielded and under the PIBT
shield) beside the references (heuristic, plain PIBT, LaCAM) and the paper's rows
(`evaluation_section`), with the re-run commands of the JSON(s) (`evaluation_block`), and the
side-by-side table of several checkpoints (`comparison_section`)."""

from __future__ import annotations

import math
from pathlib import Path

from mapf_fleet import paths

from .. import paper_results
from ..paper_results import BASELINE, CURRICULUM, FIXED
from .compute import compute_spent
from .facts import dagger_record, dagger_training_text
from .inputs import CardError, RunInfo, match_policy

# The paper's tables: (summary field, title, format), as mapf_fleet.evaluation.report prints them.
CARD_METRICS = (("success_rate", "Success rate ↑", "{:.3f}"), ("average_steps", "Average time steps ↓", "{:.2f}"))
REPO_ROOT = paths.SOURCE_ROOT  # paths given by the user are shown relative to a checkout


def _fmt(value, pattern: str) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    return pattern.format(value)


def _episode_count(row: dict) -> int:
    episodes = row.get("episodes")
    return len(episodes) if isinstance(episodes, list) else int(episodes or 0)


def _map_size(map_name: str) -> int | None:
    parts = map_name.split("x")
    if len(parts) == 2 and parts[0] == parts[1] and parts[0].isdigit():
        return int(parts[0])
    return None


def evaluation_section(evaluation: dict, policy: str, metadata: dict, eval_path: Path,
                       level: int = 3) -> list[str]:
    """Per map (a heading of `level`): the measured rows of this checkpoint and of the references,
    the paper's rows of the same algorithm below them."""
    references = [p["name"] for p in evaluation["metadata"]["policies"] if p.get("kind") != "checkpoint"]
    # the same checkpoint under the coordination layer (rows "<policy> +PIBT", "+PIBT(mode)")
    shielded = [p["name"] for p in evaluation["metadata"]["policies"] if p.get("kind") == "checkpoint"
                and p["name"].startswith(f"{policy} +PIBT")]
    rows = [r for r in evaluation["results"] if r["policy"] in (policy, *shielded, *references)]
    if not any(r["policy"] == policy for r in rows):
        raise CardError(f"--eval {eval_path}: metadata lists {policy!r} but results hold no row of it")
    algorithm, alpha = metadata["algorithm"], float(metadata["alpha"])
    fixed = (metadata.get("training_config") or {}).get("alpha_mode") == "fixed"
    lines = []
    for map_name in dict.fromkeys(r["map"] for r in rows):
        mine = [r for r in rows if r["map"] == map_name]
        agents = sorted({int(r["agents"]) for r in mine})
        limits = "/".join(str(v) for v in sorted({r["max_steps"] for r in mine}))
        # this checkpoint's rows, shielded ones included (a map may have only those)
        counts = "/".join(str(v) for v in sorted({_episode_count(r) for r in mine
                                                  if r["policy"] in (policy, *shielded)}))
        sources = "; ".join(sorted({str(r.get("source", "?")) for r in mine}))
        size = _map_size(map_name)
        paper = []
        if size in paper_results.TABLE_BY_SIZE:
            methods = (BASELINE, CURRICULUM, FIXED) if fixed else (BASELINE, CURRICULUM)
            paper = paper_results.paper_rows(algorithm, size, methods)
        lines.append(f"{'#' * level} {map_name}\n")
        if counts:
            lines.append(f"Measured on {counts} instances per scenario, limit {limits} steps; "
                         f"instances: {sources}.")
        else:  # only the references were run on this map
            others = "/".join(str(v) for v in sorted({_episode_count(r) for r in mine}))
            lines.append(f"This checkpoint has no row on this map: the references' rows below were "
                         f"measured on {others} instances per scenario, limit {limits} steps; "
                         f"instances: {sources}.")
        if paper:
            tables = ", ".join(dict.fromkeys(r.table for r in paper))
            lines.append(f"Paper rows ({tables}) are the paper's own numbers on 200 instances per scenario "
                         "(its instances, its training compute), quoted for comparison.")
        lines.append("")
        for metric, title, pattern in CARD_METRICS:
            cell = {(r["policy"], int(r["agents"])): r[metric] for r in mine}
            lines.append(f"| {title} | " + " | ".join(str(n) for n in agents) + " |")
            lines.append("|---|" + "---:|" * len(agents))
            own = [policy, *[n for n in shielded if any(r["policy"] == n for r in mine)]]
            for name in [*own, *[n for n in references if any(r["policy"] == n for r in mine)]]:
                label = (f"**{name}** (this checkpoint)" if name == policy else
                         f"**{name}** (this checkpoint under the PIBT shield)" if name in own else
                         f"{name} (reference)")
                lines.append(f"| {label} | " + " | ".join(_fmt(cell.get((name, n)), pattern) for n in agents) + " |")
            for row in paper:
                values = getattr(row, metric)
                same_method = row.method == BASELINE or (row.method == FIXED) == fixed
                mark = " ◀ same α" if abs(row.alpha - alpha) < 1e-9 and same_method else ""
                lines.append(f"| paper {row.table}: {row.label}{mark} | "
                             + " | ".join(_fmt(values.get(n), pattern) for n in agents) + " |")
            lines.append("")
        lines += _against_heuristic(mine, policy, agents)
        # the rows under a shield (the checkpoint's own row too when the JSON ran it shielded)
        for name in [*([policy] if "+PIBT" in policy else []), *shielded]:
            lines += _against_plain_pibt(mine, name, agents)
    return lines


RECIPES = {"none": "paper recipe (no demonstrations)",
           "planner": "DQfD warm start on LaCAM plans",
           "heuristic": "DQfD warm start on the heuristic policy"}


def _hours(value: float | None) -> str:
    return "not recorded" if value is None else f"{value / 3600:.2f}"


def comparison_section(evaluation: dict, policy: str, metadata: dict, eval_path: Path,
                       others: list[tuple[Path, dict]], run: RunInfo | None, level: int = 2) -> list[str]:
    """This checkpoint beside other checkpoints measured in the same evaluation JSON(s) (e.g. a warm
    start beside the paper's recipe): how each was trained, the compute spent up
    to it and its success rates. `others`: (checkpoint, its metadata, its RunInfo or None)."""
    entries = [(policy, metadata, compute_spent(run, metadata))]
    for path, meta, other_run in others:
        name = match_policy(evaluation, path, eval_path)
        if name == policy:
            raise CardError(f"--compare {path}: is the card's own checkpoint")
        entries.append((name, meta, compute_spent(other_run, meta)))
    lines = [f"{'#' * level} Side by side", "",
             f"Checkpoints measured with the same protocol (`{eval_path.name}`); compute up to each "
             "checkpoint, read from its metadata (measured = process CPU time of the trainer and its "
             "actors; reserved = wall time x CPUs of the run).", "",
             "| checkpoint | algorithm | training | setting reached | alpha | learner steps "
             "| CPU-h measured | CPU-h reserved |", "|---|---|---|---|---:|---:|---:|---:|"]
    for name, meta, compute in entries:
        config = meta.get("training_config") or {}
        setting = (meta.get("curriculum") or {}).get("setting") or ["?", "?"]
        setting_text = f"{setting[0]} agents on {setting[1]}x{setting[1]}"
        training = RECIPES.get(config.get('demo_source', 'none'), config.get('demo_source'))
        measured = None if compute is None else compute.measured_cpu_seconds
        dagger = dagger_record(meta)
        if dagger is not None:  # a DAgger round: its task mix, its own measured CPU time
            training, setting_text = dagger_training_text(dagger), "DAgger task mix"
            if compute is None and isinstance(dagger.get("cpu_seconds"), (int, float)):
                measured = float(dagger["cpu_seconds"])
        if compute is not None and compute.measured_from_elapsed > 0 and measured is not None:
            measured_text = f"{measured / 3600:.2f} (last {(compute.wall_seconds - compute.measured_from_elapsed) / 3600:.2f} h of wall time)"
        else:
            measured_text = _hours(measured)
        reserved = None if compute is None or compute.cpu_hours is None else compute.cpu_hours * 3600
        label = f"**{name}** (this checkpoint)" if name == policy else name
        lines.append(f"| {label} | {meta.get('algorithm', '?').upper()} "
                     f"| {training} "
                     f"| {setting_text} | {float(meta.get('alpha', 0)):g} "
                     f"| {int(meta.get('learner_steps', 0)):,} | {measured_text} | {_hours(reserved)} |")
    lines.append("")
    names = [e[0] for e in entries]
    rows = [r for r in evaluation["results"] if r["policy"] in names]
    for map_name in dict.fromkeys(r["map"] for r in rows):
        mine = [r for r in rows if r["map"] == map_name]
        agents = sorted({int(r["agents"]) for r in mine})
        cell = {(r["policy"], int(r["agents"])): r["success_rate"] for r in mine}
        lines.append(f"| Success rate ↑, {map_name} | " + " | ".join(str(n) for n in agents) + " |")
        lines.append("|---|" + "---:|" * len(agents))
        for name in names:
            lines.append(f"| {name} | " + " | ".join(_fmt(cell.get((name, n)), "{:.3f}") for n in agents) + " |")
        lines.append("")
    return lines


def _against_heuristic(rows: list[dict], policy: str, agents: list[int]) -> list[str]:
    """Where this checkpoint's success rate is above the non-learned decentralized policy's
    (the first bar a learned policy must clear), from the measured rows only."""
    mine = {int(r["agents"]): r["success_rate"] for r in rows if r["policy"] == policy}
    floor = {int(r["agents"]): r["success_rate"] for r in rows if r["policy"] == "heuristic"}
    shared = [n for n in agents if n in mine and n in floor]
    if not shared:
        return []
    above = [n for n in shared if mine[n] > floor[n]]
    verdict = "at every agent count" if len(above) == len(shared) else (
        "at " + ", ".join(map(str, above)) + " agents only" if above else "at no agent count")
    return [f"Success rate above the non-learned heuristic: {verdict} "
            f"(of {', '.join(map(str, shared))}).", ""]


PLAIN_PIBT = "heuristic +PIBT"  # the evaluator's row of the heuristic's ranking under the shield


def _against_plain_pibt(rows: list[dict], name: str, agents: list[int]) -> list[str]:
    """Where this checkpoint under the shield is at least plain PIBT (the non-learned ranking
    under the same shield: the bar a learned ranking must clear), in success rate and in average steps, from
    the measured rows only."""
    # under a guidance graph both rows carry its label last ("m +PIBT +highways"): the bar is
    # plain PIBT under the same graph
    tokens = name.split(" ")
    guided = len(tokens) >= 3 and tokens[-1].startswith("+") and tokens[-2].startswith("+")
    plain = PLAIN_PIBT + (" " + tokens[-1] if guided else "")
    mine = {int(r["agents"]): r for r in rows if r["policy"] == name}
    pibt = {int(r["agents"]): r for r in rows if r["policy"] == plain}
    shared = [n for n in agents if n in mine and n in pibt]
    if not shared:
        return []

    def verdict(ok: list[int]) -> str:
        if len(ok) == len(shared):
            return "at every agent count"
        return ("at " + ", ".join(map(str, ok)) + " agents only") if ok else "at no agent count"

    success = [n for n in shared if mine[n]["success_rate"] >= pibt[n]["success_rate"]]
    steps = [n for n in shared if mine[n]["average_steps"] <= pibt[n]["average_steps"]]
    return [f"{name} against plain PIBT ({plain}, same shield): success rate at least "
            f"PIBT's {verdict(success)}, average steps at most PIBT's {verdict(steps)} "
            f"(of {', '.join(map(str, shared))}).", ""]


def _repo_relative(path: str) -> str:
    try:
        return Path(path).resolve().relative_to(REPO_ROOT).as_posix()
    except ValueError:
        return path


def evaluation_block(evaluation: dict, policy: str, metadata: dict, eval_path, title: str,
                     level: int = 2) -> list[str]:
    """The card's evaluation section (a heading of `level`): the re-run commands of the JSON(s),
    then the tables, one sub-heading per map."""
    runs = evaluation["runs"]
    lines = [f"{'#' * level} {title}", "",
              "Re-run the numbers below with (from the directory it was run in):", ""]
    for path, meta in runs:
        if len(runs) > 1:
            lines += [f"`{path.name}`:", ""]
        lines += [f"```\n{meta.get('command', '(the evaluation JSON does not record its command)')}\n```", ""]
        info = []
        if meta.get("protocol_file"):
            info.append(f"protocol `{_repo_relative(meta['protocol_file'])}`")
        if meta.get("density") is not None:
            info.append(f"obstacle density {meta['density']}")
        if meta.get("seed") is not None:
            info.append(f"generator seed {meta['seed']}")
        if meta.get("wall_time_s") is not None:
            info.append(f"wall time {meta['wall_time_s']:.0f} s with {meta.get('workers', '?')} worker(s)")
        if meta.get("versions"):
            info.append("versions " + ", ".join(f"{k} {v}" for k, v in meta["versions"].items()))
        if info:
            lines += ["Evaluation: " + "; ".join(info) + ".", ""]
    if len(runs) > 1:
        lines += ["A row measured in several of these files is taken from the first one listed.", ""]
    lines += evaluation_section(evaluation, policy, metadata, eval_path, level + 1)
    return lines
