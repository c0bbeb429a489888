"""`mapf-fleet render`: one episode as an animated GIF or WebP (or a folder of PNG frames).

    mapf-fleet render --checkpoint C --size 40 --agents 16 --seed 3 --out ep.gif
    mapf-fleet render --checkpoint lacam --map F.map --scen F.scen --agents 8 --out ep.gif
    mapf-fleet render --run run.json --out run.gif     # a fleet's run: `up --record run.json`
    mapf-fleet render --run bags/run1 --out run.webp   # or its rosbag2 (`record` / `up --bag`)

Each agent has a colour (`robot_colour`: the same as in `mapf-fleet view` and Foxglove): its disc
is the agent, numbered where the cells are large enough, the hollow square of the same colour its
goal; a red ring marks an agent whose move was just reverted (a collision); a recorded run also shows
the paths taken. The format follows --out: .gif, .webp (animated, smaller), .mp4 (only with the
optional imageio-ffmpeg installed: `pip install imageio-ffmpeg`), else a folder of PNG frames.
"""

from __future__ import annotations

import argparse
import colorsys
import os
import sys
from pathlib import Path

import numpy as np

# the policies, the protocol and the runner are imported where used: the live view takes its
# colours from here (`robot_colour`) and must not load them
GOLDEN = 0.618033988749895
LABEL_MIN_CELL_PX = 14  # robots are numbered where a cell is this many pixels (the web view's)


def robot_colour(i: int) -> tuple[int, int, int]:
    """RGB (0-255) of robot i: hues spread by the golden ratio, so neighbours in id differ. One
    formula for every picture of a fleet: these renders, `mapf-fleet view` (its page gets the
    colours from `view.picture`) and the Foxglove scene."""
    r, g, b = colorsys.hls_to_rgb((i * GOLDEN) % 1.0, 0.45, 0.85)
    return round(r * 255), round(g * 255), round(b * 255)


def record_episode(spec, instances, max_steps: int) -> tuple[np.ndarray, np.ndarray, bool]:
    """Run the first instance of `instances`: positions (T+1, N, 2), collided (T, N), success."""
    from mapf_fleet.coordination.planners import positions_to_actions

    from .policies import build_policy
    from .runner import _make_env

    policy = build_policy(spec)
    env = _make_env(instances, 0, max_steps, getattr(policy, "observation", "paper"))
    obs = env.reset()
    trail, bumps, success = [np.asarray(env.positions).copy()], [], False
    plan = None
    if spec.is_planner:
        plan = positions_to_actions(policy.plan(instances.maps[0], instances.starts[0], instances.goals[0]).positions)
    else:
        policy.reset(1, instances.starts.shape[1])
    done = bool(np.array_equal(env.positions, instances.goals[0]))
    t = 0
    while not done:
        if plan is not None:
            actions = plan[t] if t < len(plan) else np.zeros(len(trail[0]), dtype=np.int64)
        else:
            actions = np.asarray(policy.act(obs[None].astype(np.float32), np.asarray(env.positions)[None]))[0]
        obs, _, done, info = env.step(actions)
        trail.append(np.asarray(env.positions).copy())
        bumps.append(np.asarray(info["collisions"], dtype=bool))
        success = bool(info["success"])
        t += 1
    n = len(trail[0])
    return np.stack(trail), (np.stack(bumps) if bumps else np.zeros((0, n), bool)), success


