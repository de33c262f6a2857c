"""A rerun recording (.rrd) of a plan: the scanner moving through its scan, in millimetres.

Written headless to a file (no viewer, no network). Entity layout, world frame of
docs/conventions.md (+z up, LPS), lengths in mm:

- ``world``: view coordinates (right-handed, z up).
- ``world/obstacles/<name>``: collision objects fixed to the world (platform, floor trimmed to
  :data:`FLOOR_HALF_EXTENT_MM`, patient envelope), static pose and shape.
- ``world/scanner/<name>``: collision objects carried by a joint (arm links, tube housing,
  panel housing, column): the shape in its own frame (static) and its world pose as a
  ``Transform3D`` on the ``plan_time`` timeline, sampled at ``rate_hz``.
- ``world/paths/source``, ``world/paths/detector``: the desired focal-spot and panel-centre
  paths over all views (static).
- ``world/views/frustum``, ``world/views/source``, ``world/views/detector``: each achieved
  view's rays from the focal spot to the panel corners and the panel outline, and the two
  centre points, at the view's time on ``plan_time`` and its index on ``view``.
- ``joints/<name>``: every joint at every trajectory sample on ``plan_time`` (deg, lift mm).
- ``plan/summary``: :meth:`Plan.summary` as a markdown text document (static).

``plan_time`` counts seconds from the start of the approach.
"""

from __future__ import annotations

import json
from pathlib import Path

import coal
import numpy as np
import pinocchio as pin
import rerun as rr

from recon.geometry import View
from trajectories.model import ScannerModel
from trajectories.plan import Plan

TIMELINE = "plan_time"
"""Duration timeline, seconds from the start of the approach."""

VIEW_TIMELINE = "view"
"""Sequence timeline, the view index."""

FLOOR_HALF_EXTENT_MM = 1000.0
"""World-fixed boxes are trimmed to this half extent along x and y (the floor is 20 m wide)."""

COLORS = {
    "source": (230, 120, 40),
    "detector": (60, 130, 220),
    "scanner": (150, 150, 150),
    "obstacle": (120, 120, 120, 90),
    "patient": (220, 180, 160, 110),
}
"""RGB(A) per kind of object."""


def _shape(
    shape: coal.CollisionGeometry, color: tuple[int, ...], trim_mm: float | None
) -> rr.AsComponents:
    """The rerun archetype of a coal shape in its own frame (mm); ``trim_mm`` caps a box's half
    extent along x and y."""
    if isinstance(shape, coal.Capsule):
        half = shape.halfLength * 1000.0
        return rr.Capsules3D(
            lengths=[2 * half],
            radii=[shape.radius * 1000.0],
            translations=[(0.0, 0.0, -half)],
            colors=[color],
        )
    if isinstance(shape, coal.Box):
        half_sizes = np.asarray(shape.halfSide) * 1000.0
        if trim_mm is not None:
            half_sizes[:2] = np.minimum(half_sizes[:2], trim_mm)
        return rr.Boxes3D(half_sizes=[half_sizes], colors=[color], fill_mode="solid")
    if isinstance(shape, coal.Cylinder):
        return rr.Cylinders3D(
            lengths=[2 * shape.halfLength * 1000.0],
            radii=[shape.radius * 1000.0],
            colors=[color],
            fill_mode="solid",
        )
    if isinstance(shape, coal.Sphere):
        return rr.Ellipsoids3D(
            half_sizes=[[shape.radius * 1000.0] * 3], colors=[color], fill_mode="solid"
        )
    raise TypeError(f"no rerun shape for coal {type(shape).__name__}")


def _color(name: str, fixed: bool) -> tuple[int, ...]:
    if fixed:
        return COLORS["patient" if name.startswith("patient") else "obstacle"]
    role = name.split("_")[0]
    return COLORS[role if role in COLORS else "scanner"]


def frustum(view: View) -> list[np.ndarray]:
    """Rays from the focal spot to the panel's four outer corners and the closed outline (mm)."""
    u = (-0.5, view.cols - 0.5, view.cols - 0.5, -0.5)
    v = (-0.5, -0.5, view.rows - 0.5, view.rows - 0.5)
    corners = view.pixel_to_world(np.array(u), np.array(v))
    rays = [np.stack((view.source_mm, corner)) for corner in corners]
    return [*rays, np.vstack((corners, corners[:1]))]


def sample_indices(t_s: np.ndarray, rate_hz: float) -> np.ndarray:
    """Indices of the trajectory samples kept at ``rate_hz``: the first sample at or after each
    tick of a 1/rate_hz grid from ``t_s[0]``, and always the last sample.

    Args:
        t_s: increasing sample times, seconds.
        rate_hz: wanted rate, Hz (> 0).

    Returns:
        Increasing unique indices into ``t_s``.
    """
    if not rate_hz > 0:
        raise ValueError(f"rate_hz must be > 0, got {rate_hz!r}")
    ticks = np.arange(t_s[0], t_s[-1], 1.0 / rate_hz)
    picks = np.searchsorted(t_s, ticks - 1e-9)
    return np.unique(np.append(picks, len(t_s) - 1))


