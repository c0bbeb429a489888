"""Before/after check of a refactor: the shipped checkpoint's evaluation JSON under every conflict
rule, per episode, on the first published 40x40 instances with 64 agents.

    python benchmarks/eval_equivalence.py run OUT_DIR [--instances 20]     # one JSON per rule
    python benchmarks/eval_equivalence.py compare BEFORE_DIR AFTER_DIR      # episode by episode

Run `run` on the old commit (a `git worktree` with PYTHONPATH pointing at it) and on the new one,
then `compare`: it prints, per rule, how many episodes are identical in every metric (wall times
left out) and which metrics differ. Exit 1 when any episode differs.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mapf_fleet.coordination.rules import CONFLICT_RULES  # noqa: E402


def run(out: Path, instances: int, checkpoint: str) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for rule in CONFLICT_RULES:
        subprocess.run([sys.executable, "-m", "mapf_fleet.cli", "evaluate", "--checkpoint",
                        checkpoint, "--no-references", "--conflict-rule", rule, "--sizes", "40",
                        "--agents", "64", "--instances", str(instances), "--json", str(out / f"{rule}.json"), "--quiet",
                        "--workers", "1"], check=True, stdout=subprocess.DEVNULL)
        print(f"{rule}: {out / f'{rule}.json'}", flush=True)


def episodes(path: Path) -> list[dict]:
    data = json.loads(path.read_text())
    return [{k: v for k, v in e.items() if "time" not in k and "second" not in k}
            for result in data["results"] for e in result["episodes"]]


def compare(before: Path, after: Path) -> int:
    bad = 0
    for path in sorted(before.glob("*.json")):
        a, b = episodes(path), episodes(after / path.name)
        same = sum(x == y for x, y in zip(a, b)) if len(a) == len(b) else 0
        keys = sorted({k for x, y in zip(a, b) for k in x if x[k] != y.get(k)})
        bad += same != len(a)
        print(f"{path.stem:30s} {same}/{len(a)} episodes identical"
              f"{'; differ in ' + ', '.join(keys) if keys else ''}")
    return 1 if bad else 0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="action", required=True)
    r = sub.add_parser("run")
    r.add_argument("out", type=Path)
    r.add_argument("--instances", type=int, default=20)
    r.add_argument("--checkpoint", default=str(ROOT / "models" / "default.pt"))
    c = sub.add_parser("compare")
    c.add_argument("before", type=Path)
    c.add_argument("after", type=Path)
    args = p.parse_args()
    if args.action == "run":
        run(args.out, args.instances, args.checkpoint)
        return 0
    return compare(args.before, args.after)


if __name__ == "__main__":
    sys.exit(main())
