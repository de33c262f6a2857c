"""Calibrate a scan of the BB phantom: every view's geometry and its deviation from the plan.

Steps: detect and identify the balls in each view (calibration.detect, .identify); place the
phantom by fitting its pose through the planned views (or take it as known from a pinned
holder: either way this fixes the gauge, calibration.fit); fit each
view's focal spot and panel (9 parameters, prior toward the plan); report per view the
reprojection error and the deviation from the plan (the arms' vibration).

A calibration belongs to one protocol and one plan: it records the protocol's name and a hash
of its plan (orbit and panel, :func:`plan_hash`), and :func:`corrected_geometry` refuses to
apply it to a scan of any other protocol or plan. Views with fewer than ``min_balls``
identified balls keep their planned geometry and are reported as such, never filled in
silently.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from calibration.detect import detect_balls
from calibration.fit import Prior, fit_phantom_pose, fit_view
from calibration.identify import identify
from calibration.phantom import BBPhantomSpec
from recon.config import ScanProtocol
from recon.geometry import Geometry
from recon.rtk_xml import PanelHeader, read_rtk_geometry, write_rtk_geometry

MIN_BALLS = 8
"""Fewest identified balls a view needs to be calibrated (9 parameters, 2 equations a ball)."""

CENTROID_NOISE_PX = 0.1
"""Assumed centroid noise, px: weighs the reprojection against the prior."""


@dataclass(frozen=True)
class ViewReport:
    """One view's calibration.

    Attributes:
        view: index.
        status: "calibrated" or "planned: too few balls (n < MIN_BALLS)".
        balls_detected, balls_used: blobs found, balls identified and fitted.
        reprojection_rms_px: RMS reprojection error of the used balls.
        source_deviation_mm, detector_deviation_mm, detector_deviation_deg: calibrated minus
            planned (vibration).
    """

    view: int
    status: str
    balls_detected: int
    balls_used: int
    reprojection_rms_px: float
    source_deviation_mm: float
    detector_deviation_mm: float
    detector_deviation_deg: float


def plan_hash(protocol: ScanProtocol) -> str:
    """SHA-256 of the protocol's views (orbit and the panel's physical size, canonical JSON):
    which plan a calibration is for. The panel's read-out (binning) is left out: the views are
    physical, so a calibration made with fine pixels corrects a binned scan of the same plan."""
    d = protocol.detector
    plan = {
        "orbit": protocol.orbit.model_dump(mode="json"),
        "panel_mm": [round(d.width_mm, 6), round(d.height_mm, 6)],
    }
    return hashlib.sha256(json.dumps(plan, sort_keys=True).encode()).hexdigest()


def _deviation(calibrated, planned) -> tuple[float, float, float]:
    source = float(np.linalg.norm(calibrated.source_mm - planned.source_mm))
    detector = float(np.linalg.norm(calibrated.detector_center_mm - planned.detector_center_mm))
    n_c, n_p = calibrated.normal, planned.normal
    u_c, u_p = calibrated.e_u, planned.e_u
    angle = max(
        math.degrees(math.acos(np.clip(n_c @ n_p, -1.0, 1.0))),
        math.degrees(math.acos(np.clip(u_c @ u_p, -1.0, 1.0))),
    )
    return source, detector, angle


@dataclass(frozen=True)
class Calibration:
    """Calibrated geometry of a protocol's plan, with the per-view report."""

    protocol: str
    plan_hash: str
    planned: Geometry
    geometry: Geometry
    T_world_phantom: np.ndarray
    views: tuple[ViewReport, ...]
    seconds: float

    def summary(self) -> dict:
        used = [v for v in self.views if v.status == "calibrated"]
        rms = np.array([v.reprojection_rms_px for v in used])
        worst = sorted(used, key=lambda v: -v.reprojection_rms_px)[:5]
        return {
            "protocol": self.protocol,
            "plan_hash": self.plan_hash,
            "views": len(self.views),
            "calibrated_views": len(used),
            "uncalibrated_views": [v.view for v in self.views if v.status != "calibrated"],
            "reprojection_rms_px_median": float(np.median(rms)) if len(rms) else None,
            "reprojection_rms_px_max": float(rms.max()) if len(rms) else None,
            "worst_views": [v.view for v in worst],
            "phantom_center_mm": self.T_world_phantom[:3, 3].round(3).tolist(),
            "seconds": round(self.seconds, 2),
        }

    def save(self, folder: Path) -> list[Path]:
        """``folder/geometry.xml`` (RTK) and ``folder/report.json``; never overwrites."""
        folder = Path(folder)
        if folder.exists():
            raise FileExistsError(f"{folder} exists: a calibration is never written over")
        tmp = folder.with_name(folder.name + ".partial")
        tmp.mkdir(parents=True)
        write_rtk_geometry(tmp / "geometry.xml", self.geometry)
        report = {
            "summary": self.summary(),
            "views": [asdict(v) for v in self.views],
            "T_world_phantom": self.T_world_phantom.tolist(),
        }
        (tmp / "report.json").write_text(json.dumps(report, indent=2), encoding="utf-8")
        tmp.rename(folder)
        return [folder / "geometry.xml", folder / "report.json"]


