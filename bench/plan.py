"""Benchmark: planning the clinical knee protocols on the default scanner.

For the 360- and 180-degree reverse spirals (360 views each): planning wall time (best of
three, the scanner model built once), the scan's duration against its lower bound (the slowest
axis covering its path at its velocity and acceleration limits, rest to rest per sweep), the
smallest clearance along the whole motion against the margin, the worst pose error of any
view, and the number of trajectory samples that break a position, velocity or acceleration
limit (counted here from the plan's own samples, not taken from the planner).

Prints one JSON object ``{"protocols": [...]}``. Usage: ``python bench/plan.py``.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from recon.config import load_config, load_protocol  # noqa: E402
from trajectories.config import ScannerConfig  # noqa: E402
from trajectories.model import ScannerModel  # noqa: E402
from trajectories.plan import Plan, plan_scan  # noqa: E402

PROTOCOLS = ("knee_reverse_spiral_360", "knee_reverse_spiral_180")


ROUNDING = 1e-6
"""Excess (in the joint's unit: mm, deg, /s, /s^2) counted as floating-point rounding."""


def limit_violations(plan: Plan, model: ScannerModel) -> int:
    """Samples (joint x time) beyond a position, velocity or acceleration limit by more than
    :data:`ROUNDING` (a move ending exactly on a limit lands within 1e-13 of it)."""
    lower, upper, vmax, amax = (
        model.to_units(np.asarray(x)[None])[0]
        for x in (
            model.limits.lower,
            model.limits.upper,
            model.limits.velocity,
            model.limits.acceleration,
        )
    )
    return int(
        np.count_nonzero(plan.q < lower - ROUNDING)
        + np.count_nonzero(plan.q > upper + ROUNDING)
        + np.count_nonzero(np.abs(plan.qd) > vmax + ROUNDING)
        + np.count_nonzero(np.abs(plan.qdd) > amax + ROUNDING)
    )


def main() -> None:
    model = ScannerModel(load_config(ROOT / "configs" / "scanner.yaml", ScannerConfig))
    entries = []
    for name in PROTOCOLS:
        protocol = load_protocol(ROOT / "configs" / "protocols" / f"{name}.yaml")
        seconds = []
        for _ in range(3):
            start = time.perf_counter()
            plan = plan_scan(model, protocol)
            seconds.append(time.perf_counter() - start)
        entries.append(
            {
                "protocol": name,
                "views": len(plan.desired),
                "plan_s": round(min(seconds), 3),
                "duration_s": round(plan.scan_duration_s, 3),
                "total_duration_s": round(plan.duration_s, 3),
                "duration_lower_bound_s": round(plan.lower_bound_s, 3),
                "duration_ratio": round(plan.scan_duration_s / plan.lower_bound_s, 4),
                "min_clearance_mm": round(plan.min_clearance_mm, 2),
                "min_clearance_at": plan.min_clearance_at,
                "clearance_margin_mm": plan.clearance_margin_mm,
                "max_pose_error_mm": float(plan.pose_error_mm.max()),
                "max_pose_error_deg": float(plan.pose_error_deg.max()),
                "limit_violations": limit_violations(plan, model),
                "trajectory_samples": int(plan.q.size),
            }
        )
    print(json.dumps({"benchmark": "plan", "protocols": entries}, indent=1))


if __name__ == "__main__":
    main()
