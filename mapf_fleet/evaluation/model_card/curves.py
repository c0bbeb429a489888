"""The training curves of a card: the run's TensorBoard scalars (`read_scalars`), cut at the
checkpoint's update (`scalars_up_to`), drawn as one PNG (`plot_curves`)."""

from __future__ import annotations

from pathlib import Path

# TensorBoard tags written by mapf_fleet.training.trainer (training.loop_report.write_scalars).
TAG_GATE_SUCCESS = "curriculum/gate_success_rate"
TAG_AGENTS = "curriculum/num_agents"
TAG_MAP_SIZE = "curriculum/map_size"
TAG_ALPHA = "curriculum/alpha"
TAG_LOSS = "learner/loss"
CURVE_TAGS = (TAG_GATE_SUCCESS, TAG_AGENTS, TAG_MAP_SIZE, TAG_ALPHA, TAG_LOSS)


def read_scalars(tb_dir: Path) -> dict[str, list[tuple[int, float]]]:
    """Every scalar of RUN/tb as tag -> [(step, value)] (all event files, in order)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    accumulator = EventAccumulator(str(tb_dir), size_guidance={"scalars": 0})
    accumulator.Reload()
    return {tag: [(e.step, e.value) for e in accumulator.Scalars(tag)]
            for tag in accumulator.Tags().get("scalars", [])}


def scalars_up_to(scalars: dict[str, list[tuple[int, float]]], learner_steps: int
                  ) -> tuple[dict[str, list[tuple[int, float]]], int | None]:
    """The scalars logged up to a checkpoint's learner update, and the last update the run logged
    beyond it (None if none): the card of an intermediate checkpoint (a warm start, an alpha of
    stage 2) shows the training that made it, not what the run did afterwards."""
    later = [step for points in scalars.values() for step, _ in points if step > learner_steps]
    kept = {tag: [(step, value) for step, value in points if step <= learner_steps]
            for tag, points in scalars.items()}
    return {tag: points for tag, points in kept.items() if points}, (max(later) if later else None)


def plot_curves(scalars: dict[str, list[tuple[int, float]]], out: Path, title: str) -> list[str]:
    """PNG of the curves (success rate, curriculum setting, alpha, loss) against learner
    updates; returns the tags plotted."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(10, 7))
    plotted = []

    def line(ax, tag, label, **style):
        points = scalars.get(tag)
        if not points:
            return False
        ax.plot([p[0] for p in points], [p[1] for p in points], label=label, **style)
        plotted.append(tag)
        return True

    panels = [
        (axes[0, 0], "success rate of the gating actors", [(TAG_GATE_SUCCESS, "gate success rate", {})]),
        (axes[0, 1], "curriculum setting", [(TAG_AGENTS, "agents", {"drawstyle": "steps-post"})]),
        (axes[1, 0], "alpha (cooperation coefficient)", [(TAG_ALPHA, "alpha", {"drawstyle": "steps-post"})]),
        (axes[1, 1], "learner loss", [(TAG_LOSS, "loss", {})]),
    ]
    for ax, name, tags in panels:
        drawn = [line(ax, tag, label, **style) for tag, label, style in tags]
        if ax is axes[0, 1] and scalars.get(TAG_MAP_SIZE):
            twin = ax.twinx()
            line(twin, TAG_MAP_SIZE, "map size", color="tab:orange", linestyle="--", drawstyle="steps-post")
            twin.set_ylabel("map size (cells per side)", color="tab:orange")
            drawn.append(True)
        if not any(drawn):
            ax.text(0.5, 0.5, "not logged", ha="center", va="center", transform=ax.transAxes)
        ax.set_title(name)
        ax.set_xlabel("learner updates")
        ax.grid(alpha=0.3)
    if scalars.get(TAG_GATE_SUCCESS):
        axes[0, 0].set_ylim(-0.02, 1.02)
    loss = scalars.get(TAG_LOSS) or []
    if loss and all(v > 0 for _, v in loss):
        axes[1, 1].set_yscale("log")
    axes[0, 1].set_ylabel("agents")
    fig.suptitle(title)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return plotted
