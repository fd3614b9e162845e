"""``l1flow-rl`` with the point-mass double registered, for tests that run the real command in a
process of its own: ``PYTHONPATH=tests python -m doubles.cli train task.simulator=point_mass ...``."""

import sys

import doubles.point_mass  # noqa: F401  registers the simulator and its expert, as a user's package would
from l1flow_rl.commands.cli import main

if __name__ == "__main__":
    sys.exit(main())
