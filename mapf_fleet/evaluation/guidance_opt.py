"""`mapf-fleet guidance`: learned guidance for continuous operation.

    mapf-fleet guidance optimize --kinds dense --agents 64 --out runs/guidance/dense64
    mapf-fleet guidance optimize --model online --init both --kinds warehouse --size 33 \
        --agents 128 --out runs/guidance/online_warehouse128
    mapf-fleet guidance make --map M.map --guidance highways --out M.guidance.npz

`optimize` learns a `grid.guidance_made.CostModel` (edge costs from local map features) with
CMA-ES (the `cmaes` package; GGO's recipe, Zhang et al., IJCAI 2024) against lifelong throughput:
each candidate runs `--episodes` lifelong episodes of plain PIBT under the fleet's rule on maps of
the family (`--kinds` / `--sizes`, a new draw of maps and goal streams every generation, the same
draw for every candidate of a generation) or on one `--map`. The objective is exactly what
`mapf-fleet evaluate --lifelong --checkpoint heuristic --guidance MODEL` measures (the same
`lifelong_runs` and `rollout`). CMA-ES starts from `--init`: none (theta = 0, unit costs, the
default of the cost model) or a hand-made graph the model can express exactly (highways; and for
`--model online`, whose costs also read recent traffic (`grid.guidance_online.OnlineModel`, Online
GGO's recipe), congestion or both, its default), so the search begins at the best hand-made point;
or a model file of the same model (a learned model, warm-started: e.g. under a new plan). Under
the `_lns` rules the task records their plan (`rules.LNS_*`); a run is resumed only under it.

Rollouts run on Ray's local pool (`--workers N`, nice'd by the caller) or a cluster (`--address`),
in this process with `--workers 1`. The state (the optimiser, history, best, CPU seconds) is
written atomically after every generation to `OUT/state.pkl`; the same command resumes it after
Ctrl-C or kill -9 (at most one generation lost). At the end the CMA-ES mean is measured on held-out
seeds beside no guidance and the hand-made graphs (a row a rollout process), and written as
`OUT/NAME.costmodel.json` (`OUT/NAME.online.json` for `--model online`) plus its card `OUT/NAME.md`
(family, agents, throughput before and after, CPU-hours, command).
"""

from __future__ import annotations

import argparse
import pickle
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from mapf_fleet.coordination import rules
from mapf_fleet.files import atomic_write
from mapf_fleet.grid.guidance import GuidanceError
from mapf_fleet.grid.guidance_made import (CONGESTION, FEATURES, HIGHWAYS, LOG_COST_CLIP,
                                           MODEL_SUFFIX, ONLINE, CostModel, GuidanceSource)
from mapf_fleet.grid.guidance_online import ONLINE_SUFFIX, PRESETS, TRAFFIC, OnlineModel

KINDS = ("dense", "random", "maze", "rooms", "warehouse")
MODELS = ("cost", ONLINE)  # what CMA-ES searches: a static CostModel or an OnlineModel
# task keys added after runs were written: the value an older state.pkl ran with
TASK_DEFAULTS = {"model": "cost"}
# held-out draws are this far from the training seeds (never drawn by a generation)
HELD_OUT_OFFSET = 1_000_003
BOTH = "both"  # the online model's preset: highways' costs times congestion's


# POGEMA's benchmark families (evaluation/pogema_bench.py's data): CMA-ES draws its maps from the
# instances after the first HELD_OUT_MAPS, which the benchmark's tables and the held-out rows use
POGEMA_FAMILIES = ("pogema-random", "pogema-mazes", "pogema-warehouse")
HELD_OUT_MAPS = 32


