"""A session's inputs, read and validated before anything is written or moved; also the study's
config snapshot of a scan stage."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from pydantic import BaseModel

from recon.config import ScanProtocol, load_config, load_protocol
from recon.geometry import DetectorSpec
from scanner import registry
from scanner.registry import Subject
from trajectories.config import ScannerConfig


@dataclass(frozen=True)
class SessionInputs:
    """Validated inputs of a session (also the study's config snapshot).

    Attributes:
        protocol: the scan protocol.
        scanner: the scanner's hardware config.
        backend_kind: the backend's registered name (:mod:`scanner.registry`).
        backend: its config.
        phantom_kind: the phantom's registered name.
        phantom: its config (what a simulated panel images).
        phantom_voxel_mm: the voxel a rasterised phantom is simulated at, mm.
    """

    protocol: ScanProtocol
    scanner: ScannerConfig
    backend_kind: str
    backend: BaseModel
    phantom_kind: str
    phantom: BaseModel
    phantom_voxel_mm: float

    @property
    def panel(self) -> DetectorSpec:
        """The protocol's panel read-out."""
        d = self.protocol.detector
        return DetectorSpec(rows=d.rows, cols=d.cols, pixel_pitch_mm=d.pixel_pitch_mm)

    def snapshot(self) -> dict:
        """The inputs as the study's ``config`` records them (JSON types)."""
        return {
            "protocol": self.protocol.model_dump(mode="json"),
            "scanner": self.scanner.model_dump(mode="json"),
            "backend": {"kind": self.backend_kind, **self.backend.model_dump(mode="json")},
            "phantom": {"kind": self.phantom_kind, **self.phantom.model_dump(mode="json")},
            "phantom_voxel_mm": self.phantom_voxel_mm,
        }

    @classmethod
    def from_snapshot(cls, config: dict) -> SessionInputs:
        """The inputs a study's ``config`` recorded (:meth:`snapshot`)."""
        backend = dict(config["backend"])
        kind = backend.pop("kind")
        phantom = dict(config["phantom"])
        shape = phantom.pop("kind")
        return cls(
            protocol=ScanProtocol.model_validate(config["protocol"]),
            scanner=ScannerConfig.model_validate(config["scanner"]),
            backend_kind=kind,
            backend=registry.backend_kind(kind).spec.model_validate(backend),
            phantom_kind=shape,
            phantom=registry.phantom_kind(shape).spec.model_validate(phantom),
            phantom_voxel_mm=float(config["phantom_voxel_mm"]),
        )


def read_inputs(
    protocol: Path | ScanProtocol,
    scanner: Path,
    backend_kind: str,
    backend_config: Path,
    phantom: Path,
    *,
    phantom_voxel_mm: float = 1.0,
    phantom_kind: str = "knee",
) -> SessionInputs:
    """Read and validate every input before anything is written or moved."""
    phantom_spec = registry.phantom_kind(
        phantom_kind
    ).spec  # an unknown kind: refused before any file
    if not 0.25 <= phantom_voxel_mm <= 4.0:
        raise ValueError(f"phantom_voxel_mm must be in [0.25, 4] mm, got {phantom_voxel_mm}")
    if not isinstance(protocol, ScanProtocol):
        protocol = load_protocol(protocol)
    protocol = ScanProtocol.model_validate(protocol.model_dump())  # checks edits, dose included
    return SessionInputs(
        protocol=protocol,
        scanner=load_config(scanner, ScannerConfig),
        backend_kind=backend_kind,
        backend=load_backend_spec(backend_kind, backend_config),
        phantom_kind=phantom_kind,
        phantom=load_config(phantom, phantom_spec),
        phantom_voxel_mm=phantom_voxel_mm,
    )


def load_backend_spec(kind: str, path: str | Path) -> BaseModel:
    """Read the config of the backend called ``kind``; raises naming the file and field on any
    problem."""
    return load_config(path, registry.backend_kind(kind).spec)


def subject(inputs: SessionInputs, say: Callable[[str], None], scan_s: float = 1.0) -> Subject:
    """What the simulated panel sees of the inputs' phantom over a scan of ``scan_s`` seconds
    (its kind's :attr:`PhantomKind.subject`)."""
    return registry.phantom_kind(inputs.phantom_kind).subject(inputs, say, scan_s)
