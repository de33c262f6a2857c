"""The rerun recording of a plan: written headless, readable, with poses that match the FK."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import rerun as rr

from recon.config import load_config, load_protocol
from trajectories.config import ScannerConfig
from trajectories.model import ScannerModel
from trajectories.plan import Plan, plan_scan
from trajectories.plan_recording import TIMELINE, VIEW_TIMELINE, record_plan, sample_indices

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def model() -> ScannerModel:
    return ScannerModel(load_config(ROOT / "configs/scanner.yaml", ScannerConfig))


@pytest.fixture(scope="module")
def plan(model: ScannerModel) -> Plan:
    protocol = load_protocol(ROOT / "configs/protocols/demo_knee.yaml")
    orbit = protocol.orbit.model_copy(update={"views": 24})
    return plan_scan(model, protocol.model_copy(update={"orbit": orbit}))


@pytest.fixture(scope="module")
def recording(plan: Plan, model: ScannerModel, tmp_path_factory) -> Path:
    return record_plan(plan, model, tmp_path_factory.mktemp("rec") / "plan.rrd", rate_hz=10.0)


@pytest.fixture(scope="module")
def chunks(recording: Path) -> dict[str, list[rr.chunk.Chunk]]:
    """Chunks of the recording by entity path (as logged, without the leading slash)."""
    out: dict[str, list[rr.chunk.Chunk]] = defaultdict(list)
    for chunk in rr.chunk.RrdReader(recording).stream():
        out[chunk.entity_path.lstrip("/")].append(chunk)
    return out


def _temporal(chunks: dict, entity: str):
    """The one time-indexed record batch of ``entity``."""
    (chunk,) = [c for c in chunks[entity] if not c.is_static]
    return chunk.timeline_names, chunk.to_record_batch()


def _rows(batch, column: str) -> list:
    """Per-row component batches of ``column`` (each a list of instances)."""
    return batch.column(column).to_pylist()


def test_recording_is_written_and_complete(recording: Path):
    assert recording.is_file() and recording.stat().st_size > 0
    assert not recording.with_name(recording.name + ".partial").exists()


def test_lists_every_collision_object_frustum_and_joint(chunks, plan: Plan, model: ScannerModel):
    for obj in model.geometry.geometryObjects:
        if obj.parentJoint == 0:
            (chunk,) = chunks[f"world/obstacles/{obj.name}"]
            assert chunk.is_static
        else:
            timelines, batch = _temporal(chunks, f"world/scanner/{obj.name}")
            assert timelines == [TIMELINE]
            assert batch.num_rows == len(sample_indices(plan.t_s, 10.0))
            assert any(c.is_static for c in chunks[f"world/scanner/{obj.name}"])  # the shape
    timelines, batch = _temporal(chunks, "world/views/frustum")
    assert sorted(timelines) == sorted([TIMELINE, VIEW_TIMELINE])
    assert batch.num_rows == len(plan.desired)
    for k, name in enumerate(plan.joint_names):
        timelines, batch = _temporal(chunks, f"joints/{name}")
        assert timelines == [TIMELINE]
        np.testing.assert_allclose(_rows(batch, "Scalars:scalars"), plan.q[:, [k]])
    for entity in ("world", "plan/summary", "world/paths/source", "world/paths/detector"):
        assert all(c.is_static for c in chunks[entity])
    (summary,) = chunks["plan/summary"]
    assert plan.protocol in _rows(summary.to_record_batch(), "TextDocument:text")[0][0]


def test_link_pose_matches_forward_kinematics(chunks, plan: Plan, model: ScannerModel):
    name = "source_link3"
    _, batch = _temporal(chunks, f"world/scanner/{name}")
    row = batch.num_rows // 2
    time_s = batch.column(TIMELINE)[row].value / 1e9
    k = int(np.argmin(np.abs(plan.t_s - time_s)))
    assert abs(plan.t_s[k] - time_s) < 1e-6
    data = model.model.createData()
    geometry_data = pin.GeometryData(model.geometry)
    pin.forwardKinematics(model.model, data, model.from_units(plan.q[k]))
    pin.updateGeometryPlacements(model.model, data, model.geometry, geometry_data)
    expected = geometry_data.oMg[model.geometry.getGeometryId(name)]
    translation_mm = np.array(_rows(batch, "Transform3D:translation")[row][0])
    rotation = np.array(_rows(batch, "Transform3D:mat3x3")[row][0]).reshape(3, 3, order="F")
    np.testing.assert_allclose(translation_mm, expected.translation * 1000.0, atol=1e-3)
    np.testing.assert_allclose(rotation, expected.rotation, atol=1e-6)


def test_frustum_starts_at_the_achieved_focal_spot(chunks, plan: Plan):
    _, batch = _temporal(chunks, "world/views/frustum")
    views = batch.column(VIEW_TIMELINE).to_pylist()
    for row, strips in enumerate(_rows(batch, "LineStrips3D:strips")):
        view = plan.achieved[views[row]]
        assert len(strips) == 5  # four rays and the panel outline
        for ray in strips[:4]:
            np.testing.assert_allclose(ray[0], view.source_mm, atol=1e-3)
            assert abs(view.depth(np.array(ray[1]))[0] - 1.0) < 1e-6  # on the panel plane
        assert len(strips[4]) == 5


def test_refuses_to_overwrite(plan: Plan, model: ScannerModel, recording: Path):
    before = recording.read_bytes()
    with pytest.raises(FileExistsError, match=recording.name):
        record_plan(plan, model, recording)
    assert recording.read_bytes() == before


def test_sample_indices_keep_the_rate_and_the_last_sample():
    t_s = np.arange(0.0, 3.01, 0.02)
    keep = sample_indices(t_s, 10.0)
    assert keep[0] == 0 and keep[-1] == len(t_s) - 1
    np.testing.assert_allclose(np.diff(t_s[keep]), 0.1, atol=1e-9)
    with pytest.raises(ValueError, match="rate_hz"):
        sample_indices(t_s, 0.0)