def pogema_grids(family: str, held_out: bool) -> list[np.ndarray]:
    """The grids of a POGEMA benchmark family ('#' obstacles): its first `HELD_OUT_MAPS` maps
    (held out) or the rest (training); the warehouse is one map."""
    from .pogema_bench import FAMILIES, load_maps

    name = family.removeprefix("pogema-")
    maps = load_maps(name)
    names = sorted(maps)
    if FAMILIES[name].single_map is None:
        names = names[:HELD_OUT_MAPS] if held_out else names[HELD_OUT_MAPS:]
    grids = [np.array([[ch == "#" for ch in row] for row in maps[n].splitlines()], np.uint8)
             for n in names]
    # padded with obstacles to the family's largest side, as the "dense" maps are: one batch
    h = max(g.shape[0] for g in grids)
    w = max(g.shape[1] for g in grids)
    return [np.pad(g, ((0, h - g.shape[0]), (0, w - g.shape[1])), constant_values=1)
            for g in grids]


def task_instances(task: dict, seed: int, held_out: bool = False):
    """The `InstanceSet` of one evaluation: `task["episodes"]` instances of the family (or of
    the one map) drawn from `seed`."""
    from .lifelong import lifelong_instances
    from .protocol import InstanceSet

    if task.get("pogema"):
        from mapf_fleet.grid.maps import place_agents

        grids = pogema_grids(task["pogema"], held_out)
        rng = np.random.default_rng([seed, 17])
        picks = (range(task["episodes"]) if held_out and len(grids) > 1
                 else rng.integers(len(grids), size=task["episodes"]))
        made = [place_agents(grids[int(k) % len(grids)], task["agents"],
                             np.random.default_rng([seed, i])) for i, k in enumerate(picks)]
        return InstanceSet.from_instances(made, f"POGEMA benchmark {task['pogema']}")
    if task.get("map"):
        from mapf_fleet.grid.maps import place_agents
        from mapf_fleet.grid.movingai import read_map

        grid = read_map(task["map"])
        made = [place_agents(grid, task["agents"], np.random.default_rng([seed, i]))
                for i in range(task["episodes"])]
        return InstanceSet.from_instances(made, f"MovingAI {Path(task['map']).name}")
    return lifelong_instances(task["kind"], task["size"], task["agents"], task["episodes"], seed)


def throughput(guidance, task: dict, seed: int, held_out: bool = False) -> tuple[float, float]:
    """(mean goals per step, CPU seconds) of plain PIBT under `task["rule"]` with `guidance` (a
    `GuidanceSource`, a `CostModel`, or a parameter vector) on the task's instances of `seed`."""
    from .lifelong import lifelong_runs, rollout
    from .policies import build_policy, parse_policy, with_conflict_rule

    began = time.process_time()
    source = as_source(guidance, task)
    instances = task_instances(task, seed, held_out)
    runs = lifelong_runs(instances, task["steps"], task["rule"], seed, series=(),
                         guidance=source)
    policy = build_policy(with_conflict_rule(parse_policy("heuristic"), task["rule"]))
    rollout(policy, runs, shielded=True)
    value = float(np.mean([run.goals_reached for run in runs])) / task["steps"]
    return value, time.process_time() - began


def as_source(guidance, task: dict) -> GuidanceSource:
    """A `GuidanceSource` of a source, a model, or a parameter vector of the task's model."""
    if isinstance(guidance, GuidanceSource):
        return guidance
    if isinstance(guidance, OnlineModel):
        return GuidanceSource(ONLINE, model=guidance)
    if isinstance(guidance, CostModel):
        return GuidanceSource("model", model=guidance)
    return as_source(model_of(guidance, task), task)


def model_of(vector, task: dict, meta: dict | None = None):
    """The task's model (`task["model"]`) of a flat parameter vector."""
    if task.get("model") == ONLINE:
        return OnlineModel.from_vector(vector, meta)
    return CostModel.from_vector(vector, meta)


