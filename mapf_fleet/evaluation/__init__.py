"""The paper's evaluation protocol (no rclpy): metrics, scenarios, batched runner, references
(heuristic policy, classical planner), tables/CSV/JSON/plots, renders.

Entry points: `mapf-fleet evaluate` (`cli.main`) and `mapf-fleet render` (`render.main`).
"""

from .metrics import EpisodeRecord, EpisodeTracker, ScenarioSummary, episode_from_trajectory, summarize

__all__ = ["EpisodeRecord", "EpisodeTracker", "ScenarioSummary", "episode_from_trajectory", "summarize"]
