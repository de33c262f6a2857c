"""Shared scanner model and small protocols for the trajectory tests."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from recon.config import ScanProtocol, load_config, load_protocol
from trajectories.config import ScannerConfig
from trajectories.model import ScannerModel

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
