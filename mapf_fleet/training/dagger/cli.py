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
    args = parser.parse_args(argv)
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
    if not args.run_dir:
        parser.error("--run-dir is required (or --compare RUN ...)")
    run_dir = Path(args.run_dir)
    try:
        overrides = {}
        for item in args.set:
            if "=" not in item:
                raise DaggerConfigError(f"--set expects FIELD=VALUE, got {item!r}")
            key, value = item.split("=", 1)
            overrides[key.strip()] = yaml.safe_load(value)
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