def draw_frames(grid: np.ndarray, goals: np.ndarray, positions: np.ndarray, collided: np.ndarray, title: str,
                trails: bool = False, captions=None):
    """Yield RGB frames (H, W, 3) uint8, one per time step. `goals` (N, 2), or (T + 1, N, 2)
    when they change during the run; `collided` (T, N) may have no rows (nothing known);
    `trails`: draw each agent's path so far; `captions[t]` replaces frame t's default
    "on goal" text."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h, w = grid.shape
    n = positions.shape[1]
    goals = np.asarray(goals)
    goals_at = (lambda t: goals[t]) if goals.ndim == 3 else (lambda t: goals)
    colours = np.array([robot_colour(i) for i in range(n)], dtype=float).reshape(-1, 3) / 255.0
    scale = max(4.0, min(8.0, 480 / max(h, w) / 10))
    fig, ax = plt.subplots(figsize=(scale * w / max(h, w) + 0.5, scale * h / max(h, w) + 0.7), dpi=80)
    # row 0 at the bottom, as in the map frame (y grows with the row), RViz, Foxglove and the
    # web view: a building map is drawn as its image (docs/fleet.md, "Rows and columns")
    ax.imshow(grid != 0, cmap="Greys", vmin=0, vmax=1.6, interpolation="nearest",
              origin="lower")
    marker = max(8.0, 2400.0 / max(h, w))
    paths = [ax.plot([], [], color=colours[i], alpha=0.45, linewidth=max(1.0, 70.0 / max(h, w)))[0]
             for i in range(n)] if trails else []
    targets = ax.scatter(goals_at(0)[:, 1], goals_at(0)[:, 0], s=marker, marker="s", facecolors="none",
                         edgecolors=colours, linewidths=1.2)
    agents = ax.scatter(positions[0, :, 1], positions[0, :, 0], s=marker, c=colours, edgecolors="none")
    rings = ax.scatter([], [], s=marker * 2.2, facecolors="none", edgecolors="red", linewidths=1.5)
    ax.set_xticks([])
    ax.set_yticks([])
    # the robots' numbers, as `mapf-fleet goal` and the web view count them, where they fit
    fig.canvas.draw()
    cell_px = ax.get_window_extent().width / w
    labels = [ax.text(0, 0, str(i), ha="center", va="center", color="black",
                      fontsize=max(5.0, cell_px * (0.28 if n > 99 else 0.4) * 72 / fig.dpi))
              for i in range(n)] if cell_px >= LABEL_MIN_CELL_PX else []
    for t in range(len(positions)):
        agents.set_offsets(positions[t][:, ::-1])
        for i, label in enumerate(labels):
            label.set_position((positions[t, i, 1], positions[t, i, 0]))
        targets.set_offsets(goals_at(t)[:, ::-1])
        for i, line in enumerate(paths):
            line.set_data(positions[: t + 1, i, 1], positions[: t + 1, i, 0])
        bumped = collided[t - 1] if 0 < t <= len(collided) else np.zeros(n, bool)
        rings.set_offsets(positions[t][bumped][:, ::-1] if bumped.any() else np.empty((0, 2)))
        on_goal = int(np.all(positions[t] == goals_at(t), axis=1).sum())
        caption = captions[t] if captions is not None else f"on goal {on_goal}/{n}"
        ax.set_title(f"{title}  step {t}/{len(positions) - 1}  {caption}", fontsize=9)
        fig.canvas.draw()
        yield np.asarray(fig.canvas.buffer_rgba())[:, :, :3].copy()
    plt.close(fig)


ANIMATIONS = (".gif", ".webp", ".mp4")


def check_out(out: str) -> None:
    """Refuse, before any work, an output the installed writers cannot make (ValueError)."""
    if Path(out).suffix.lower() == ".mp4":
        try:
            import imageio_ffmpeg  # noqa: F401
        except ImportError:
            raise ValueError(f"--out {out}: MP4 needs the optional imageio-ffmpeg (pip install "
                             "imageio-ffmpeg); .gif and .webp work without it") from None


def save_frames(out, frames, fps: float) -> Path:
    """Write the frames (an iterable of RGB arrays) to `out`: an animated .gif or .webp, an
    .mp4 (imageio-ffmpeg), else a folder of PNG frames."""
    import imageio.v2 as imageio

    out = Path(out)
    suffix = out.suffix.lower()
    if suffix in ANIMATIONS:
        out.parent.mkdir(parents=True, exist_ok=True)
        if suffix == ".mp4":
            check_out(str(out))
            # H.264 wants even sides: the writer's block size 2 pads the frames
            imageio.mimsave(out, list(frames), fps=fps, macro_block_size=2)
        else:
            # the Pillow writers take each frame's duration in milliseconds
            imageio.mimsave(out, list(frames), duration=1000.0 / fps, loop=0)
    else:
        out.mkdir(parents=True, exist_ok=True)
        for t, frame in enumerate(frames):
            imageio.imwrite(out / f"frame_{t:04d}.png", frame)
    return out


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mapf-fleet render", description=__doc__.split("\n")[0],
                                epilog="A fleet's recorded run: mapf-fleet render --run F.json|BAG_DIR --out "
                                       "F.gif (mapf-fleet render --run X --help for its options).")
    from mapf_fleet.models.policy import DEVICE_HELP, device_arg

    from .policies import REFERENCE_NAMES

    p.add_argument("--checkpoint", required=True, help=f"checkpoint file or one of {', '.join(REFERENCE_NAMES)}")
    p.add_argument("--size", type=int, default=40, help="square map size of a generated instance")
    p.add_argument("--agents", type=int, default=16)
    p.add_argument("--seed", type=int, default=0, help="seed of the generated instance")
    p.add_argument("--density", type=float, help="obstacle density (default: the protocol's 0.3)")
    p.add_argument("--map", help="MovingAI .map instead of a generated instance")
    p.add_argument("--scen", help="MovingAI .scen (with --map)")
    p.add_argument("--max-steps", type=int, help="step limit (default: the protocol's for the size)")
    p.add_argument("--out", required=True, help="output .gif / .webp / .mp4, or a folder for PNG frames")
    p.add_argument("--fps", type=float, default=8.0, help="frames per second of the GIF (default %(default)s)")
    p.add_argument("--device", default="auto", type=device_arg,
                   help=f"torch device of learned policies: {DEVICE_HELP}")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(sys.argv[1:] if argv is None else argv)
    if not args.fps > 0:  # also rejects nan
        print(f"mapf-fleet render: --fps must be > 0, got {args.fps:g}", file=sys.stderr)
        return 2
    try:
        check_out(args.out)
    except ValueError as exc:
        print(f"mapf-fleet render: {exc}", file=sys.stderr)
        return 2
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    from .policies import parse_policy
    from .protocol import InstanceSet, ProtocolConfig
    from .runner import lower_bounds

    config = ProtocolConfig.from_yaml()
    try:
        spec = parse_policy(args.checkpoint, device=args.device, planner_time_limit=config.planner_time_limit)
        if args.map:
            from mapf_fleet.grid.movingai import load_movingai_instances

            if not args.scen:
                raise ValueError("--map needs --scen")
            instance = load_movingai_instances(args.map, args.scen, args.agents)
            label = Path(args.map).stem
        else:
            from mapf_fleet.grid.instance import generate_instance

            density = config.density if args.density is None else args.density
            instance = generate_instance(args.size, args.agents, density, np.random.default_rng(args.seed))
            label = f"{args.size}x{args.size} seed {args.seed}"
    except (ValueError, FileNotFoundError) as exc:
        print(f"mapf-fleet render: {exc}", file=sys.stderr)
        return 2
    limits = {m.size: m.max_steps for m in config.maps}
    side = max(instance.grid.shape)
    max_steps = args.max_steps or limits.get(side, 256 if side <= 40 else 386)
    instances = InstanceSet.from_instances([instance], label)
    positions, collided, success = record_episode(spec, instances, max_steps)
    frames = draw_frames(instance.grid, instance.goals, positions, collided, f"{spec.name} | {label}")

    out = save_frames(args.out, frames, args.fps)
    print(f"{out}: {len(positions)} frames, {'success' if success else 'failure'} after {len(positions) - 1} steps "
          f"(lower bound {int(lower_bounds(instances)[0])})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
