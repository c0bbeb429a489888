"""`mapf-fleet dagger`: start or resume a DAgger run, or compare finished runs."""

from __future__ import annotations

import json
import os
from pathlib import Path

import yaml

from mapf_fleet.aliases import renamed_keys

from . import __doc__ as OVERVIEW
from .config import DaggerConfigError, config_from_dict
from .driver import CONFIG_FILE, STATE_JSON, Dagger
from .report import compare_runs, plot_runs


def main(argv: list[str] | None = None) -> int:
    import argparse
    import sys

    parser = argparse.ArgumentParser(prog="mapf-fleet dagger", description=OVERVIEW,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", help="DAgger config YAML (config/training/dagger_*.yaml); "
                                         "ignored when RUN already holds a run (it resumes)")
    parser.add_argument("--run-dir", help="run directory (created; rerun to resume)")
    parser.add_argument("--compare", nargs="+", metavar="RUN",
                        help="print a Markdown table of these runs' held-out curves side by side "
                             "(the A/Bs) and exit; no training")
    parser.add_argument("--last", type=int, default=4,
                        help="with --compare: average the held-out checks of the last K rounds")
    parser.add_argument("--plot", metavar="PNG",
                        help="with --compare: also draw the runs' success per round to this PNG")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                        help="override a config field (repeatable; also on a resume)")
    parser.add_argument("--guidance", metavar="G",
                        help="the guidance graph the rollouts' observations and rule read: none, "
                             "highways, a *.guidance.npz or a *.costmodel.json (same as --set "
                             "guidance=G)")
    parser.add_argument("--expert-ceiling", action="store_true",
                        help="run the configured labeller as the policy under the configured "
                             "conflict rule beside plain PIBT on the config's `ceiling` suites "
                             "(ceiling.py) and exit; no training, no run directory")
    parser.add_argument("--count", type=int, metavar="N",
                        help="with --expert-ceiling: instances per row (default: the config's "
                             "ceiling_count)")
    parser.add_argument("--json", metavar="OUT",
                        help="with --expert-ceiling: also write the rows to this JSON file")
    args = parser.parse_args(argv)
    if args.guidance is not None:
        args.set.append(f"guidance={args.guidance}")
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    if args.compare:
        try:
            print(compare_runs(args.compare, args.last))
            if args.plot:
                print(f"curves: {plot_runs(args.compare, args.plot)}")
        except (DaggerConfigError, OSError, ValueError, KeyError) as exc:
            print(f"mapf-fleet dagger: {exc}", file=sys.stderr)
            return 2
        return 0
    if args.expert_ceiling:
        return _ceiling(args)
    if not args.run_dir:
        parser.error("--run-dir is required (or --compare RUN ..., or --expert-ceiling)")
    run_dir = Path(args.run_dir)
    try:
        overrides = _overrides(args.set)
        if (run_dir / STATE_JSON).is_file():
            data = yaml.safe_load((run_dir / CONFIG_FILE).read_text()) or {}
            source = str(run_dir / CONFIG_FILE)
        elif args.config:
            data = yaml.safe_load(Path(args.config).read_text()) or {}
            source = args.config
        else:
            raise DaggerConfigError(f"{run_dir}: no run to resume; give --config")
        cfg = config_from_dict({**renamed_keys(data, source), **renamed_keys(overrides, "--set")},
                               source=source)
        result = Dagger(cfg, run_dir, log=lambda m: print(m, flush=True)).run()
    except (DaggerConfigError, FileNotFoundError, OSError, ValueError) as exc:
        print(f"mapf-fleet dagger: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(result, indent=1))
    return 0


def _overrides(items: list[str]) -> dict:
    overrides = {}
    for item in items:
        if "=" not in item:
            raise DaggerConfigError(f"--set expects FIELD=VALUE, got {item!r}")
        key, value = item.split("=", 1)
        overrides[key.strip()] = yaml.safe_load(value)
    return overrides


def _ceiling(args) -> int:
    import sys

    from .ceiling import expert_ceiling, markdown

    try:
        if not args.config:
            raise DaggerConfigError("--expert-ceiling needs --config (a DAgger config YAML)")
        if args.count is not None and args.count < 1:
            raise DaggerConfigError(f"--count must be >= 1, got {args.count}")
        try:
            data = yaml.safe_load(Path(args.config).read_text()) or {}
        except yaml.YAMLError as exc:
            raise DaggerConfigError(f"{args.config}: invalid YAML: {exc}") from None
        cfg = config_from_dict({**renamed_keys(data, args.config),
                                **renamed_keys(_overrides(args.set), "--set")}, source=args.config)
        result = expert_ceiling(cfg, args.count, log=lambda m: print(m, flush=True))
    except (DaggerConfigError, OSError, ValueError) as exc:
        print(f"mapf-fleet dagger: {exc}", file=sys.stderr)
        return 2
    print(markdown(result))
    if args.json:
        Path(args.json).write_text(json.dumps({"argv": sys.argv, **result}, indent=1))
    return 0
