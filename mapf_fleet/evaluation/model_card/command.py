"""`mapf-fleet card`: a checkpoint's model card in Markdown.

The command line: write a new card (`build_card`) or append an evaluation section to an existing
one (`--append`, `append_evaluation`); a bad input is one line on stderr and exit 2."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mapf_fleet.files import atomic_write

from .card import add_section, append_evaluation, build_card, default_notes
from .inputs import CardError


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mapf-fleet card", description=__doc__.split("\n")[0])
    p.add_argument("--checkpoint", required=True, help="the checkpoint file (models/X.pt)")
    p.add_argument("--eval", required=True, nargs="+", metavar="JSON",
                   help="JSON(s) of `mapf-fleet evaluate --json` on it (several are read as one)")
    p.add_argument("--run-dir", help="the trainer's run directory (config, counters, tb/ scalars)")
    p.add_argument("--out", required=True, help="Markdown file to write (models/X.md)")
    p.add_argument("--curves", metavar="PNG", help="write the training curves here (needs --run-dir)")
    p.add_argument("--append", metavar="TITLE",
                   help="add the --eval section under this heading to the existing card --out "
                        "(which must name the checkpoint's SHA-256) instead of writing a new card: "
                        "with its other results, before 'How it was trained' (an older card: at "
                        "the end)")
    p.add_argument("--compare", nargs="+", metavar="CHECKPOINT", default=[],
                   help="other checkpoints evaluated in the --eval JSON(s), as CHECKPOINT or "
                        "CHECKPOINT=RUN_DIR (its run directory, for what the checkpoint does not "
                        "record): a side-by-side table of how each was trained, the compute up to it "
                        "and its success rates")
    p.add_argument("--notes", metavar="MD",
                   help="hand-written assessment (Markdown) included verbatim after the header "
                        "(default: the card's X.notes.md beside --out, when it exists)")
    return p


def main(argv: list[str] | None = None) -> int:
    import shlex

    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    if args.append:
        try:
            text = append_evaluation(args.checkpoint, args.eval, args.out, args.append,
                                     "mapf-fleet card " + shlex.join(argv))
        except CardError as exc:
            print(f"mapf-fleet card: {exc}", file=sys.stderr)
            return 2
        atomic_write(args.out, add_section(Path(args.out).read_text(), text).encode())
        print(f"added to {args.out}")
        return 0
    notes = args.notes
    if notes is None and default_notes(args.out).is_file():
        notes = default_notes(args.out)
    try:
        text = build_card(args.checkpoint, args.eval, run_dir=args.run_dir, out=args.out,
                          curves=args.curves, command="mapf-fleet card " + shlex.join(argv),
                          compare=args.compare, notes=notes)
    except (CardError, FileNotFoundError) as exc:
        print(f"mapf-fleet card: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    print(f"wrote {out}" + (f" and {args.curves}" if args.curves else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