def ball_radius_px(planned: Geometry, phantom: BBPhantomSpec) -> float:
    """Largest ball shadow radius to expect (px): the large ball at the helix's near side,
    magnified by the planned views, plus 1.5 px of blur margin."""
    view = planned[0]
    sod = float(np.linalg.norm(view.source_mm - phantom.T_world_phantom[:3, 3]))
    magnification = view.sdd_mm / max(sod - phantom.helix_radius_mm, 1.0)
    return 0.5 * phantom.large_diameter_mm * magnification / view.pitch_u_mm + 1.5


def find_balls(
    projections: np.ndarray,
    planned: Geometry,
    phantom: BBPhantomSpec,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[list[tuple[np.ndarray, np.ndarray]], list[int]]:
    """Per view: (ball ids, centroids uv) of the identified balls, and the blobs detected."""
    proj = np.asarray(projections)
    if proj.shape != (len(planned), planned.rows, planned.cols):
        raise ValueError(
            f"the stack holds {proj.shape[0]} projections of {proj.shape[1:]} but the plan "
            f"has {len(planned)} views of {(planned.rows, planned.cols)}"
        )
    found, counts = [], []
    radius = ball_radius_px(planned, phantom)
    for k in range(len(planned)):
        detections = detect_balls(proj[k], radius)
        ids = identify(detections, phantom.code, 360.0 / phantom.angle_step_deg)
        ok = ids >= 0
        found.append((ids[ok], detections.uv[ok]))
        counts.append(len(detections))
        if progress is not None:
            progress(k + 1, len(planned))
    return found, counts


def calibrate(
    projections: np.ndarray,
    planned: Geometry,
    phantom: BBPhantomSpec,
    protocol: ScanProtocol,
    *,
    prior: Prior | None = None,
    min_balls: int = MIN_BALLS,
    phantom_pose: str = "estimate",
    progress: Callable[[int, int], None] | None = None,
) -> Calibration:
    """Calibrate every view of a BB-phantom scan (see the module docstring).

    Args:
        projections: line integrals (views, rows, cols).
        planned: the protocol's planned views, one per projection.
        phantom: the phantom's layout and nominal placement.
        protocol: the protocol that acquired the scan (its name and plan hash are recorded
            for matching later scans).
        prior: the planned pose's uncertainty.
        min_balls: fewest identified balls per calibrated view.
        phantom_pose: "estimate" (fit the placement through the planned views: the gauge
            absorbs any offset common to all views) or "known" (the phantom stands exactly
            where ``phantom`` says, e.g. in a pinned holder: the gauge is fixed explicitly).
        progress: ``progress(done, total)`` over the views.
    """
    started = time.perf_counter()
    found, counts = find_balls(projections, planned, phantom, progress)
    return calibrate_balls(
        found,
        counts,
        planned,
        phantom,
        protocol,
        prior=prior,
        min_balls=min_balls,
        phantom_pose=phantom_pose,
        started=started,
    )


def calibrate_balls(
    found: list[tuple[np.ndarray, np.ndarray]],
    counts: list[int],
    planned: Geometry,
    phantom: BBPhantomSpec,
    protocol: ScanProtocol,
    *,
    prior: Prior | None = None,
    min_balls: int = MIN_BALLS,
    phantom_pose: str = "estimate",
    started: float | None = None,
) -> Calibration:
    """:func:`calibrate` from identified balls (see :func:`find_balls`)."""
    started = time.perf_counter() if started is None else started
    if phantom_pose not in ("estimate", "known"):
        raise ValueError(f"phantom_pose must be 'estimate' or 'known', got {phantom_pose!r}")
    prior = prior or Prior()
    local = phantom.ball_positions_local_mm()
    if sum(len(ids) for ids, _ in found) < min_balls:
        raise ValueError(
            f"no balls identified in any view (balls detected per view: median "
            f"{int(np.median(counts))}): wrong phantom definition or not a BB-phantom scan?"
        )
    T_wp = (
        fit_phantom_pose(planned, local, found, phantom.T_world_phantom)
        if phantom_pose == "estimate"
        else phantom.T_world_phantom
    )
    world = local @ T_wp[:3, :3].T + T_wp[:3, 3]
    views, reports = [], []
    for k, (view, (ids, uv)) in enumerate(zip(planned, found, strict=True)):
        if len(ids) < min_balls:
            views.append(view)
            reports.append(
                ViewReport(
                    k,
                    f"planned: too few balls ({len(ids)} < {min_balls})",
                    counts[k],
                    len(ids),
                    math.nan,
                    0.0,
                    0.0,
                    0.0,
                )
            )
        else:
            fitted, residual = fit_view(view, world[ids], uv, prior, CENTROID_NOISE_PX)
            views.append(fitted)
            rms = float(np.sqrt(np.mean(np.sum(residual**2, axis=1))))
            reports.append(
                ViewReport(k, "calibrated", counts[k], len(ids), rms, *_deviation(fitted, view))
            )
    return Calibration(
        protocol.name,
        plan_hash(protocol),
        planned,
        Geometry(views),
        T_wp,
        tuple(reports),
        time.perf_counter() - started,
    )


def corrected_geometry(folder: Path, protocol: ScanProtocol) -> Geometry:
    """The calibrated views stored in ``folder`` for a scan of ``protocol``; refuses (ValueError
    naming the folder or file) a calibration made for another protocol or another plan of it,
    and a report.json or geometry.xml that is not one."""
    folder = Path(folder)
    path = folder / "report.json"
    try:
        report = json.loads(path.read_text(encoding="utf-8"))["summary"]
        report = {"protocol": str(report["protocol"]), "plan_hash": str(report["plan_hash"])}
    except (ValueError, KeyError, TypeError) as err:  # JSON and UTF-8 errors are ValueErrors
        raise ValueError(
            f"{path}: not a calibration report ({type(err).__name__}: {err})"
        ) from None
    if report["protocol"] != protocol.name:
        raise ValueError(
            f"{folder}: calibration of protocol {report['protocol']!r} cannot correct a scan "
            f"of protocol {protocol.name!r}"
        )
    if report["plan_hash"] != plan_hash(protocol):
        raise ValueError(
            f"{folder}: calibration was made for another plan of {protocol.name!r} (plan "
            "hash differs): recalibrate after changing the protocol"
        )
    d = protocol.detector
    return read_rtk_geometry(
        folder / "geometry.xml", PanelHeader.centered(d.rows, d.cols, d.pixel_pitch_mm)
    )