def record_plan(
    plan: Plan,
    model: ScannerModel,
    path: str | Path,
    *,
    rate_hz: float = 10.0,
    application_id: str = "dualarm-cbct",
) -> Path:
    """Write a rerun recording of ``plan`` on ``model`` to ``path`` (entity layout: module doc).

    Args:
        plan: the checked, timed scan (joint units deg / mm).
        model: the scanner model the plan was made on (its collision geometry is drawn).
        path: the .rrd file to write; it must not exist. Written as ``<path>.partial`` and
            renamed when complete.
        rate_hz: rate (Hz) at which the collision objects' poses are sampled; joints are
            recorded at every trajectory sample.
        application_id: rerun application id.

    Returns:
        ``path``.

    Raises:
        FileExistsError: ``path`` (or its partial file) exists.
        ValueError: ``rate_hz`` is not positive.
        TypeError: a collision shape has no rerun counterpart.
    """
    path = Path(path)
    partial = path.with_name(path.name + ".partial")
    for target in (path, partial):
        if target.exists():
            raise FileExistsError(f"{target} exists: a recording is never written over another")
    keep = sample_indices(plan.t_s, rate_hz)
    rec = rr.RecordingStream(application_id)
    rec.save(partial)
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    text = "```json\n" + json.dumps(plan.summary(), indent=2) + "\n```"
    rec.log("plan/summary", rr.TextDocument(text, media_type="text/markdown"), static=True)
    _log_collision_objects(rec, plan, model, keep)
    _log_views(rec, plan)
    _log_joints(rec, plan)
    rec.flush()
    rec.disconnect()
    partial.rename(path)
    return path


def _log_collision_objects(
    rec: rr.RecordingStream, plan: Plan, model: ScannerModel, keep: np.ndarray
) -> None:
    geometry = model.geometry
    data = model.model.createData()
    geometry_data = pin.GeometryData(geometry)
    objects = list(geometry.geometryObjects)
    moving = [k for k, obj in enumerate(objects) if obj.parentJoint != 0]
    rotations = np.empty((len(keep), len(objects), 3, 3))
    translations_mm = np.empty((len(keep), len(objects), 3))
    for row, q in enumerate(model.from_units(plan.q[keep])):
        pin.forwardKinematics(model.model, data, q)
        pin.updateGeometryPlacements(model.model, data, geometry, geometry_data)
        for k in moving:
            placement = geometry_data.oMg[k]
            rotations[row, k] = placement.rotation
            translations_mm[row, k] = placement.translation * 1000.0
    times = rr.TimeColumn(TIMELINE, duration=plan.t_s[keep])
    for k, obj in enumerate(objects):
        fixed = obj.parentJoint == 0
        entity = f"world/{'obstacles' if fixed else 'scanner'}/{obj.name}"
        shape = _shape(
            obj.geometry, _color(obj.name, fixed), FLOOR_HALF_EXTENT_MM if fixed else None
        )
        if fixed:
            pose = rr.Transform3D(
                translation=obj.placement.translation * 1000.0, mat3x3=obj.placement.rotation
            )
            rec.log(entity, shape, pose, static=True)
        else:
            rec.log(entity, shape, static=True)
            rec.send_columns(
                entity,
                indexes=[times],
                columns=rr.Transform3D.columns(
                    translation=translations_mm[:, k], mat3x3=rotations[:, k]
                ),
            )


def _log_views(rec: rr.RecordingStream, plan: Plan) -> None:
    desired = plan.desired
    rec.log(
        "world/paths/source",
        rr.LineStrips3D([desired.sources_mm], colors=[COLORS["source"]]),
        static=True,
    )
    rec.log(
        "world/paths/detector",
        rr.LineStrips3D(
            [np.array([view.detector_center_mm for view in desired])],
            colors=[COLORS["detector"]],
        ),
        static=True,
    )
    achieved = list(plan.achieved)
    indexes = [
        rr.TimeColumn(TIMELINE, duration=plan.view_times_s),
        rr.TimeColumn(VIEW_TIMELINE, sequence=np.arange(len(achieved))),
    ]
    strips = [strip for view in achieved for strip in frustum(view)]
    rec.send_columns(
        "world/views/frustum",
        indexes=indexes,
        columns=rr.LineStrips3D.columns(strips=strips).partition([5] * len(achieved)),
    )
    for role, points in (
        ("source", np.array([view.source_mm for view in achieved])),
        ("detector", np.array([view.detector_center_mm for view in achieved])),
    ):
        rec.log(f"world/views/{role}", rr.Points3D.from_fields(colors=[COLORS[role]]), static=True)
        rec.send_columns(
            f"world/views/{role}", indexes=indexes, columns=rr.Points3D.columns(positions=points)
        )


def _log_joints(rec: rr.RecordingStream, plan: Plan) -> None:
    times = rr.TimeColumn(TIMELINE, duration=plan.t_s)
    for k, (name, unit) in enumerate(zip(plan.joint_names, plan.joint_units, strict=True)):
        rec.log(f"joints/{name}", rr.SeriesLines(names=f"{name} ({unit})"), static=True)
        rec.send_columns(
            f"joints/{name}", indexes=[times], columns=rr.Scalars.columns(scalars=plan.q[:, k])
        )
