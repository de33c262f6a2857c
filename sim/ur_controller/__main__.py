"""``python -m sim.ur_controller``: the fake controller's process (sim.ur_controller.server)."""

import sys

from sim.ur_controller.server import main

sys.exit(main())
