"""Backends, panels and phantoms found by name (scanner.registry): the scanner opens the
simulated backend without importing the simulator."""

from __future__ import annotations

import subprocess
import sys

import pytest
from pydantic import ValidationError

from scanner import registry
from scanner.backends import URBackendSpec

UR = {
    "source_host": "127.0.0.2",
    "detector_host": "127.0.0.3",
    "stage_port": "/dev/null",
    "generator_port": "/dev/null",
}


def test_the_installed_kinds_are_found_by_name() -> None:
    assert registry.names("backend") == ["sim", "ur"]
    assert registry.names("panel") == ["sim"]
    assert registry.names("phantom") == ["bb", "knee", "tka"]
    assert registry.backend_kind("sim").calibrate_panel is not None
    assert registry.backend_kind("ur").calibrate_panel is None  # its maps come from a folder


def test_an_unknown_name_is_refused_naming_the_registered_ones() -> None:
    with pytest.raises(ValueError, match=r"backend must be one of \['sim', 'ur'\], got 'xyz'"):
        registry.backend_kind("xyz")
    with pytest.raises(ValueError, match=r"phantom must be one of \['bb', 'knee', 'tka'\]"):
        registry.phantom_kind("ankle")


def test_the_ur_backends_panel_config_is_checked_by_its_kind() -> None:
    spec = URBackendSpec(**UR, simulated_panel={"seed": 7})
    assert spec.simulated_panel["seed"] == 7 and "vibration" in spec.simulated_panel  # complete
    with pytest.raises(ValidationError, match="simulated_panel"):
        URBackendSpec(**UR, simulated_panel={"seed": 7, "sway_mm": 1.0})
    with pytest.raises(ValidationError, match=r"panel must be one of \['sim'\], got 'flat'"):
        URBackendSpec(**UR, detector="flat")
    assert URBackendSpec(**UR, detector="gige", gige_device="panel-1").simulated_panel == {}


def test_the_scanner_runs_a_session_module_without_the_simulator_loaded() -> None:
    """Importing the session, the UR backend and the registry loads no simulator module: only
    a look-up by name does."""
    code = (
        "import sys, scanner.session, scanner.backends, scanner.detector_calibration; "
        "print(sorted(m for m in sys.modules if m == 'sim' or m.startswith('sim.')))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert out.stdout.strip() == "[]"
