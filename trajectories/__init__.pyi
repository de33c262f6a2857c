"""``trajectories``'s public names for type checkers and IDEs (they load lazily: __init__.py)."""

from trajectories.config import ScannerConfig as ScannerConfig
from trajectories.model import ScannerModel as ScannerModel
from trajectories.move import JointMove as JointMove
from trajectories.move import park_pose as park_pose
from trajectories.move import plan_move as plan_move
from trajectories.plan import Plan as Plan
from trajectories.plan import plan_scan as plan_scan