def initial_vector(model: str, init: str) -> np.ndarray:
    """CMA-ES's first mean: the hand-made graph `init` as the model's parameters, or the model
    file `init` of the same model (a learned model trained on, e.g. under another plan)."""
    if init not in PRESETS:
        if not init.endswith(ONLINE_SUFFIX if model == ONLINE else MODEL_SUFFIX):
            raise ValueError(f"--init {init}: neither a preset {PRESETS} nor a "
                             f"{ONLINE_SUFFIX if model == ONLINE else MODEL_SUFFIX} file "
                             f"of --model {model}")
        try:
            return (OnlineModel if model == ONLINE else CostModel).load(init).vector()
        except GuidanceError as exc:
            raise ValueError(str(exc)) from None
    start = OnlineModel.preset(init)
    if model == ONLINE:
        return start.vector()
    if start.phi.any():
        raise ValueError(f"--init {init} reads traffic: a static cost model cannot express it "
                         f"(--model online can)")
    return np.append(start.theta, start.wait)


class Evaluator:
    """Candidates' throughputs, on Ray (`workers` > 1 or an `address`) or in this process."""

    def __init__(self, workers: int, address: str | None):
        self.ray = None
        if workers > 1 or address:
            import ray

            from mapf_fleet.training.ray_pool import init_ray

            init_ray(address, workers)
            self.ray = ray
            self.remote = ray.remote(num_cpus=1)(throughput)

    def __call__(self, vectors, task, seed) -> list[tuple[float, float]]:
        if self.ray is None:
            return [throughput(np.asarray(v), task, seed) for v in vectors]
        return self.ray.get([self.remote.remote(list(map(float, v)), task, seed)
                             for v in vectors])

    def held_out(self, guidances, task, seed) -> list[tuple[float, float]]:
        """The held-out rows' (throughput, CPU seconds): one guidance (a `GuidanceSource` or a
        model) a row, the rows side by side on the pool."""
        if self.ray is None:
            return [throughput(g, task, seed, held_out=True) for g in guidances]
        return self.ray.get([self.remote.remote(g, task, seed, True) for g in guidances])


def _save(path: Path, state: dict) -> None:
    atomic_write(path, lambda handle: pickle.dump(state, handle))


def _task(args) -> dict:
    pogema = args.kinds[0] if args.kinds[0] in POGEMA_FAMILIES else None
    return {"kind": args.kinds[0] if not (args.map or pogema) else None, "size": args.size,
            "agents": args.agents, "episodes": args.episodes, "steps": args.steps,
            "rule": args.conflict_rule, "map": args.map, "pogema": pogema, "model": args.model,
            "plan": plan_of(args.conflict_rule)}


def plan_of(rule: str) -> list[int] | None:
    """The `_lns` rules' plan the rollouts run under: [ticks ahead, repairs a tick, robots a
    repair] (`coordination.rules.LNS_*`, read now: a run resumed under another plan is refused,
    and the model's card names it); None for the other rules."""
    if not rules.Rule.parse(rule).lns:
        return None
    return [rules.LNS_WINDOW, rules.LNS_ITERATIONS, rules.LNS_NEIGHBOURHOOD]


