"""The card itself, in the order a reader needs it: `build_card` puts the sections together
(what it is, how to run it, results beside the references and the paper, how it was trained and
what it cost: configuration, compute, curves, side by side; versions); `append_evaluation`
writes another results section for an existing card and `add_section` puts it with the results."""

from __future__ import annotations

import datetime as _dt
import os
from pathlib import Path

from .compute import CHECKPOINT_POINT, compute_spent
from .curves import CURVE_TAGS, plot_curves, read_scalars, scalars_up_to
from .facts import (_alpha_star_text, _trained_with_text, _version_text, dagger_facts, dagger_record,
                    model_summary, rankings_text, training_config_diff)
from .inputs import CardError, _sha256, load_evaluations, match_policy, read_run_dir
from .tables import _repo_relative, comparison_section, evaluation_block


def _yaml_block(data: dict) -> str:
    import yaml

    return "```yaml\n" + yaml.safe_dump(data, sort_keys=False).rstrip() + "\n```"


def _relative(target: Path, start: Path) -> str:
    return Path(os.path.relpath(target.resolve(), start.resolve())).as_posix()


def append_evaluation(checkpoint: str | Path, eval_path, out: str | Path, title: str,
                      command: str) -> str:
    """Append an evaluation section (tables and re-run commands) to the existing card `out` of
    `checkpoint`, e.g. its protocol under the coordination layer, for a card whose training run
    directory is gone (a new card would lose its compute and curves). The card must name the
    checkpoint's SHA-256; returns the appended text."""
    from mapf_fleet.models.checkpoint import CheckpointError, load_checkpoint

    checkpoint, out = Path(checkpoint), Path(out)
    try:
        _, metadata = load_checkpoint(checkpoint)
    except CheckpointError as exc:
        raise CardError(f"--checkpoint: {exc}") from exc
    if not out.is_file():
        raise CardError(f"--append: {out}: no such card to append to")
    card = out.read_text()
    if _sha256(checkpoint) not in card:
        raise CardError(f"--append: {out} does not name the SHA-256 of {checkpoint}: the card of "
                        f"another checkpoint (or an older version of it)")
    evaluation, eval_path = load_evaluations(eval_path)
    policy = match_policy(evaluation, checkpoint, eval_path)
    now = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    # in a card of the reader's order the section is one of its results (a level-3 heading)
    level = 3 if f"\n{TRAINED}\n" in card else 2
    lines = evaluation_block(evaluation, policy, metadata, eval_path, title, level=level)
    lines.insert(2, f"Appended {now} by `{command}`.")
    lines.insert(3, "")
    return "\n" + "\n".join(lines) + "\n"


RESULTS = "## Results"
TRAINED = "## How it was trained and what it cost"  # `--append` puts new results before it


def how_to_run(checkpoint: Path, metadata: dict) -> list[str]:
    """The commands that run the checkpoint on the fleet and in the evaluator (under the fleet's
    default conflict rule beside plain PIBT)."""
    path = _repo_relative(str(checkpoint))
    lines = ["```bash",
             f"mapf-fleet up --checkpoint {path}            # a simulated fleet over ROS 2",
             f"mapf-fleet evaluate --checkpoint {path} heuristic --conflict-rule revert pibt_anchor --sizes 40",
             "```", ""]
    if metadata["algorithm"] == "dcc":
        lines += ["On a fleet, DCC robots exchange requests and replies with their neighbours each tick "
                  "(services `/robot_<i>/dcc_request`, `/robot_<i>/dcc_reply`).", ""]
    return lines


def add_section(card: str, section: str) -> str:
    """`card` with an evaluation `section` (from `append_evaluation`) added: before the training
    part of a card in the reader's order, so results stay together; at the end of an older card."""
    marker = f"\n{TRAINED}\n"
    if marker in card:
        head, _, tail = card.partition(marker)
        return head.rstrip("\n") + "\n" + section.rstrip("\n") + "\n" + marker + tail
    return card + section


NOTES_SUFFIX = ".notes.md"
ASSESSMENT = "## Assessment"


