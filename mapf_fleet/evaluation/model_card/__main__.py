"""`python -m mapf_fleet.evaluation.model_card` = `mapf-fleet card`."""

import sys

from .command import main

sys.exit(main())