def optimize(args) -> int:
    from cmaes import CMA

    from mapf_fleet.stop_signals import StopSignals

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    state_path = out / "state.pkl"
    task = _task(args)
    command = shlex.join(["mapf-fleet", "guidance", *args.argv])
    if state_path.exists():
        with open(state_path, "rb") as f:
            state = pickle.load(f)
        # a key added since: unset, or the value older runs had
        state["task"] = {**dict.fromkeys(task), **TASK_DEFAULTS, **state["task"]}
        if state["task"] != task:
            print(f"mapf-fleet guidance optimize: {state_path} holds a run of another task "
                  f"({state['task']}); use another --out", file=sys.stderr)
            return 2
        print(f"[guidance] resuming {state_path} at generation {state['generation']}",
              file=sys.stderr, flush=True)
        # the card names the command that finishes the run: a resumed run may be given other
        # --generations (or --workers) than it started with, and the last one says where it ended
        state["command"] = command
    else:
        mean = initial_vector(args.model, args.init)
        dim = len(mean)
        state = {"task": task, "command": command, "generation": 0, "history": [],
                 "best": None, "cpu_seconds": 0.0, "wall_seconds": 0.0, "init": args.init,
                 "start": mean.tolist(),  # the point itself: an --init file may move
                 "optimizer": CMA(mean=mean, sigma=args.sigma, seed=args.seed,
                                  population_size=args.popsize,
                                  bounds=np.tile([-args.bound, args.bound], (dim, 1)))}
    evaluate = Evaluator(args.workers, args.address)
    opt = state["optimizer"]
    if state["generation"]:
        # cmaes pickles its optimiser without the sampler's generator and unpickles a fresh,
        # unseeded one: a resumed run would draw other candidates than the run it continues. The
        # generator's state travels in our state instead (written without it: seeded by the
        # generation)
        opt._rng = np.random.RandomState([args.seed, state["generation"]])
        if state.get("rng") is not None:
            opt._rng.set_state(state["rng"])
    with StopSignals() as stop:
        while state["generation"] < args.generations and not stop.requested:
            began = time.perf_counter()
            gen = state["generation"]
            seed = args.seed * 100_003 + gen  # one draw per generation, shared by its candidates
            xs = [opt.ask() for _ in range(opt.population_size)]
            results = evaluate(xs, task, seed)
            if stop.requested:
                break  # a generation cut short is not told (the resumed run redoes it)
            opt.tell([(x, -value) for x, (value, _) in zip(xs, results)])
            values = [value for value, _ in results]
            k = int(np.argmax(values))
            if state["best"] is None or values[k] > state["best"][0]:
                state["best"] = (values[k], xs[k].tolist(), gen)
            state["history"].append({"generation": gen, "mean": float(np.mean(values)),
                                     "max": float(values[k]), "sigma": float(opt._sigma)})
            state["cpu_seconds"] += sum(cpu for _, cpu in results)
            state["wall_seconds"] += time.perf_counter() - began
            state["generation"] = gen + 1
            state["rng"] = opt._rng.get_state()
            _save(state_path, state)
            print(f"[guidance] generation {gen + 1}/{args.generations}: throughput mean "
                  f"{np.mean(values):.3f} max {values[k]:.3f} sigma {opt._sigma:.3f} "
                  f"({time.perf_counter() - began:.0f} s, {state['cpu_seconds'] / 3600:.2f} "
                  f"CPU-h)", file=sys.stderr, flush=True)
        if stop.requested:
            print(f"[guidance] stopped ({stop.name}); state in {state_path}: run the same "
                  f"command to resume", file=sys.stderr)
            return stop.exit_code or 130
    return finish(args, state, evaluate, out)


def finish(args, state: dict, evaluate, out: Path) -> int:
    """Measure the CMA-ES mean on held-out draws beside none, the hand-made graphs and the point
    it started from; write the model and its card."""
    task = dict(state["task"], episodes=args.held_out)
    seed = args.seed * 100_003 + HELD_OUT_OFFSET
    online = task["model"] == ONLINE
    model = model_of(state["optimizer"].mean, task, meta={
        "family": _family(task), "agents": task["agents"], "rule": task["rule"],
        "generations": state["generation"], "init": state.get("init", "none"),
        "plan": task.get("plan"), "command": state["command"]})
    candidates = [("none", GuidanceSource.parse("none")),
                  (HIGHWAYS, GuidanceSource.parse(HIGHWAYS)),
                  (CONGESTION, GuidanceSource.parse(CONGESTION))]
    init = state.get("init", "none")
    if online and init not in PRESETS:
        # from a learned model: the best hand-made point of the model is measured all the same
        candidates.append((BOTH, OnlineModel.preset(BOTH)))
    if init not in ("none", HIGHWAYS, CONGESTION):
        start = state.get("start")
        if start is None:  # a state written before the point was kept: a preset
            start = initial_vector(task["model"], state["init"])
        candidates.append(("start", model_of(start, task)))
    candidates.append(("learned", model))
    rows = {}
    for (row, _), (value, cpu) in zip(candidates, evaluate.held_out(
            [guidance for _, guidance in candidates], task, seed)):
        rows[row] = value
        state["cpu_seconds"] += cpu
    name = args.name or f"{'online_' if online else ''}{_family(task).replace(' ', '_')}_" \
                        f"{task['agents']}"
    model.meta.update({"held_out_throughput": rows, "cpu_hours": state["cpu_seconds"] / 3600})
    model_path = model.save(out / f"{name}{'.online.json' if online else '.costmodel.json'}")
    card = out / f"{name}.md"
    card.write_text(card_text(name, task, rows, state, model, args))
    print(card.read_text())
    print(f"[guidance] wrote {model_path} and {card}", file=sys.stderr)
    return 0


