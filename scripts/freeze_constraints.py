"""Write constraints.txt: the exact version of every PyPI distribution in the current venv.

Why not `pip freeze`: the ROS wheels register egg-info names (rclpy, std_msgs, ...) that PyPI
does not serve, so a frozen list would not install. Only dist-info distributions are kept.
Run inside the project's environment: `bash scripts/run.sh exec python scripts/freeze_constraints.py`.
"""

from __future__ import annotations

import importlib.metadata as metadata
from pathlib import Path

HEADER = """\
# Exact versions of every PyPI distribution in the project's venv (direct and transitive),
# so a fresh set-up resolves to the tested set. Used as: pip install -r requirements.txt -c constraints.txt
# Regenerate after changing requirements.txt: bash scripts/run.sh exec python scripts/freeze_constraints.py
"""
SKIPPED = {"mapf-fleet", "pip"}  # the project itself (editable) and the installer


def pinned_distributions() -> list[str]:
    pins: dict[str, str] = {}
    for dist in metadata.distributions():
        if not str(getattr(dist, "_path", "")).endswith(".dist-info"):
            continue  # egg-info metadata written by ROS wheels: not a PyPI name
        name = dist.metadata["Name"]
        key = name.lower().replace("_", "-")
        if key in SKIPPED:
            continue
        # drop local labels such as +cpu: "torch==2.13.0" still matches the local CPU wheel
        pins[key] = f"{name}=={dist.version.split('+')[0]}"
    return [pins[key] for key in sorted(pins)]


def main() -> int:
    target = Path(__file__).resolve().parent.parent / "constraints.txt"
    target.write_text(HEADER + "\n".join(pinned_distributions()) + "\n")
    print(f"wrote {target}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
