"""Configuration files: YAML validated by frozen pydantic models, with errors users can act on.

Every package defines its own models (units in the field names); this module loads a file into
one and turns validation failures into a :class:`ConfigError` that names the file, the field,
the value and the limit. It also holds the scan protocol shared by planning, simulation,
scanning and reconstruction.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Literal, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from recon.geometry import DetectorSpec, OrbitSpec

Model = TypeVar("Model", bound=BaseModel)


class ConfigError(ValueError):
    """A configuration file that cannot be used; the message says where and why."""


def _describe(path: Path, err: ValidationError, model: type[BaseModel]) -> str:
    errors = err.errors()
    unknown = [".".join(str(p) for p in e["loc"]) for e in errors if e["type"] == "extra_forbidden"]
    missing = [".".join(str(p) for p in e["loc"]) for e in errors if e["type"] == "missing"]
    if len(unknown) > 2 and missing:  # another kind of file altogether
        kind = re.sub(r"(?<!^)(?=[A-Z])", " ", model.__name__).lower()
        shown = ", ".join(unknown[:4]) + (", ..." if len(unknown) > 4 else "")
        return (
            f"{path}: not a {kind} file? {len(unknown)} unknown fields ({shown}), and "
            f"{', '.join(missing)} missing"
        )
    lines = [f"{path}: {err.error_count()} invalid field(s)"]
    for e in errors:
        field = ".".join(str(p) for p in e["loc"]) or "(top level)"
        value = e.get("input")
        shown = "missing" if e["type"] == "missing" else f"value {value!r}"
        lines.append(f"  {field}: {shown}: {e['msg']}")
    return "\n".join(lines)


def _read_mapping(path: Path, seen: tuple[Path, ...] = ()) -> dict:
    """A YAML file's mapping of fields, those of the file it ``extends`` beneath its own."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise ConfigError(f"{path}: cannot read ({err.strerror or err})") from None
    except UnicodeDecodeError as err:
        raise ConfigError(f"{path}: not UTF-8 text ({err.reason} at byte {err.start})") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML ({err})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of fields, got {type(data).__name__}")
    if "extends" not in data:
        return data
    base = data.pop("extends")
    if not isinstance(base, str):
        raise ConfigError(f"{path}: extends: value {base!r}: give the path of a YAML file")
    seen = (*seen, path.resolve())
    if (path.parent / base).resolve() in seen:
        raise ConfigError(f"{path}: extends: {base!r}, which extends this file again (a loop)")
    try:
        return {**_read_mapping(path.parent / base, seen), **data}
    except ConfigError as err:
        raise ConfigError(f"{path}: extends: {base!r}: {err}") from None


def load_config(path: str | Path, model: type[Model]) -> Model:
    """Read a YAML file into a pydantic model, raising :class:`ConfigError` on any problem.

    NaN or infinite numbers are refused too. A file may start from another: ``extends:
    other.yaml`` (relative to the file) takes every field of that file, and the file's own
    fields replace them.

    Args:
        path: YAML file, UTF-8.
        model: The pydantic model class to validate against.
    """
    path = Path(path)
    data = _read_mapping(path)
    _check_finite(path, data)  # before pydantic, whose limits say nothing useful of NaN
    try:
        config = model.model_validate(data)
    except ValidationError as err:
        raise ConfigError(_describe(path, err, model)) from None
    _check_finite(path, config.model_dump())  # e.g. the string "nan", which pydantic parses
    return config


def _check_finite(path: Path, tree: object) -> None:
    for field, value in _numbers(tree):
        if not math.isfinite(value):
            raise ConfigError(f"{path}: {field} is {value!r}: give a finite number")


def _numbers(tree: object, where: str = "") -> Iterator[tuple[str, float]]:
    """(dotted field, value) of every float in a dumped model."""
    if isinstance(tree, float):
        yield where or "(top level)", tree
    elif isinstance(tree, dict):
        for key, value in tree.items():
            yield from _numbers(value, f"{where}.{key}" if where else str(key))
    elif isinstance(tree, list | tuple):
        for i, value in enumerate(tree):
            yield from _numbers(value, f"{where}.{i}" if where else str(i))


class ExposureSpec(BaseModel):
    """X-ray technique per view."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    tube_kv: float = Field(ge=40.0, le=150.0, description="tube voltage, kVp")
    tube_ma: float = Field(gt=0.0, le=1000.0, description="tube current, mA")
    pulse_ms: float = Field(gt=0.0, le=1000.0, description="pulse width per view, ms")

    @property
    def mas(self) -> float:
        """Tube current-time product per view, mAs."""
        return self.tube_ma * self.pulse_ms * 1e-3


class ReconstructionSpec(BaseModel):
    """How a protocol's scans are reconstructed (recon.iterative for sart and tv)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    method: Literal["fdk", "sart", "tv"] = Field(
        "fdk", description="fdk (weighted FDK), sart (OS-SART from FDK) or tv (OS-SART + TV)"
    )
    iterations: int = Field(12, ge=1, le=200, description="sart/tv: most iterations")
    tv_weight_per_mm: float | None = Field(
        None, ge=0.0, description="tv: TV step's strength, 1/mm (None: from the data's noise)"
    )

    @model_validator(mode="after")
    def _weight_for_tv(self) -> ReconstructionSpec:
        if self.tv_weight_per_mm is not None and self.method != "tv":
            raise ValueError(f"tv_weight_per_mm is for method tv, not {self.method}")
        return self


class ScanProtocol(BaseModel):
    """A scan protocol: which views, on which panel, with which technique."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = Field(min_length=1, max_length=80, pattern=r"^[A-Za-z0-9_.-]+$")
    description: str = ""
    detector: DetectorSpec
    orbit: OrbitSpec
    exposure: ExposureSpec
    dose_limit_mas: float = Field(
        250.0, gt=0.0, le=5000.0, description="limit on the whole scan's tube load, mAs"
    )
    reconstruction: ReconstructionSpec = Field(default_factory=ReconstructionSpec)

    @model_validator(mode="after")
    def _dose_within_limit(self) -> ScanProtocol:
        dose = self.orbit.views * self.exposure.mas
        if dose > self.dose_limit_mas:
            raise ValueError(
                f"scan dose {dose:.1f} mAs ({self.orbit.views} views x {self.exposure.mas:.3f} "
                f"mAs) exceeds dose_limit_mas {self.dose_limit_mas:.1f} mAs"
            )
        return self


def load_protocol(path: str | Path) -> ScanProtocol:
    """Load a scan protocol YAML file (see configs/protocols/).

    Args:
        path: Protocol YAML file.
    """
    return load_config(path, ScanProtocol)
