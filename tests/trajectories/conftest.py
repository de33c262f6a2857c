"""Shared scanner model and small protocols for the trajectory tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from recon.config import ScanProtocol, load_config, load_protocol
from trajectories.config import ScannerConfig
from trajectories.model import ScannerModel
from trajectories.move import park_pose

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def scanner_config(**changes) -> ScannerConfig:
    """configs/scanner.yaml with top-level sections replaced (nested dicts merged one level)."""
    data = yaml.safe_load((CONFIGS / "scanner.yaml").read_text(encoding="utf-8"))
    for key, value in changes.items():
        if isinstance(value, dict) and isinstance(data.get(key), dict):
            data[key] = {**data[key], **value}
        else:
            data[key] = value
    return ScannerConfig.model_validate(data)


def small_protocol(name: str = "demo_knee", **orbit) -> ScanProtocol:
    protocol = load_protocol(CONFIGS / "protocols" / f"{name}.yaml")
    return protocol.model_copy(update={"orbit": protocol.orbit.model_copy(update=orbit)})


@pytest.fixture(scope="session")
def scanner() -> ScannerModel:
    return ScannerModel(load_config(CONFIGS / "scanner.yaml", ScannerConfig))


def random_rest_pose(
    model: ScannerModel,
    rng: np.random.Generator,
    rotary_deg: float = 180.0,
    lift_mm: float = 400.0,
    arm_deg: float = 20.0,
) -> np.ndarray:
    """A rest pose (plan units) where an interrupted session may leave the scanner: rotary
    within ``rotary_deg`` of 0 either way, lift in its lowest ``lift_mm``, every arm joint
    within ``arm_deg`` of its home posture; within limits and clear of everything by the
    margin (drawn again until it is)."""
    margin_m = model.config.obstacles.clearance_margin_mm / 1000.0
    while True:
        q = park_pose(model)
        q[0] = rng.uniform(-rotary_deg, rotary_deg)
        q[1] = rng.uniform(0.0, lift_mm)
        q[2:] += rng.uniform(-arm_deg, arm_deg, 12)
        if model.clearance(model.from_units(q))[0] >= margin_m:
            return q
