"""Where mapf_fleet finds its own data (checkpoints in `models/`, `config/...`, `launch/`).

`setup.py` installs the data under `<prefix>/share/mapf_fleet/` (colcon, `pip install .`), so a
lookup relative to the source tree fails in an installed package. Every module finds data here:
the share directory of the install this module was imported from, then the ament index
(`get_package_share_directory`, when `ament_index_python` is importable and knows the package),
then `<sys.prefix>/share/mapf_fleet`, and the source tree (a checkout) last. The first root that
holds the asked-for path wins, so a share directory missing a new folder still falls back to the
checkout. No torch or rclpy here: `demo` and `evaluate` import it.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

PACKAGE = "mapf_fleet"
# The directory above the mapf_fleet package: the checkout when run from source (pip -e), the
# site-packages directory in an installed package.
SOURCE_ROOT = Path(__file__).resolve().parent.parent
# The DHC authors' published test sets live beside the checkout, in ../shared (not installed).
DEFAULT_TESTSETS = SOURCE_ROOT.parent / "shared" / "data" / "dhc_testsets"


def _is_share_dir(path: Path) -> bool:
    return (path / "package.xml").is_file()


def _install_share_dir() -> Path | None:
    """<prefix>/share/mapf_fleet of the install this file belongs to
    (<prefix>/lib/pythonX.Y/site-packages/mapf_fleet/paths.py), found by walking up."""
    for parent in Path(__file__).resolve().parents:
        candidate = parent / "share" / PACKAGE
        if _is_share_dir(candidate):
            return candidate
    return None


def _ament_share_dir() -> Path | None:
    try:
        from ament_index_python.packages import get_package_share_directory
    except ImportError:
        return None
    try:
        return Path(get_package_share_directory(PACKAGE))
    except (LookupError, OSError, ValueError):  # not in the index, or AMENT_PREFIX_PATH unset
        return None


def is_checkout(root: Path = SOURCE_ROOT) -> bool:
    """True when `root` is a source checkout of the package (setup.py beside package.xml)."""
    return (root / "setup.py").is_file() and (root / "package.xml").is_file()


def share_dirs() -> list[Path]:
    """Share directories of mapf_fleet, most specific first, without duplicates."""
    found: list[Path] = []
    for candidate in (_install_share_dir(), _ament_share_dir(),
                      Path(sys.prefix) / "share" / PACKAGE):
        if candidate is not None and _is_share_dir(candidate) and candidate not in found:
            found.append(candidate)
    return found


def data_roots() -> list[Path]:
    """Where data is looked up, in order: the share directories, then the checkout."""
    roots = share_dirs()
    if is_checkout() and SOURCE_ROOT not in roots:
        roots.append(SOURCE_ROOT)
    return roots


def data_root(*parts: str | os.PathLike) -> Path:
    """The first root of `data_roots()` that holds `parts` (e.g. "models"), else the first root
    (where the data would be installed), else the source tree."""
    roots = data_roots()
    for root in roots:
        if root.joinpath(*parts).exists():
            return root
    return roots[0] if roots else SOURCE_ROOT


def data_path(*parts: str | os.PathLike) -> Path:
    """`config/evaluation/paper.yaml` and the like: `data_path("config", "evaluation",
    "paper.yaml")`, from the first root that holds it (see `data_root`). Symbolic links are
    resolved (the project's venv links its share directory into the checkout), so paths read
    and recorded are the files' own."""
    path = data_root(*parts).joinpath(*parts)
    return path.resolve() if path.exists() else path


def cache_dir(*parts: str) -> Path:
    """A folder for caches: `cache/` of the checkout when run from source (as before), else
    `$XDG_CACHE_HOME/mapf_fleet` (~/.cache/mapf_fleet): an install prefix may be read-only."""
    if is_checkout():
        base = SOURCE_ROOT / "cache"
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / PACKAGE
    return base.joinpath(*parts)
