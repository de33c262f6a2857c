"""Backends, panels and phantoms by name: the one registry a session finds its devices in.

A backend kind is a config type and what opens its devices; a panel kind is what the UR
backend's ``detector`` names besides the GigE Vision panel; a phantom kind is a phantom config
type and the subject a simulated panel sees through it. Each kind registers itself when its
module is imported; the modules are named by the ``dualarm_cbct.backends`` entry points of the
installed package (``ur``: :mod:`scanner.backends`; ``sim``: :mod:`study.simulator`, the simulator's
backend, its panel and its phantoms), loaded at the first look-up. So the scanner finds the
simulator by name and imports none of it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from pydantic import BaseModel

from recon.geometry import DetectorSpec, View
from scanner.corrections import PanelMaps
from scanner.hardware import Backend, Clock, Detector, Technique, XrayGenerator
from trajectories.model import ScannerModel

if TYPE_CHECKING:
    from scanner.inputs import SessionInputs

ENTRY_POINTS = "dualarm_cbct.backends"
"""The entry-point group naming the modules that register kinds."""

Subject = Callable[[View, float], np.ndarray]
"""What a simulated panel images: line integrals (unitless) through a view at a time, s."""


def nothing_in_the_beam(panel: DetectorSpec) -> Subject:
    """Zero line integrals on every pixel of ``panel`` at any time (a panel calibrated, or a
    scanner that only moves)."""
    clear = np.zeros((panel.rows, panel.cols))
    return lambda _view, _t_s=0.0: clear


@dataclass(frozen=True)
class Rig:
    """What a backend's devices are opened for.

    Attributes:
        model: the scanner's kinematic model.
        start_q: where the simulated joints stand at the start (the plan's joint units).
        panel: the panel's read-out (rows, cols, pitch).
        sdd_mm: source-to-detector distance, mm.
        subject: what a simulated panel images (a hardware panel images what is there).
        on_generator_sent: hears every command sent to the generator, with its
            ``time.monotonic()``.
    """

    model: ScannerModel
    start_q: np.ndarray
    panel: DetectorSpec
    sdd_mm: float
    subject: Subject
    on_generator_sent: Callable[[str, float], None] | None = None


class Truth(Protocol):
    """What a simulated scanner knows and hardware does not."""

    def view_matrix(self) -> np.ndarray:
        """The 3x4 projection matrix the last view read was truly taken through."""
        ...

    def body_poses(self) -> dict[str, np.ndarray] | None:
        """Each moving body's 4x4 pose at the last view read (None: a still subject)."""
        ...

    def events(self) -> list[tuple[int, float, str, str]]:
        """The ordered device log: (sequence, virtual time s, device, event)."""
        ...


Opened = tuple[Backend, "Truth | None"]


@dataclass(frozen=True)
class BackendKind:
    """A backend: its config type and what opens its devices (not yet connected).

    Attributes:
        spec: the config type (``configs/backends/<name>.yaml``).
        open: the devices of a config for a rig, and the truth when simulated.
        calibrate_panel: the panel's maps made at a session's start, when the config names no
            ``detector_maps`` folder (None: such a config is refused).
        resumed: the config a resumed session runs on, and what to tell the operator about
            the change (e.g. injected faults not injected again).
    """

    spec: type[BaseModel]
    open: Callable[[Any, Rig], Opened]
    calibrate_panel: Callable[[Any, Rig, Technique], PanelMaps] | None = None
    resumed: Callable[[Any], tuple[Any, str | None]] = lambda spec: (spec, None)


@dataclass(frozen=True)
class PanelKind:
    """A panel for a backend whose own panel is not there: its config type, and what opens it
    from that config, the rig, the arms' measured joints, the clock and the generator's
    driver (the panel and the generator the scan then drives)."""

    config: type[BaseModel]
    open: Callable[
        [Any, Rig, Callable[[], np.ndarray], Clock, XrayGenerator],
        tuple[Detector, XrayGenerator],
    ]


@dataclass(frozen=True)
class PhantomKind:
    """A phantom: its config type, and the subject a simulated panel sees through it over a
    scan of the session's inputs (``say`` tells the long work; the scan lasts ``scan_s``)."""

    spec: type[BaseModel]
    subject: Callable[[SessionInputs, Callable[[str], None], float], Subject]


_KINDS: dict[str, dict[str, Any]] = {"backend": {}, "panel": {}, "phantom": {}}
_loaded = False


def register_backend(name: str, kind: BackendKind) -> None:
    """Make ``kind`` the backend called ``name``."""
    _KINDS["backend"][name] = kind


def register_panel(name: str, kind: PanelKind) -> None:
    """Make ``kind`` the panel called ``name``."""
    _KINDS["panel"][name] = kind


def register_phantom(name: str, kind: PhantomKind) -> None:
    """Make ``kind`` the phantom called ``name``."""
    _KINDS["phantom"][name] = kind


def names(what: str) -> list[str]:
    """The registered names of ``what`` (``backend``, ``panel`` or ``phantom``), sorted."""
    _load()
    return sorted(_KINDS[what])


def backend_kind(name: str) -> BackendKind:
    """The backend called ``name``; raises naming the registered ones."""
    return _find("backend", name)


def panel_kind(name: str) -> PanelKind:
    """The panel called ``name``; raises naming the registered ones."""
    return _find("panel", name)


def phantom_kind(name: str) -> PhantomKind:
    """The phantom called ``name``; raises naming the registered ones."""
    return _find("phantom", name)


def _find(what: str, name: str) -> Any:
    _load()
    if name not in _KINDS[what]:
        raise ValueError(
            f"{what} must be one of {sorted(_KINDS[what])}, got {name!r} (kinds register through "
            f"the {ENTRY_POINTS} entry points of the installed package: pip install -e .)"
        )
    return _KINDS[what][name]


def _load() -> None:
    """Import every module the entry points name, once (each registers its kinds)."""
    global _loaded
    if not _loaded:
        _loaded = True
        for point in entry_points(group=ENTRY_POINTS):
            point.load()
