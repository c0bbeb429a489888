#!/usr/bin/env bash
# Set up (idempotent, seconds when nothing changed) and run one of the project's jobs:
#   bash scripts/run.sh main [args]   the main job: `mapf-fleet up` (8 simulated robots over ROS 2)
#   bash scripts/run.sh test [args]   the full pytest suite (extra args go to pytest)
#   bash scripts/run.sh exec CMD ...  any command inside the project's environment
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
job="${1:-}"
[ $# -gt 0 ] && shift

case "$job" in
  main|test|exec) ;;
  *) echo "usage: bash scripts/run.sh {main|test|exec CMD...} [args]" >&2; exit 2 ;;
esac

bash "$REPO/scripts/setup.sh"
# shellcheck source=env.sh
source "$REPO/scripts/env.sh"
cd "$REPO"

case "$job" in
  main) exec mapf-fleet up "$@" ;;
  test) exec python -m pytest "$@" ;;
  exec) exec "$@" ;;
esac
