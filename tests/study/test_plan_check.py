"""study.jobs.check_is_plan: a scan's planned views are its protocol's orbit to within the
plan's own precision, and a message says by how much they are not."""

from __future__ import annotations

import numpy as np
import pytest

from configs import CONFIGS
from recon.config import load_protocol
from recon.geometry import Geometry
from study.jobs import PLAN_TOLERANCE_MM, check_is_plan


def _shifted(geometry: Geometry, view: int, shift_mm: float) -> Geometry:
    T = np.eye(4)
    T[0, 3] = shift_mm
    return Geometry([v.transformed(T) if k == view else v for k, v in enumerate(geometry)])


def test_the_plans_own_precision_passes_and_a_real_difference_is_measured(tmp_path):
    protocol = load_protocol(CONFIGS / "protocols" / "demo_knee.yaml")
    nominal = protocol.orbit.geometry(protocol.detector)
    # cbct scan's planned_geometry.xml lies 5.4e-6 mm from the nominal orbit (IK and FK)
    check_is_plan(_shifted(nominal, 7, 5.4e-6), protocol, tmp_path / "planned.xml")
    apart = 20 * PLAN_TOLERANCE_MM
    with pytest.raises(ValueError, match=r"view 7 lies 0\.02 mm from it .* tolerance 0\.001 mm"):
        check_is_plan(_shifted(nominal, 7, apart), protocol, tmp_path / "planned.xml")
    with pytest.raises(ValueError, match="plans 180 of 256 x 256"):
        check_is_plan(nominal[:90], protocol, tmp_path / "planned.xml")
