"""recon.config: YAML files into frozen models, errors that say file, field, value and limit."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from pydantic import ValidationError

from recon.config import ConfigError, ScanProtocol, load_config, load_protocol

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


@pytest.mark.parametrize(
    "path", sorted((CONFIGS / "protocols").glob("*.yaml")), ids=lambda p: p.stem
)
def test_every_shipped_protocol_loads_and_builds_its_views(path):
    protocol = load_protocol(path)
    geometry = protocol.orbit.geometry(protocol.detector)
    assert len(geometry) == protocol.orbit.views
    assert (geometry.rows, geometry.cols) == (protocol.detector.rows, protocol.detector.cols)
    with pytest.raises(ValidationError):  # frozen
        protocol.name = "other"  # type: ignore[misc]


def write(tmp_path: Path, data) -> Path:
    path = tmp_path / "protocol.yaml"
    path.write_text(yaml.safe_dump(data) if not isinstance(data, str) else data)
    return path


def demo_data() -> dict:
    return yaml.safe_load((CONFIGS / "protocols" / "demo_knee.yaml").read_text(encoding="utf-8"))


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        (
            ("detector", "pixel_pitch_mm", 0.0),
            ["detector.pixel_pitch_mm", "value 0.0", "greater than 0"],
        ),
        (
            ("detector", "rows", 100000),
            ["detector.rows", "value 100000", "less than or equal to 16384"],
        ),
        (
            ("exposure", "tube_kv", 200),
            ["exposure.tube_kv", "value 200", "less than or equal to 150"],
        ),
        (("orbit", "kind", "zigzag"), ["orbit.kind", "'zigzag'", "circular"]),
        (("orbit", "z_step_mm", "fast"), ["orbit.z_step_mm", "'fast'", "number"]),
        (("orbit", "sdd_mm", 500), ["sdd_mm = 500.0 must exceed sid_mm = 600.0"]),
        (("orbit", "speed_mm", 3), ["orbit.speed_mm", "Extra inputs are not permitted"]),
    ],
)
def test_a_wrong_field_is_named_with_file_value_and_limit(tmp_path, change, expected):
    data = demo_data()
    section, field, value = change
    data[section][field] = value
    path = write(tmp_path, data)
    with pytest.raises(ConfigError) as info:
        load_protocol(path)
    message = str(info.value)
    assert message.startswith(str(path))
    for part in expected:
        assert part in message


def test_missing_fields_unreadable_files_and_non_mappings(tmp_path):
    data = demo_data()
    del data["exposure"]
    with pytest.raises(ConfigError, match="exposure: missing"):
        load_protocol(write(tmp_path, data))
    with pytest.raises(ConfigError, match="cannot read"):
        load_protocol(tmp_path / "absent.yaml")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_protocol(write(tmp_path, "name: [unclosed"))
    with pytest.raises(ConfigError, match="expected a mapping"):
        load_config(write(tmp_path, "- 1\n- 2\n"), ScanProtocol)


def test_a_config_extends_another_and_replaces_its_fields(tmp_path):
    """The gait settings are the implant settings but for the fields they give; a base that
    is missing, a loop, or an ``extends`` that is not a path are refused by name."""
    from registration.settings import Settings

    implants = load_config(CONFIGS / "registration_implants.yaml", Settings).model_dump()
    gait = load_config(CONFIGS / "registration_gait.yaml", Settings).model_dump()
    own = yaml.safe_load((CONFIGS / "registration_gait.yaml").read_text())
    assert set(own) == {"extends", "kpm_depth", "drop_ncc"}
    assert {k: v for k, v in gait.items() if k not in own} == {
        k: v for k, v in implants.items() if k not in own
    }
    assert (gait["kpm_depth"], gait["drop_ncc"]) == (own["kpm_depth"], own["drop_ncc"])
    (tmp_path / "a.yaml").write_text("extends: b.yaml\nname: a\n")
    (tmp_path / "b.yaml").write_text("extends: a.yaml\n")
    with pytest.raises(ConfigError, match=r"b\.yaml: extends: 'a\.yaml', which extends this"):
        load_config(tmp_path / "a.yaml", ScanProtocol)
    (tmp_path / "c.yaml").write_text("extends: absent.yaml\n")
    with pytest.raises(
        ConfigError, match=r"c\.yaml: extends: 'absent\.yaml': .*absent\.yaml: cannot"
    ):
        load_config(tmp_path / "c.yaml", ScanProtocol)
    (tmp_path / "d.yaml").write_text("extends: [1, 2]\n")
    with pytest.raises(ConfigError, match=r"d\.yaml: extends: value \[1, 2\]: give the path"):
        load_config(tmp_path / "d.yaml", ScanProtocol)