def _family(task: dict) -> str:
    if task.get("pogema"):
        return task["pogema"]
    if task.get("map"):
        return Path(task["map"]).stem
    return f"{task['kind']} {task['size']}x{task['size']}"


ROW_NAMES = {"none": "none (plain PIBT)", HIGHWAYS: "highways (hand-made)",
             CONGESTION: "congestion (hand-made, online)",
             BOTH: "highways x congestion (hand-made, online)", "start": "the starting point",
             "learned": "learned (this model)"}


def card_text(name, task, rows, state, model, args) -> str:
    online = isinstance(model, OnlineModel)
    init = state.get("init", "none")
    # every row but none and the learned ones is hand-made: the starting point is, when a preset
    not_hand = ("none", "learned") if init in PRESETS else ("none", "learned", "start")
    hand = max(v for k, v in rows.items() if k not in not_hand)
    gain = rows["learned"] / rows["none"] - 1 if rows["none"] else float("nan")
    vs_hand = rows["learned"] / hand - 1 if hand else float("nan")
    vs_start = rows["learned"] / rows["start"] - 1 if rows.get("start") else float("nan")
    theta = ", ".join(f"{f} {v:+.3f}" for f, v in zip(FEATURES, model.theta))
    if online:
        theta += "; traffic: " + ", ".join(f"{f} {v:+.3f}" for f, v in zip(TRAFFIC, model.phi))
        theta += f"; decay {model.decay}, period {model.period}"
    names = dict(ROW_NAMES, start=ROW_NAMES["start"] + ("" if init in PRESETS
                                                       else f" (learned: {Path(init).name})"))
    table = "".join(f"| {names[k]} | {v:.3f} |\n" for k, v in rows.items())
    updated = f", costs recomputed from recent traffic every {model.period} ticks" if online else ""
    plan = task.get("plan")
    if plan:
        updated += (f"; the rule's plan {plan[0]} ticks ahead, {plan[1]} repairs a tick of "
                    f"{plan[2]} robots")
    return (f"# Guidance {'online model' if online else 'cost model'} `{name}`\n\n"
            f"Learned by CMA-ES against lifelong throughput of plain PIBT under `{task['rule']}`"
            f"{updated}.\n\n"
            f"- maps: {_family(task)}; agents: {task['agents']}; {task['steps']} steps per "
            f"episode, {task['episodes']} episodes per held-out row ({args.episodes} per "
            f"candidate in training)\n"
            f"- CMA-ES: {state['generation']} generations of {state['optimizer'].population_size}"
            f" candidates, sigma0 {args.sigma}, from {state.get('init', 'none')}; "
            f"{state['cpu_seconds'] / 3600:.2f} CPU-hours, "
            f"{state['wall_seconds'] / 3600:.2f} h wall\n"
            f"- parameters: {theta}; wait {model.wait:+.3f}\n\n"
            f"| guidance | throughput (goals/step, held-out draws) |\n|---|---:|\n{table}\n"
            f"Learned over none: {gain:+.1%}; over the best hand-made graph: {vs_hand:+.1%}"
            f"{'' if init in PRESETS else f'; over its starting point: {vs_start:+.1%}'}.\n\n"
            f"Command: `{state['command']}`\n")


