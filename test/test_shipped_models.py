"""What `models/` ships: every checkpoint loads with this code, stays under the issue's 10 MB, has
its model card naming its exact bytes (SHA-256) and the evaluation files the card was built from,
and `models/default.pt` (the main job's policy) points at one of them. Superseded checkpoints live
in `models/archive/` under the same rules, so the evidence behind the tables of README.md and docs/results.md still loads."""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

import pytest

MODELS = Path(__file__).resolve().parents[1] / "models"
SHIPPED = sorted(p for p in MODELS.glob("*.pt") if not p.is_symlink())
ARCHIVED = sorted((MODELS / "archive").glob("*.pt"))


def test_models_ships_checkpoints():
    assert SHIPPED, f"no checkpoint in {MODELS}"


@pytest.mark.parametrize("path", SHIPPED + ARCHIVED,
                         ids=[p.stem for p in SHIPPED] + [f"archive/{p.stem}" for p in ARCHIVED])
def test_shipped_checkpoint_loads_and_has_its_card(path):
    from mapf_fleet.models import load_checkpoint

    assert path.stat().st_size < 10 * 1024 * 1024, f"{path.name}: {path.stat().st_size} bytes"
    model, metadata = load_checkpoint(path)
    assert metadata["algorithm"] in ("dhc", "dcc")
    card = path.with_suffix(".md")
    assert card.is_file(), f"{path.name} has no model card {card.name}"
    text = card.read_text()
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    assert f"| checkpoint SHA-256 | `{digest}` |" in text, f"{card.name} describes other bytes than {path.name}"
    command = re.search(r"by `(mapf-fleet card [^`]*)`", text)
    assert command, f"{card.name}: no generating command"
    evals = re.search(r"--eval ((?:\S+\.json ?)+)", command.group(1)).group(1).split()
    for name in evals:  # the evaluations the card's tables come from are shipped beside it
        assert (MODELS.parent / name).is_file(), f"{card.name} reads {name}, which is not in the repository"
    curves = re.search(r"--curves (\S+)", command.group(1))
    if curves:
        assert (MODELS.parent / curves.group(1)).is_file()


def test_default_checkpoint_is_a_shipped_one():
    default = MODELS / "default.pt"
    assert default.is_symlink() and default.resolve().parent == MODELS
    assert default.resolve() in SHIPPED


def test_archived_cards_say_so_and_point_into_the_archive():
    for path in ARCHIVED:
        text = path.with_suffix(".md").read_text()
        assert "**Archived**" in text, path.name
        assert f"--checkpoint models/archive/{path.name}" in text, path.name
