"""Plan the clinical knee protocol on the scanner: inverse kinematics for both arms, the rotary
and the lift, clearance along the whole motion, time-optimal timing.

Prints the plan's summary (views, duration, smallest clearance and where it occurs).
"""

from pathlib import Path

from recon.config import load_config, load_protocol
from trajectories import ScannerConfig, ScannerModel, plan_scan

configs = Path(__file__).resolve().parent.parent / "configs"
scanner = ScannerModel(load_config(configs / "scanner.yaml", ScannerConfig))
plan = plan_scan(scanner, load_protocol(configs / "protocols" / "knee_reverse_spiral_360.yaml"))
summary = plan.summary()
pair = " and ".join(summary["min_clearance_at"]["pair"])
print(
    f"{summary['views']} views in {summary['duration_s']:.1f} s; smallest clearance "
    f"{summary['min_clearance_mm']:.1f} mm between {pair}"
)
