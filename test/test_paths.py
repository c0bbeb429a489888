"""mapf_fleet.paths: data is found in the share directory of an install first (or through the
ament index), the checkout second. The install into a temporary prefix is in
test_installed_package.py."""

import os
from pathlib import Path

import pytest

from mapf_fleet import paths

REPO = Path(__file__).resolve().parents[1]


def _share(prefix: Path, *files: str) -> Path:
    share = prefix / "share" / "mapf_fleet"
    share.mkdir(parents=True)
    (share / "package.xml").write_text("<package/>")
    for name in files:
        (share / name).parent.mkdir(parents=True, exist_ok=True)
        (share / name).write_text(name)
    return share


def test_checkout_data_is_found():
    found = paths.data_path("config", "evaluation", "paper.yaml")
    assert found.is_file()
    assert found.read_bytes() == (REPO / "config" / "evaluation" / "paper.yaml").read_bytes()
    assert paths.data_path("models", "default.pt").resolve() == (REPO / "models" / "default.pt").resolve()


def test_share_directory_first_then_the_checkout(tmp_path, monkeypatch):
    share = _share(tmp_path, "models/default.pt")
    monkeypatch.setattr(paths, "_install_share_dir", lambda: share)
    assert paths.data_roots()[0] == share
    assert paths.data_path("models", "default.pt") == (share / "models" / "default.pt").resolve()
    assert paths.data_root("models") == share
    # absent from the share directory: the checkout's copy
    assert paths.data_path("config", "evaluation", "paper.yaml") == \
        (REPO / "config" / "evaluation" / "paper.yaml").resolve()
    # absent everywhere: where it would be installed
    assert paths.data_path("models", "none.pt") == share / "models" / "none.pt"


def test_ament_index_is_used(tmp_path, monkeypatch):
    pytest.importorskip("ament_index_python")
    share = _share(tmp_path, "config/fleet/fleet.yaml")
    marker = tmp_path / "share" / "ament_index" / "resource_index" / "packages" / "mapf_fleet"
    marker.parent.mkdir(parents=True)
    marker.write_text("")
    monkeypatch.setattr(paths, "_install_share_dir", lambda: None)
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(tmp_path))
    assert paths.share_dirs()[0] == share
    assert paths.data_path("config", "fleet", "fleet.yaml") == (share / "config/fleet/fleet.yaml").resolve()
    monkeypatch.delenv("AMENT_PREFIX_PATH")  # no index: no error, the other places
    assert share not in paths.share_dirs()


def test_cache_is_the_checkouts_unless_installed(tmp_path, monkeypatch):
    assert paths.cache_dir("evaluation") == REPO / "cache" / "evaluation"
    monkeypatch.setattr(paths, "is_checkout", lambda root=None: False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert paths.cache_dir("evaluation") == tmp_path / "mapf_fleet" / "evaluation"


def test_published_test_sets_stay_beside_the_checkout():
    from mapf_fleet.evaluation.protocol import DEFAULT_TESTSETS

    assert DEFAULT_TESTSETS == REPO.parent / "shared" / "data" / "dhc_testsets"


def test_no_module_finds_data_relative_to_its_own_file():
    """Every data lookup goes through mapf_fleet.paths (an installed package has no
    ../models or ../config beside its modules)."""
    offenders = []
    for module in (REPO / "mapf_fleet").rglob("*.py"):
        if module.name == "paths.py":
            continue
        for number, line in enumerate(module.read_text().splitlines(), 1):
            if "__file__" in line and ("parents[" in line or ".parent.parent" in line):
                offenders.append(f"{module.relative_to(REPO)}:{number}: {line.strip()}")
    assert not offenders, "\n".join(offenders)