def make(args) -> int:
    """Write a map's guidance file from a source (highways, a cost model)."""
    from mapf_fleet.grid.movingai import read_map

    grid = read_map(args.map)
    guidance = GuidanceSource.parse(args.guidance).for_map(grid)
    if guidance is None:
        print("mapf-fleet guidance make: --guidance none has no file to write", file=sys.stderr)
        return 2
    print(f"wrote {guidance.save(args.out)}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mapf-fleet guidance", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="action", required=True)
    o = sub.add_parser("optimize", help="learn a guidance cost model by CMA-ES (resumable)")
    o.add_argument("--model", default="cost", choices=MODELS,
                   help="cost: edge costs from the map (*.costmodel.json, default); online: "
                        "from the map and recent traffic, updated as the fleet moves "
                        "(*.online.json)")
    o.add_argument("--init",
                   help="CMA-ES's starting point, a hand-made graph the model expresses "
                        "exactly: none, highways; congestion and both (highways and congestion) "
                        "with --model online (default: none for cost, both for online); or a "
                        "model file of --model (*.costmodel.json, *.online.json), e.g. one "
                        "learned under another plan")
    o.add_argument("--kinds", nargs=1, default=["dense"], choices=KINDS + POGEMA_FAMILIES,
                   help="map family (default dense: random maps of 17-21 cells; pogema-*: the "
                        "POGEMA benchmark's maps after its first 32, which stay held out)")
    o.add_argument("--size", type=int, default=21, help="map side (default 21)")
    o.add_argument("--map", help="one MovingAI .map instead of a family")
    o.add_argument("--agents", type=int, default=64)
    o.add_argument("--steps", type=int, default=128, help="steps per episode (default 128)")
    o.add_argument("--episodes", type=int, default=4, help="episodes per candidate (default 4)")
    o.add_argument("--held-out", type=int, default=32,
                   help="episodes of the final held-out comparison (default 32)")
    o.add_argument("--generations", type=int, default=40)
    o.add_argument("--popsize", type=int, default=10)
    o.add_argument("--sigma", type=float, default=0.5, help="CMA-ES initial step (default 0.5)")
    o.add_argument("--bound", type=float, default=LOG_COST_CLIP,
                   help="each parameter within [-B, B] (default: the model's log-cost clip, "
                        f"{LOG_COST_CLIP}: beyond it a cost no longer changes)")
    o.add_argument("--conflict-rule", default=rules.FLEET_RULE)
    o.add_argument("--seed", type=int, default=0)
    o.add_argument("--workers", type=int, default=1, help="rollout processes (Ray when > 1)")
    o.add_argument("--address", help="a Ray cluster's address (default: a local Ray)")
    o.add_argument("--name", help="the model's name (default: family and agents)")
    o.add_argument("--out", required=True, help="run directory (state, model, card)")
    m = sub.add_parser("make", help="write a map's guidance file (highways or a cost model)")
    m.add_argument("--map", required=True, help="MovingAI .map file")
    m.add_argument("--guidance", required=True, help="highways or a *.costmodel.json")
    m.add_argument("--out", required=True, help="*.guidance.npz to write")
    return p


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    args.argv = argv
    if args.action == "make":
        return make(args)
    args.conflict_rule = rules.Rule.parse(args.conflict_rule, "--conflict-rule").name
    if args.init is None:
        args.init = "both" if args.model == ONLINE else "none"
    try:
        initial_vector(args.model, args.init)
    except ValueError as exc:
        print(f"mapf-fleet guidance optimize: {exc}", file=sys.stderr)
        return 2
    for name in ("agents", "steps", "episodes", "held_out", "generations", "popsize", "workers"):
        if getattr(args, name) < 1:
            print(f"mapf-fleet guidance optimize: --{name.replace('_', '-')} must be >= 1",
                  file=sys.stderr)
            return 2
    return optimize(args)


__all__ = ["throughput", "optimize", "main", "as_source", "model_of", "initial_vector"]
