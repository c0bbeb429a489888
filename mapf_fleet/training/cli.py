"""`mapf-fleet train`: start a training run from a config, or resume one after a kill.

    mapf-fleet train --config config/training/dhc_cpu.yaml --run-dir runs/dhc_cpu
    mapf-fleet train --resume runs/dhc_cpu
    mapf-fleet train --config config/training/tiny.yaml --run-dir /tmp/t --set max_updates=100
    mapf-fleet train --export runs/dhc_cpu --out models/dhc.pt   # latest saved weights, any time
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import yaml


def _parse_overrides(items: list[str]) -> dict:
    overrides = {}
    for item in items:
        if "=" not in item:
            raise argparse.ArgumentTypeError(f"--set expects FIELD=VALUE, got {item!r}")
        key, value = item.split("=", 1)
        overrides[key.strip()] = yaml.safe_load(value)
    return overrides


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mapf-fleet train", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", help="training config YAML (config/training/*.yaml)")
    parser.add_argument("--run-dir", help="run directory to create (config, state, checkpoints, tb)")
    parser.add_argument("--resume", metavar="RUN", help="continue the run in this directory")
    parser.add_argument("--export", metavar="RUN",
                        help="write RUN's latest saved state (train_state.pt) as a checkpoint file "
                             "--out, without training; safe while RUN is still training")
    parser.add_argument("--out", help="checkpoint file written by --export")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                        help="override a config field (repeatable)")
    parser.add_argument("--guidance", metavar="G",
                        help="the guidance graph the actors' observations and rule read: none, "
                             "highways, a *.guidance.npz or a *.costmodel.json (same as --set "
                             "guidance=G)")
    args = parser.parse_args(argv)
    if args.guidance is not None:
        args.set.append(f"guidance={args.guidance}")
    if args.export:
        if not args.out or args.config or args.run_dir or args.resume or args.set:
            parser.error("--export RUN takes only --out FILE")
        from .export import export_checkpoint

        try:
            path, meta = export_checkpoint(args.export, args.out)
        except FileNotFoundError as exc:
            print(f"mapf-fleet train: {exc}", file=sys.stderr)
            return 2
        print(f"{path}: {meta['learner_steps']} learner updates, "
              f"curriculum {json.dumps(meta['curriculum'])}")
        return 0
    if args.resume and (args.config or args.run_dir):
        parser.error("--resume RUN takes the config from RUN; do not combine with --config/--run-dir")
    if not args.resume and not (args.config and args.run_dir):
        parser.error("give --config and --run-dir, or --resume RUN")
    # Ray workers inherit the environment; nothing here uses ROS, but stay local if anything does.
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    from .config import TrainConfigError, config_from_dict
    from .trainer import train

    try:
        overrides = _parse_overrides(args.set)
        if overrides:  # validate names and types early with a clear message
            config_from_dict(overrides, source="--set")
        result = train(args.config, args.run_dir, resume=args.resume, overrides=overrides)
    except (TrainConfigError, FileNotFoundError, argparse.ArgumentTypeError) as exc:
        print(f"mapf-fleet train: {exc}", file=sys.stderr)
        return 2
    summary = {k: result[k] for k in ("stage", "finished", "stop_reason", "alpha_star",
                                      "alpha_passed", "setting", "learner_updates")}
    print(json.dumps(summary, indent=2))
    return 0
