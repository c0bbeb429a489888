"""`mapf-fleet card`: a checkpoint's model card in Markdown.

    mapf-fleet card --checkpoint models/X.pt --eval X_eval.json [--run-dir RUN]
        --out models/X.md [--curves models/X_curves.png]

Every number of the card comes from one of these files: the checkpoint's metadata, the JSON of
`mapf-fleet evaluate` (which records its own command line, so the card can show how to re-run
it), the run directory of the trainer (config.yaml, result.json, train_state.pt, tb/) and the
paper's tables (`paper_results`). Inputs that do not belong together (an evaluation of another
checkpoint, a run directory of another algorithm or network) raise `CardError`.

One module per job, each readable on its own:

- `inputs`: the evaluation JSON(s), which row is the checkpoint's, the run directory; `CardError`
- `facts`: what the checkpoint is (network, training config against the paper's, alpha*, versions)
- `compute`: what it cost (wall time x reserved CPUs, measured CPU time)
- `curves`: the TensorBoard scalars and their PNG
- `tables`: the results beside the references and the paper, the side-by-side table
- `card`: `build_card`, `append_evaluation` and `add_section`: the sections in the reader's order
  (what it is, how to run it, results, how it was trained and what it cost, versions)
- `command`: `build_parser` and `main` (`mapf-fleet card`)

The names below are re-exported so `from mapf_fleet.evaluation.model_card import X` keeps working.
"""

from .card import add_section, append_evaluation, build_card
from .command import build_parser, main
from .compute import CHECKPOINT_POINT, Compute, compute_spent, uncounted_warm_start_seconds
from .curves import CURVE_TAGS, plot_curves, read_scalars, scalars_up_to
from .facts import _alpha_star_text, model_summary, training_config_diff
from .inputs import (CardError, EvalFiles, RunInfo, load_evaluation, load_evaluations, match_policy,
                     read_run_dir)
from .tables import (CARD_METRICS, PLAIN_PIBT, _against_plain_pibt, comparison_section,
                     evaluation_block, evaluation_section)

__all__ = [
    "CARD_METRICS", "CHECKPOINT_POINT", "CURVE_TAGS", "PLAIN_PIBT", "CardError", "Compute",
    "EvalFiles", "RunInfo", "add_section", "append_evaluation", "build_card", "build_parser", "comparison_section",
    "compute_spent", "evaluation_block", "evaluation_section",
    "load_evaluation", "load_evaluations", "main", "match_policy", "model_summary", "plot_curves",
    "read_run_dir", "read_scalars", "scalars_up_to", "training_config_diff",
    "uncounted_warm_start_seconds", "_against_plain_pibt", "_alpha_star_text",
]
