"""Tables in the paper's layout (rows = policies, columns = agent counts, one table per map and
metric), CSV, JSON and the success-rate plot."""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

from .metrics import STALL_STEPS
from .runner import ScenarioResult

# (summary field, table title, number format); the first two are the paper's tables.
PAPER_METRICS = (
    ("success_rate", "Success Rate ↑", "{:.3f}"),
    ("average_steps", "Average Time Steps ↓", "{:.2f}"),
)
EXTRA_METRICS = (
    ("agent_success_rate", "Per-agent Success ↑", "{:.3f}"),
    ("sum_of_costs", "Sum of Costs ↓", "{:.1f}"),
    ("makespan", "Makespan ↓", "{:.2f}"),
    ("collisions", "Collisions (reverted moves) per Episode ↓", "{:.2f}"),
    ("lower_bound_ratio", "Steps / Lower Bound ↓", "{:.3f}"),
    ("lower_bound_ratio_solved", "Steps / Lower Bound, solved episodes ↓", "{:.3f}"),
    ("stalled_agents", f"Stalled Agents per Episode (off goal, still for the last {STALL_STEPS} steps) ↓",
     "{:.2f}"),
    ("stalled_beside_agent", "Stalled Beside Another Agent per Episode (deadlocks) ↓", "{:.2f}"),
    ("overrides", "Shield Overrides per Episode (agent-steps not executed as first chosen)", "{:.1f}"),
)


def _maps(results: list[ScenarioResult]) -> list[str]:
    return list(dict.fromkeys(r.scenario.map_name for r in results))


def _policies(results: list[ScenarioResult]) -> list[str]:
    return list(dict.fromkeys(r.policy for r in results))


def _fmt(value: float, pattern: str) -> str:
    return "–" if value is None or (isinstance(value, float) and math.isnan(value)) else pattern.format(value)


def metric_table(results: list[ScenarioResult], map_name: str, metric: str, title: str, pattern: str) -> str:
    """One Markdown table: rows = policies, columns = agent counts of `map_name`."""
    mine = [r for r in results if r.scenario.map_name == map_name]
    agents = sorted({r.scenario.num_agents for r in mine})
    cell = {(r.policy, r.scenario.num_agents): getattr(r.summary, metric) for r in mine}
    lines = [
        f"| {title} | " + " | ".join(str(n) for n in agents) + " |",
        "|---|" + "---:|" * len(agents),
    ]
    for policy in _policies(mine):
        lines.append(f"| {policy} | " + " | ".join(_fmt(cell.get((policy, n)), pattern) for n in agents) + " |")
    return "\n".join(lines)


def _limits(results: list[ScenarioResult], map_name: str) -> str:
    limits = sorted({r.scenario.max_steps for r in results if r.scenario.map_name == map_name})
    counts = sorted({r.summary.episodes for r in results if r.scenario.map_name == map_name})
    sources = sorted({r.source for r in results if r.scenario.map_name == map_name})
    return (f"limit {'/'.join(map(str, limits))} steps, {'/'.join(map(str, counts))} instances per scenario; "
            f"instances: {'; '.join(sources)}")


def markdown_report(results: list[ScenarioResult], *, extra: bool | tuple[str, ...] = True) -> str:
    """The paper's two tables per map (success rate, average steps), then the extra metrics
    (all of them, or the named ones)."""
    if extra is True:
        extras = EXTRA_METRICS
    else:
        extras = tuple(m for m in EXTRA_METRICS if extra and m[0] in extra)
    parts = []
    for map_name in _maps(results):
        parts.append(f"### {map_name} ({_limits(results, map_name)})\n")
        for metric, title, pattern in PAPER_METRICS + extras:
            parts.append(metric_table(results, map_name, metric, title, pattern) + "\n")
    return "\n".join(parts)


CSV_FIELDS = (
    "policy", "map", "agents", "max_steps", "episodes", "success_rate", "average_steps",
    "agent_success_rate", "sum_of_costs", "makespan", "collisions", "lower_bound",
    "lower_bound_ratio", "lower_bound_ratio_solved", "stalled_agents", "stalled_beside_agent",
    "overrides", "compute_time_s", "plan_time_s", "plan_failures", "source",
)


def _row(r: ScenarioResult) -> dict:
    s = r.summary.to_dict()
    return {
        "policy": r.policy, "map": r.scenario.map_name, "agents": r.scenario.num_agents,
        "max_steps": r.scenario.max_steps, **{k: s[k] for k in s},
        "compute_time_s": round(r.compute_time, 3),
        "plan_time_s": None if r.plan_time is None else round(r.plan_time, 3),
        "plan_failures": r.plan_failures, "source": r.source,
    }


def csv_report(results: list[ScenarioResult]) -> str:
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=CSV_FIELDS, lineterminator="\n")
    writer.writeheader()
    for r in results:
        writer.writerow({k: ("" if v is None else v) for k, v in _row(r).items()})
    return out.getvalue()


def json_report(results: list[ScenarioResult], metadata: dict | None = None, *, episodes: bool = True) -> dict:
    """Every figure: the summaries and, with `episodes`, every episode's record."""
    rows = []
    for r in results:
        row = _row(r)
        if episodes:
            row["episodes"] = [e.to_dict() for e in r.episodes]
        rows.append(row)
    return {"metadata": metadata or {}, "results": rows}


def write_json(path: str | Path, results: list[ScenarioResult], metadata: dict | None = None) -> None:
    Path(path).write_text(json.dumps(json_report(results, metadata), indent=1, allow_nan=False) + "\n")


def plot_success(results: list[ScenarioResult], path: str | Path) -> None:
    """PNG: success rate against agent count, one panel per map, one line per policy."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    maps = _maps(results)
    fig, axes = plt.subplots(1, len(maps), figsize=(5 * len(maps), 4), squeeze=False)
    for ax, map_name in zip(axes[0], maps):
        mine = [r for r in results if r.scenario.map_name == map_name]
        for policy in _policies(mine):
            points = sorted((r.scenario.num_agents, r.summary.success_rate) for r in mine if r.policy == policy)
            ax.plot([p[0] for p in points], [p[1] for p in points], marker="o", label=policy)
        ax.set_xscale("log", base=2)
        agents = sorted({r.scenario.num_agents for r in mine})
        ax.set_xticks(agents, [str(n) for n in agents])
        ax.set_ylim(-0.02, 1.02)
        ax.set_xlabel("agents")
        ax.set_ylabel("success rate")
        ax.set_title(map_name)
        ax.grid(alpha=0.3)
        ax.legend(fontsize="small")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
