"""recon.geometry: views, geometries, orbits, protocol orbits."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError
from scipy.spatial.transform import Rotation

from recon.geometry import (
    DetectorSpec,
    Geometry,
    OrbitSpec,
    View,
    circular_orbit,
    helical_orbit,
    short_scan_arc_deg,
)

PANEL = DetectorSpec(rows=48, cols=64, pixel_pitch_mm=0.8)


def random_view(seed: int, pitch_u: float = 0.8, pitch_v: float = 0.7) -> View:
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=seed).as_matrix()
    source = rng.normal(size=3) * 200
    origin = source + R[:, 2] * rng.uniform(300, 1500) + rng.normal(size=3) * 50
    return View(source, origin, R[:, 0], R[:, 1], pitch_u, pitch_v, 48, 64)


def test_matrix_maps_pixels_to_their_indices_and_depth_is_the_fraction_of_the_ray():
    view = random_view(1)
    u, v = np.meshgrid(np.arange(0, 64, 7.5), np.arange(0, 48, 5.5))
    on_panel = view.pixel_to_world(u, v).reshape(-1, 3)
    np.testing.assert_allclose(
        view.project(on_panel), np.column_stack((u.ravel(), v.ravel())), atol=1e-9
    )
    np.testing.assert_allclose(view.depth(on_panel), 1.0, atol=1e-12)
    midway = 0.5 * (view.source_mm + on_panel)
    np.testing.assert_allclose(view.depth(midway), 0.5, atol=1e-12)
    np.testing.assert_allclose(view.project(midway), view.project(on_panel), atol=1e-9)
    assert view.depth(view.source_mm)[0] == pytest.approx(0.0, abs=1e-12)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10_000), log_scale=st.floats(-6, 6))
def test_from_matrix_recovers_the_view_from_any_positive_multiple(seed, log_scale):
    view = random_view(seed)
    back = View.from_matrix(view.matrix * math.exp(log_scale), view.pitch_u_mm, 48, 64)
    assert back == view
    assert back.pitch_v_mm == pytest.approx(0.7, rel=1e-9)


def test_from_matrix_keeps_skewed_detector_axes():
    view = random_view(3)
    e_v = view.e_v + 0.05 * view.e_u
    skewed = View(
        view.source_mm,
        view.detector_origin_mm,
        view.e_u,
        e_v / np.linalg.norm(e_v),
        0.8,
        0.7,
        48,
        64,
    )
    assert View.from_matrix(skewed.matrix, 0.8, 48, 64) == skewed
    with pytest.raises(ValueError, match="skewed"):
        _ = skewed.T_world_detector


def test_pose_round_trip_and_center_constructor():
    view = random_view(5, 0.8, 0.8)
    again = View.from_poses(view.source_mm, view.T_world_detector, PANEL)
    assert again == view
    centred = View.from_center(view.source_mm, view.detector_center_mm, view.e_u, view.e_v, PANEL)
    assert centred == view


def test_equality_is_within_tolerance_and_repr_rebuilds():
    g = helical_orbit(6, 600, 1000, PANEL, arc_deg=360, z_start_mm=-10, z_end_mm=10, passes=2)
    assert eval(repr(g)) == g
    nudged = View(
        g[2].source_mm + 1e-8, g[2].detector_origin_mm, g[2].e_u, g[2].e_v, 0.8, 0.8, 48, 64
    )
    moved = View(
        g[2].source_mm + 1e-3, g[2].detector_origin_mm, g[2].e_u, g[2].e_v, 0.8, 0.8, 48, 64
    )
    assert nudged == g[2]
    assert moved != g[2]
    with pytest.raises(TypeError):
        hash(g[0])


def test_geometry_sequence_protocol():
    g = circular_orbit(10, 600, 1000, PANEL)
    assert len(g) == 10 and isinstance(g[3], View)
    assert isinstance(g[2:5], Geometry) and len(g[2:5]) == 3 and g[2:5][0] == g[2]
    assert g[[0, 9]][1] == g[9]
    assert list(g)[4] == g[4]
    assert g.matrices.shape == (10, 3, 4) and not g.matrices.flags.writeable
    assert g != circular_orbit(10, 600, 1001, PANEL)
    other = View(g[0].source_mm, g[0].detector_origin_mm, g[0].e_u, g[0].e_v, 0.8, 0.8, 10, 10)
    with pytest.raises(ValueError, match="one projection stack"):
        Geometry([g[0], other])


def test_circular_orbit_known_angle_is_not_flipped():
    """At 90 degrees the source sits at the patient's left (+x); a point anterior (-y) and up
    (+z) of the isocentre lands left of (lower u) and above (higher v) the panel centre,
    magnified by SDD / SID."""
    g = circular_orbit(4, 600, 1000, PANEL)
    view = g[1]
    np.testing.assert_allclose(view.source_mm, [600, 0, 0], atol=1e-9)
    np.testing.assert_allclose(view.detector_center_mm, [-400, 0, 0], atol=1e-9)
    u, v = view.project([0.0, -10.0, 5.0])[0]
    magnification = 1000 / 600
    assert u == pytest.approx(31.5 - 10 * magnification / 0.8, abs=1e-9)
    assert v == pytest.approx(23.5 + 5 * magnification / 0.8, abs=1e-9)
    # angle 0: AP view, patient's left (+x) on increasing u as seen from the source
    u0, _ = g[0].project([10.0, 0.0, 0.0])[0]
    assert u0 > 31.5


def test_helical_orbit_passes_alternate_and_z_advances():
    g = helical_orbit(8, 600, 1000, PANEL, arc_deg=180, z_start_mm=0, z_step_mm=1.5, passes=2)
    angles = [math.degrees(math.atan2(v.source_mm[0], -v.source_mm[1])) for v in g]
    np.testing.assert_allclose(angles, [0, 60, 120, 180, 180, 120, 60, 0], atol=1e-9)
    np.testing.assert_allclose([v.source_mm[2] for v in g], 1.5 * np.arange(8), atol=1e-12)
    one_turn = helical_orbit(4, 600, 1000, PANEL, arc_deg=360, z_start_mm=0, z_end_mm=3)
    turn_angles = [math.degrees(math.atan2(v.source_mm[0], -v.source_mm[1])) for v in one_turn]
    np.testing.assert_allclose(turn_angles, [0, 90, 180, -90], atol=1e-9)


def test_short_scan_arc_is_180_plus_fan():
    fan = 2 * math.degrees(math.atan(0.5 * 64 * 0.8 / 1000))
    assert short_scan_arc_deg(1000, PANEL) == pytest.approx(180 + fan)
    g = circular_orbit(5, 600, 1000, PANEL, arc_deg=200)
    first = math.atan2(g[0].source_mm[0], -g[0].source_mm[1])
    last = math.atan2(g[-1].source_mm[0], -g[-1].source_mm[1])
    assert math.degrees(last - first) % 360 == pytest.approx(200)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"pitch_u_mm": 0.0}, "pitch_u_mm must be a finite pitch > 0"),
        ({"pitch_v_mm": float("nan")}, "pitch_v_mm"),
        ({"e_u": [1.0, 0.1, 0.0]}, "e_u must be a unit vector"),
        ({"e_v": [1.0, 0.0, 0.0]}, "parallel"),
        ({"rows": 0}, "rows must be a positive integer"),
        ({"source_mm": [0.0, float("inf"), 0.0]}, "source_mm must be finite"),
        ({"source_mm": [5.0, 7.0, 0.0]}, "source lies in the detector plane"),
    ],
)
def test_bad_views_name_the_field(kwargs, message):
    fields = {
        "source_mm": [0, 0, -600],
        "detector_origin_mm": [0, 0, 400],
        "e_u": [1, 0, 0],
        "e_v": [0, 1, 0],
        "pitch_u_mm": 1.0,
        "pitch_v_mm": 1.0,
        "rows": 4,
        "cols": 4,
    }
    fields.update(kwargs)
    if "source_mm" in kwargs and kwargs["source_mm"][2] == 0.0:
        fields["detector_origin_mm"] = [0, 0, 0]
    with pytest.raises(ValueError, match=message):
        View(**fields)


def test_orbit_spec_builds_each_kind():
    base = {"views": 12, "sid_mm": 600, "sdd_mm": 1000, "isocenter_mm": (0, 0, 480)}
    circ = OrbitSpec(kind="circular", **base).geometry(PANEL)
    assert circ == circular_orbit(12, 600, 1000, PANEL, isocenter_mm=(0, 0, 480))
    short = OrbitSpec(kind="short_scan", overscan_deg=4, **base).geometry(PANEL)
    expected = circular_orbit(
        12,
        600,
        1000,
        PANEL,
        arc_deg=short_scan_arc_deg(1000, PANEL) + 4,
        isocenter_mm=(0, 0, 480),
    )
    assert short == expected
    spiral = OrbitSpec(kind="reverse_spiral", passes=2, arc_deg=360, z_step_mm=1.5, **base)
    z = [v.source_mm[2] for v in spiral.geometry(PANEL)]
    np.testing.assert_allclose(np.diff(z), 1.5)
    assert np.mean(z) == pytest.approx(480)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"kind": "circular", "sdd_mm": 500}, "sdd_mm = 500.0 must exceed sid_mm"),
        ({"kind": "helix"}, "exactly one of z_travel_mm and z_step_mm"),
        ({"kind": "circular", "z_step_mm": 1.0}, "does not move in z"),
        ({"kind": "reverse_spiral", "z_step_mm": 1.0}, "passes >= 2"),
        ({"kind": "circular", "views": 2}, "views"),
        ({"kind": "circular", "sid_mm": -5}, "sid_mm"),
    ],
)
def test_orbit_spec_refuses_inconsistent_orbits(kwargs, message):
    fields = {"views": 12, "sid_mm": 600, "sdd_mm": 1000} | kwargs
    with pytest.raises(ValidationError, match=message):
        OrbitSpec(**fields)