def default_notes(out: str | Path) -> Path:
    """The hand-written notes of the card `out` (models/X.md -> models/X.notes.md)."""
    out = Path(out)
    return out.with_name(out.stem + NOTES_SUFFIX)


def notes_block(notes: str | Path, card_dir: Path) -> list[str]:
    """The card's hand-written assessment: the notes file verbatim under its own heading, so a
    card is generated whole and a regeneration keeps what people wrote."""
    notes = Path(notes)
    try:
        text = notes.read_text()
    except OSError as exc:
        raise CardError(f"--notes {notes}: {exc.strerror or exc}") from exc
    return ["", ASSESSMENT, "", f"<!-- hand-written in {_relative(notes, card_dir)}, included verbatim by "
            "`mapf-fleet card`: edit that file, not this section -->", "", text.strip()]


def build_card(checkpoint: str | Path, eval_path: str | Path, *, run_dir: str | Path | None = None,
               out: str | Path | None = None, curves: str | Path | None = None,
               command: str | None = None, compare: list[str | Path] | None = None,
               notes: str | Path | None = None) -> str:
    """The card's Markdown (and the curves PNG when `curves` is given); `compare`: other
    checkpoints of the same evaluation JSON to show side by side; `notes`: a Markdown file of
    hand-written assessment included verbatim after the header."""
    from mapf_fleet.models.checkpoint import CheckpointError, code_version, load_checkpoint

    checkpoint = Path(checkpoint)
    try:
        model, metadata = load_checkpoint(checkpoint)
    except CheckpointError as exc:
        raise CardError(f"--checkpoint: {exc}") from exc
    evaluation, eval_path = load_evaluations(eval_path)
    policy = match_policy(evaluation, checkpoint, eval_path)
    run = read_run_dir(run_dir, checkpoint, metadata) if run_dir is not None else None
    if curves is not None and (run is None or run.tb_dir is None):
        raise CardError(f"--curves {curves}: needs --run-dir with a tb/ folder of TensorBoard scalars"
                        + ("" if run is None else f" ({run.path}/tb is missing)"))
    card_dir = Path(out).parent if out is not None else Path.cwd()
    curriculum = metadata.get("curriculum") or {}
    summary = model_summary(model, metadata)
    steps = int(metadata["learner_steps"])
    # the update the run reached, when it trained on after this checkpoint (else None)
    run_updates = (run.result or {}).get("learner_updates") if run else None
    later_updates = run_updates if isinstance(run_updates, int) and run_updates > steps else None
    now = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")

    lines = [f"# Model card: {checkpoint.stem}", ""]
    lines.append(f"Generated {now} by `{command or 'mapf-fleet card'}`. Every figure below is read from "
                 f"`{checkpoint.name}`'s metadata, the evaluation JSON(s) `{eval_path.name}`"
                 + (", the training run directory" if run else "") + " or the paper's tables"
                 + (" (the assessment is hand-written)." if notes is not None else "."))
    if notes is not None:
        lines += notes_block(notes, card_dir)
    lines += ["", "## What it is", "", "| | |", "|---|---|"]
    setting = curriculum.get("setting")
    if isinstance(setting, (list, tuple)) and len(setting) == 2:
        setting_text = f"{setting[0]} agent{'s' if setting[0] != 1 else ''} on {setting[1]}x{setting[1]}"
    else:
        setting_text = "not recorded" if setting is None else str(setting)
    alpha_star = curriculum.get("alpha_star")
    if alpha_star is None and run and run.result:
        alpha_star = run.result.get("alpha_star")
    passed = curriculum.get("alpha_passed")
    dagger = dagger_record(metadata)
    if dagger is not None:  # a DAgger round has no stage-1 setting, alpha gate or alpha*
        training_rows = dagger_facts(dagger)
    else:
        training_rows = [
            ("curriculum setting reached (stage 1)", setting_text),
            ("alphas that passed the gate (stage 2)", "none" if not passed else ", ".join(f"{a:g}" for a in passed)),
            ("alpha* (stage 2)", _alpha_star_text(alpha_star, metadata.get("training_config") or {})),
        ]
    rankings = rankings_text(metadata)
    facts = [
        ("algorithm", metadata["algorithm"].upper()),
        ("network", f"preset `{summary['preset']}`, {summary['parameters']:,} parameters"
         + ("" if summary["observation"] == "paper"
            else f", observation `{summary['observation']}` (the paper's + cost-to-go channel)")),
        ("alpha (cooperation coefficient of this checkpoint)", f"{float(metadata['alpha']):g}"),
        ("curriculum stage", str(curriculum.get("stage", "not recorded"))),
        *training_rows,
        ("learner steps", f"{metadata['learner_steps']:,}"),
        *([] if rankings is None else [("ranking it runs with unless told otherwise (recorded)", rankings)]),
        ("observation padding / action order", f"{metadata['obs_padding']} / {', '.join(metadata['action_order'])}"),
        ("checkpoint written", str(metadata.get("created", "not recorded"))),
        ("code version of the checkpoint", _version_text(metadata.get("code_version"))),
        ("code that trained it (per training session)", _trained_with_text(metadata)),
        ("checkpoint SHA-256", f"`{_sha256(checkpoint)}`"),
    ]
    if curriculum.get("note"):
        facts.insert(3, ("note", str(curriculum["note"])))
    if run is not None:
        if run.checkpoint_in_run:
            facts.append(("in the run directory as", f"`checkpoints/{run.checkpoint_in_run}` (same bytes)"))
        if run.result:
            stop = str(run.result.get("stop_reason") or "–")
            if later_updates is not None:
                stop += f" (at update {later_updates:,}, after this checkpoint)"
            facts.append(("run stop reason", stop))
    lines += [f"| {k} | {v} |" for k, v in facts]
    lines += ["", "## How to run it", ""] + how_to_run(checkpoint, metadata)
    # The reader's order: what it is, how to run it, its results, then how it was trained and what
    # it cost. The training part is written first (it reads the run) and placed after the results.
    front, lines = lines, []

    lines += ["", "### Training configuration", ""]
    training_config = dict(metadata.get("training_config") or {})
    diff, closest, closest_note = training_config_diff(training_config)
    if closest:
        lines.append(f"Closest shipped config file: `{closest}` ({closest_note}). Train again with "
                     f"`mapf-fleet train --config {closest} ...`.")
    if diff:
        lines += ["", f"Fields that differ from the paper's recipe for {metadata['algorithm'].upper()} "
                  "(`preset: " + metadata["algorithm"] + "` in `mapf_fleet.training.config`):", "",
                  "| field | this run | paper |", "|---|---|---|"]
        lines += [f"| `{k}` | `{v!r}` | `{p!r}` |" for k, v, p in diff]
    elif not closest:
        lines.append("The checkpoint's training_config is not a full trainer configuration; as recorded:")
    lines += ["", "<details><summary>full training configuration (checkpoint metadata)</summary>", "",
              _yaml_block(training_config), "", "</details>"]

    lines += ["", "### Compute", ""]
    compute = compute_spent(run, metadata)
    if compute is None and dagger is not None:
        cpu = dagger.get("cpu_seconds")
        lines.append("DAgger: " + ("not recorded" if not isinstance(cpu, (int, float)) else
                     f"**{cpu / 3600:.2f} CPU-hours** measured to this checkpoint (process CPU time "
                     "of the driver and its workers: rollouts, LaCAM labelling, updates and the "
                     "held-out checks, `extra.dagger.cpu_seconds`)")
                     + ", on top of the compute of the checkpoint it started from (its own card).")
    elif compute is None:
        lines.append("Not recorded: no run directory given and the checkpoint holds no elapsed time.")
    elif compute.cpu_hours is None:
        lines.append(f"Wall time {compute.wall_seconds / 3600:.2f} h ({compute.source}); CPU-hours unknown: "
                     f"{compute.how}.")
    else:
        lines.append(f"**{compute.cpu_hours:.2f} CPU-hours** = wall time {compute.wall_seconds / 3600:.2f} h "
                     f"({compute.source}, summed over resumed sessions) x {compute.cpus} CPU(s) "
                     f"({compute.how}). CPUs reserved, not measured utilisation; "
                     + ("up to this checkpoint." if compute.source.startswith(CHECKPOINT_POINT)
                        else "the whole run, of which this checkpoint may be an intermediate point."))
    if compute is not None and not compute.source.startswith(CHECKPOINT_POINT) and later_updates is not None:
        lines.append(f"This checkpoint is an intermediate point (update {steps:,}) of a "
                     f"run that went on to update {later_updates:,}: the figures here are the whole run's, "
                     "an upper bound of the compute up to this checkpoint, which it does not record.")
    if compute is not None and compute.measured_cpu_seconds is not None:
        measured = (f"Measured: **{compute.measured_cpu_seconds / 3600:.2f} CPU-hours** of process CPU "
                    "time (the trainer's process and its actor processes, `counters.cpu_seconds`; "
                    "Ray's daemons not included)")
        if compute.measured_from_elapsed > 0:
            measured += (f", over the last {(compute.wall_seconds - compute.measured_from_elapsed) / 3600:.2f} h "
                         f"of the run's wall time only: the first {compute.measured_from_elapsed / 3600:.2f} h "
                         "ran before the trainer measured CPU time")
        lines.append(measured + ".")
    counters = (run.result or {}).get("counters") if run else None
    if isinstance(counters, dict):
        parts = [f"{counters[k]:,} {k.replace('_', ' ')}" for k in ("episodes", "env_steps", "agent_steps")
                 if isinstance(counters.get(k), int)]
        if parts:
            lines.append(f"Run totals (result.json): {', '.join(parts)}.")
    for note in (run.notes if run else []):
        lines.append(f"Note: {note}.")

    lines += ["", "### Training curves", ""]
    if curves is not None:
        scalars, cut = scalars_up_to(read_scalars(run.tb_dir), steps)
        plotted = plot_curves(scalars, Path(curves), f"{checkpoint.stem}: {metadata['algorithm'].upper()}")
        lines.append(f"![training curves]({_relative(Path(curves), card_dir)})")
        lines.append("")
        upto = (f"; up to this checkpoint's update {steps:,}, the run logged on to "
                f"update {cut:,}" if cut is not None else "")
        lines.append(f"From the TensorBoard scalars of the run directory (x axis: learner updates{upto}). "
                     "Last values:")
        lines += ["", "| scalar | last value | at update |", "|---|---:|---:|"]
        for tag in CURVE_TAGS:
            if scalars.get(tag):
                step, value = scalars[tag][-1]
                lines.append(f"| `{tag}` | {value:.4g} | {step:,} |")
        missing = [t for t in CURVE_TAGS if t not in plotted]
        if missing:
            lines.append(f"\nNot logged in this run: {', '.join(f'`{t}`' for t in missing)}.")
    else:
        lines.append("No curves: the card was written without `--run-dir` and `--curves`.")

    trained, lines = lines, front
    lines += [RESULTS, ""] + evaluation_block(evaluation, policy, metadata, eval_path,
                                                  "Evaluation (the paper's protocol)", level=3)
    lines += [TRAINED, ""] + trained[1:] + [""]
    if compare:
        others = []
        for item in map(str, compare):
            path_text, _, run_text = item.partition("=")
            path, other_run_dir = Path(path_text), (Path(run_text) if run_text else None)
            try:
                meta = load_checkpoint(path)[1]
            except (CheckpointError, FileNotFoundError) as exc:
                raise CardError(f"--compare {path}: {exc}") from exc
            other_run = read_run_dir(other_run_dir, path, meta) if other_run_dir else None
            others.append((path, meta, other_run))
        lines += comparison_section(evaluation, policy, metadata, eval_path, others, run, level=3)
    lines += ["## Versions", "",
              f"- card written {now} with code {_version_text(code_version())}",
              f"- checkpoint written {metadata.get('created', '?')} with code {_version_text(metadata.get('code_version'))}",
              ""]
    return "\n".join(lines)
