"""DHC and DCC networks (batched and per-robot steps), checkpoints and the acting policy.

See docs/architecture.md for the contract; `dhc.py` and `dcc.py` document one step in full.
"""

from .checkpoint import (
    CheckpointError, build_model, load_checkpoint, read_checkpoint, save_checkpoint,
    with_observation,
)
from .comm import dhc_partners, fov_neighbours, relative_position_index
from .common import StepOutput
from .config import ModelConfig, paper_config, small_config
from .dcc import DCCNetwork
from .dhc import DHCNetwork
from .policy import LearnedPolicy

__all__ = [
    "CheckpointError", "DCCNetwork", "DHCNetwork", "LearnedPolicy", "ModelConfig", "StepOutput",
    "build_model", "dhc_partners", "fov_neighbours", "load_checkpoint", "paper_config",
    "read_checkpoint", "relative_position_index", "save_checkpoint", "small_config",
    "with_observation",
]
