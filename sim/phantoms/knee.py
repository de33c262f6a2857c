"""Digital knee phantom of a standing, weight-bearing patient.

Bones are signed distance functions (SDF, :mod:`sim.phantoms.sdf`) built in each bone's local
frame from smooth unions of spheres, ellipsoids, capsules, spindle tori and a revolved
trochlear profile, so any point set can be labelled and any grid rasterised with partial
volume. Each bone is a cortical shell (``cortical_thickness_mm``) around cancellous bone
(marrow in the diaphyseal canals), inside a muscle envelope with a subcutaneous fat layer.

Bone-local frames (all right-handed, mm). At zero flexion every frame's axes are parallel to
the world's: x toward the patient's left (medial for a right knee, lateral for a left knee),
y posterior, z proximal along the bone's long axis. Origins:

- femur: midpoint of the transepicondylar axis (TEA), the line between the epicondyle tips,
  which is the local x axis;
- tibia: centre of the plateau, midway between the lowest points of the medial and lateral
  plateau concavities (both at local z = 0); the plateau normal is local +z;
- fibula: centre of the fibular head;
- patella: centre of the patella; local y points from the patella into the trochlear groove
  (toward the femur), local z toward the proximal pole (base).

The tibia stands vertically with its plateau centre on the world z axis at
``joint_line_height_mm``. Knee flexion rotates the femur about its TEA relative to the tibia
(the femoral shaft swings posteriorly); the condyles are spindle tori about the TEA, so they
roll in place over the tibia and the joint space is the same at every flexion. The patella
slides distally along the trochlear groove, itself a surface of revolution about the TEA,
turning relative to the femur by :data:`PATELLA_FEMUR_ROTATION_RATIO` times the flexion
(in vivo patellar flexion is roughly 60-70 % of knee flexion).

Shapes at scale 1 (mm): epicondylar width 82; distal femur 57 deep (anterior-posterior);
condyles are wheels of radius 25.5 (medial, reaching 2 mm lower) and 23.5 (lateral), 28 and
27 wide, about a 20 mm intercondylar notch whose arched roof follows Blumensaat's line (35
degrees to the shaft); a V-shaped trochlear groove (facets 22 and 17 degrees) anteriorly;
femoral shaft diameter 26. Tibial plateau 77 x 48 with shallow medial and lateral
concavities (spheres of radius 60 and 80, 2 deep), tibial spines rising 8-9 above them, a
tibial tuberosity and a 25 mm shaft. Fibular head 22 x 20 x 24 with its apex 9 below the
lateral plateau, posterolateral, 1.5 from the tibia; shaft diameter 12-13. Patella 41 wide,
21 thick, 44 high, with a median ridge and lateral and medial facets matching the groove.
No posterior tibial slope and no varus/valgus: the femoral and tibial shafts are parallel
at zero flexion.

A left knee is the exact mirror image (world x -> -x) of the right knee with the same spec.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from scipy.spatial.transform import Rotation

from recon.volume import VolumeGrid
from registration.labels import LABELS
from sim.phantoms import sdf
from sim.phantoms.sdf import box_slices, layer_fractions

BONES: tuple[str, ...] = ("femur", "tibia", "fibula", "patella")

PATELLA_FEMUR_ROTATION_RATIO = 0.7
"""Patellar rotation relative to the femur (about the TEA), per degree of knee flexion."""

# -- canonical anatomy (right knee, scale 1, mm, bone-local frames) ------------------------

_MIN_SOFT_TISSUE_RADIUS_MM = 56.0
_ANKLE_HEIGHT_MM = 75.0  # ankle joint above the platform at scale 1
_FEMUR_LENGTH_MM = 430.0  # knee centre to femoral head centre
_FEMORAL_MECHANICAL_ANGLE_DEG = 6.0  # anatomical (shaft) to mechanical axis, head medial
_ENVELOPE_OFFSET_Y_MM = -4.0  # leg axis relative to the knee centre (anterior)

# femur: condyles are spindle tori about the TEA (x axis): (centre x, major, minor radius)
_MEDIAL_CONDYLE = (23.0, 11.5, 14.0)  # outer radius 25.5
_LATERAL_CONDYLE = (-23.0, 11.5, 14.0)  # outer radius 25.5: balanced joint gaps
_EPICONDYLE_TIP_X = (41.0, -41.0)  # medial, lateral
_EPICONDYLE_RADII = ((8.0, 13.0, 13.0), (7.0, 12.0, 12.0))
_GROOVE_X, _GROOVE_RHO = -2.0, 28.0  # trochlear groove: x, and facet apex distance from TEA
_GROOVE_ROUNDING = 3.0  # rounds the groove floor and the patellar ridge alike
_FACET_TAN = (math.tan(math.radians(22.0)), math.tan(math.radians(17.0)))  # lateral, medial
_TROCHLEA_SECTOR_DEG = (-25.0, 80.0)  # elevation above anterior, about the TEA
_NOTCH_HALF_WIDTH = 10.0
_NOTCH_ROOF_RADIUS = 8.0
_NOTCH_ROOF_POINT_YZ = (-10.0, -20.0)
_NOTCH_ROOF_DEG = 35.0  # Blumensaat's line to the femoral shaft axis
# tibia
_PLATEAU_X = (23.0, -23.0)  # medial, lateral concavity centres
_PLATEAU_BOWL_RADIUS = (60.0, 80.0)
_PLATEAU_TOP_Z = 2.0
# fibula, patella
_FIBULA_HEAD_IN_TIBIA = (-31.0, 20.0, -24.0)
_TIBIOFIBULAR_GAP_MM = 1.5
_PATELLA_RADII = (21.0, 13.0, 22.5)
_PATELLA_RIDGE_Y = 9.0
_PATELLA_ELEVATION_DEG = 10.0  # patella centre above anterior, about the TEA, at extension
# interior is marrow beyond this distance (mm, along local z in the given direction; 30 mm
# transition), cancellous bone before it
_MARROW_FROM_MM = {
    "femur": (80.0, 1.0),
    "tibia": (80.0, -1.0),
    "fibula": (50.0, -1.0),
    "patella": (np.inf, 1.0),
}


# -- attenuation ---------------------------------------------------------------------------

_ENERGIES_KEV = (50.0, 60.0, 70.0, 80.0, 100.0)
# Mass attenuation coefficients mu/rho (cm^2/g, coherent scattering included) from the NIST
# tables of Hubbell & Seltzer (NISTIR 5632, the XCOM photon cross-section database) at 50, 60,
# 80 and 100 keV; the 70 keV column is log-log interpolated between 60 and 80 keV.
_MASS_ATTENUATION_CM2_G: dict[str, tuple[float, ...]] = {
    "air": (0.2080, 0.1875, 0.1758, 0.1662, 0.1541),  # Air, Dry (near sea level)
    "water": (0.2269, 0.2059, 0.1937, 0.1837, 0.1707),  # Water, Liquid
    "fat": (0.2123, 0.1974, 0.1879, 0.1800, 0.1688),  # Adipose Tissue (ICRU-44)
    "muscle": (0.2262, 0.2048, 0.1924, 0.1823, 0.1693),  # Muscle, Skeletal (ICRU-44)
    "cortical_bone": (0.4242, 0.3148, 0.2616, 0.2229, 0.1855),  # Bone, Cortical (ICRU-44)
}
_DENSITY_G_CM3 = {
    "air": 1.205e-3,
    "water": 1.0,
    "fat": 0.95,
    "muscle": 1.05,
    "cortical_bone": 1.92,
    "marrow": 0.98,  # yellow marrow (ICRU-44); its composition is adipose-like
}
_CANCELLOUS_BONE_VOLUME_FRACTION = 0.18  # trabecular BV/TV of knee epiphyses, rest marrow


def attenuation_per_mm(energy_kev: float) -> dict[str, float]:
    """Linear attenuation coefficients (1/mm) of the phantom's materials at one energy.

    ``mu = (mu/rho) * rho / 10``. Table (NIST mu/rho, see the module source), giving at
    60 keV / 70 keV in 1/mm: air 2.26e-5 / 2.12e-5, water 0.02059 / 0.01937, soft tissue
    (skeletal muscle, 1.05 g/cm3) 0.02150 / 0.02020, fat (adipose, 0.95 g/cm3) 0.01875 /
    0.01785, cortical bone (1.92 g/cm3) 0.06044 / 0.05023, marrow (yellow marrow 0.98 g/cm3
    with adipose mu/rho) 0.01935 / 0.01841, cancellous bone (18 % cortical bone tissue, 82 %
    marrow by volume) 0.02674 / 0.02414.

    Args:
        energy_kev: effective energy, one of 50, 60, 70, 80, 100 keV.

    Returns:
        mu in 1/mm for "air", "water", "fat", "muscle", "cortical_bone", "marrow",
        "cancellous_bone".
    """
    if energy_kev not in _ENERGIES_KEV:
        raise ValueError(
            f"effective_energy_kev = {energy_kev!r} keV is not in the attenuation table; "
            f"available: {', '.join(f'{e:g}' for e in _ENERGIES_KEV)} keV"
        )
    k = _ENERGIES_KEV.index(energy_kev)
    mu = {m: v[k] * _DENSITY_G_CM3[m] / 10.0 for m, v in _MASS_ATTENUATION_CM2_G.items()}
    mu["marrow"] = _MASS_ATTENUATION_CM2_G["fat"][k] * _DENSITY_G_CM3["marrow"] / 10.0
    f = _CANCELLOUS_BONE_VOLUME_FRACTION
    mu["cancellous_bone"] = f * mu["cortical_bone"] + (1.0 - f) * mu["marrow"]
    return mu


# -- specification -------------------------------------------------------------------------


class KneePhantomSpec(BaseModel):
    """Parameters of the digital knee phantom (see ``configs/phantoms/knee.yaml``)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    scale: float = Field(1.0, ge=0.7, le=1.3, description="bone size factor, 1.0 = adult")
    side: Literal["right", "left"] = Field("right", description="which knee")
    flexion_deg: float = Field(
        0.0, ge=-10.0, le=90.0, description="knee flexion, degrees; 0 = straight standing"
    )
    joint_line_height_mm: float = Field(
        480.0, ge=300.0, le=700.0, description="world z of the tibial plateau centre, mm"
    )
    cortical_thickness_mm: float = Field(1.5, ge=0.5, le=3.0, description="cortical shell, mm")
    joint_space_mm: float = Field(
        4.0, ge=2.0, le=8.0, description="bone-to-bone gap at the joints (cartilage), mm"
    )
    soft_tissue_radius_mm: float = Field(
        60.0, ge=45.0, le=120.0, description="radius of the leg at the knee, mm"
    )
    fat_thickness_mm: float = Field(8.0, ge=0.0, le=30.0, description="subcutaneous fat layer, mm")
    effective_energy_kev: float = Field(
        70.0, ge=50.0, le=100.0, description="effective X-ray energy of the attenuation, keV"
    )

    @field_validator("effective_energy_kev")
    @classmethod
    def _energy_in_table(cls, value: float) -> float:
        attenuation_per_mm(value)
        return value

    @model_validator(mode="after")
    def _leg_covers_bones(self) -> KneePhantomSpec:
        needed = _MIN_SOFT_TISSUE_RADIUS_MM * self.scale
        if self.soft_tissue_radius_mm < needed:
            raise ValueError(
                f"soft_tissue_radius_mm = {self.soft_tissue_radius_mm:g} mm must be >= "
                f"{needed:.1f} mm (= {_MIN_SOFT_TISSUE_RADIUS_MM:g} mm x scale) to cover the bones"
            )
        return self


def _femur_canonical(q: np.ndarray) -> np.ndarray:
    """Shaft, metaphyseal flare, condyles (tori about the TEA), epicondyles, trochlea, notch."""
    d = sdf.capsule(q, (0.0, -2.0, 30.0), (0.0, -2.0, 400.0), 13.0)
    d = sdf.smooth_union(d, sdf.ellipsoid(q, (0.0, 2.0, 28.0), (32.0, 20.0, 48.0)), 24.0)
    for x, major, minor in (_MEDIAL_CONDYLE, _LATERAL_CONDYLE):
        d = sdf.smooth_union(d, sdf.torus_x(q, (x, 0.0, 0.0), major, minor), 8.0)
    for tip, radii in zip(_EPICONDYLE_TIP_X, _EPICONDYLE_RADII, strict=True):
        center = (tip - math.copysign(radii[0], tip), 0.0, 0.0)
        d = sdf.smooth_union(d, sdf.ellipsoid(q, center, radii), 8.0)
    d = sdf.smooth_union(d, _trochlea(q), 8.0)
    return sdf.smooth_subtraction(d, _notch(q), 5.0)


def _trochlea(q: np.ndarray) -> np.ndarray:
    """Anterior femur: a V-grooved profile revolved about the TEA over an angular sector."""
    x, ant, up = q[:, 0], -q[:, 1], q[:, 2]
    rho = np.hypot(ant, up)
    dx = x - _GROOVE_X
    tan = np.where(dx < 0.0, _FACET_TAN[0], _FACET_TAN[1])
    # V-shaped facets with a rounded groove floor (smooth |dx|)
    groove = (rho - _GROOVE_RHO - np.hypot(dx, _GROOVE_ROUNDING) * tan) / np.sqrt(1.0 + tan * tan)
    body = sdf.ellipsoid(np.stack((x, rho), axis=1), (_GROOVE_X, 10.0), (24.0, 26.0))
    body = sdf.smooth_intersection(body, groove, 4.0)
    lo, hi = (math.radians(a) for a in _TROCHLEA_SECTOR_DEG)
    sector = np.maximum(
        ant * math.sin(lo) - up * math.cos(lo), up * math.cos(hi) - ant * math.sin(hi)
    )
    return sdf.smooth_intersection(body, sector, 8.0)


def _notch(q: np.ndarray) -> np.ndarray:
    """Intercondylar notch: the band between the condyles posterior-distal to the roof."""
    a = math.radians(_NOTCH_ROOF_DEG)
    y0, z0 = _NOTCH_ROOF_POINT_YZ
    into_notch = (q[:, 1] - y0) * math.cos(a) - (q[:, 2] - z0) * math.sin(a)
    # an arch: a slot of half width w (widening toward its opening) with a round roof of
    # radius r, in the plane across Blumensaat's line
    r = _NOTCH_ROOF_RADIUS
    dx = np.abs(q[:, 0]) - (_NOTCH_HALF_WIDTH + 0.15 * np.maximum(into_notch, 0.0) - r)
    dt = r - into_notch
    outside = np.hypot(np.maximum(dx, 0.0), np.maximum(dt, 0.0))
    return outside + np.minimum(np.maximum(dx, dt), 0.0) - r


def _tibia_canonical(q: np.ndarray, length: float) -> np.ndarray:
    """Tibia without the joint-space carve; ``length`` = plateau to ankle, mm.

    Head (flat-topped ellipsoid), metaphysis, shaft, distal flare, tuberosity, plateau
    concavities, posterior intercondylar fossa and the two tibial spines.
    """
    head = sdf.ellipsoid(q, (0.0, 1.0, -4.0), (39.0, 25.0, 30.0))
    head = sdf.smooth_intersection(head, q[:, 2] - _PLATEAU_TOP_Z, 6.0)
    d = sdf.smooth_union(head, sdf.ellipsoid(q, (0.0, 3.0, -40.0), (25.0, 21.0, 38.0)), 10.0)
    shaft = sdf.capsule(q, (0.0, 4.0, -45.0), (0.0, 4.0, 25.0 - length), 12.5)
    d = sdf.smooth_union(d, shaft, 12.0)
    d = sdf.smooth_union(d, sdf.ellipsoid(q, (0.0, 4.0, 12.0 - length), (21.0, 17.0, 20.0)), 12.0)
    d = sdf.smooth_union(d, sdf.ellipsoid(q, (-3.0, -17.0, -32.0), (10.0, 7.0, 16.0)), 10.0)
    for x, r in zip(_PLATEAU_X, _PLATEAU_BOWL_RADIUS, strict=True):
        d = sdf.smooth_subtraction(d, sdf.sphere(q, (x, 0.0, r), r), 2.0)
    d = sdf.smooth_subtraction(d, sdf.sphere(q, (0.0, 27.0, -3.0), 9.0), 3.0)
    d = sdf.smooth_union(d, sdf.ellipsoid(q, (4.0, 1.0, 2.0), (3.5, 8.0, 7.5)), 3.0)
    return sdf.smooth_union(d, sdf.ellipsoid(q, (-4.0, 3.0, 1.5), (3.5, 7.0, 6.5)), 3.0)


def _fibula_canonical(q: np.ndarray, ankle_z: float) -> np.ndarray:
    """Fibula without the tibiofibular carve; ``ankle_z``: local z of the ankle joint, mm."""
    d = sdf.ellipsoid(q, (0.0, 0.0, 0.0), (11.0, 10.0, 12.0))
    d = sdf.smooth_union(d, sdf.sphere(q, (-3.0, 3.0, 10.0), 5.0), 4.0)
    tip = (2.0, -6.0, ankle_z + 4.0)
    d = sdf.smooth_union(d, sdf.tapered_capsule(q, (0.0, 0.0, -8.0), tip, 6.0, 6.5), 8.0)
    return sdf.smooth_union(d, sdf.ellipsoid(q, tip, (9.0, 11.0, 18.0)), 8.0)


def _patella_canonical(q: np.ndarray) -> np.ndarray:
    """Ellipsoid cut posteriorly by lateral and medial facets meeting at a rounded ridge."""
    body = sdf.ellipsoid(q, (0.0, 0.0, 0.0), _PATELLA_RADII)
    tan = np.where(q[:, 0] < 0.0, _FACET_TAN[0], _FACET_TAN[1])
    facets = (q[:, 1] - _PATELLA_RIDGE_Y + np.hypot(q[:, 0], _GROOVE_ROUNDING) * tan) / np.sqrt(
        1.0 + tan * tan
    )
    return sdf.smooth_intersection(body, facets, 2.0)


# -- poses -----------------------------------------------------------------------------------


def _rot_x(deg: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("x", deg, degrees=True).as_matrix()
    return T


def _trans(v) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = v
    return T


_MIRROR = np.diag([-1.0, 1.0, 1.0, 1.0])


def _apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return np.asarray(points, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]


class _Knee:
    """One phantom instance: poses, local SDFs and world boxes for a spec."""

    def __init__(self, spec: KneePhantomSpec) -> None:
        self.spec = spec
        s = spec.scale
        self.s = s
        self.sign = 1.0 if spec.side == "right" else -1.0  # canonical medial = +x local
        self.tibia_length = spec.joint_line_height_mm - _ANKLE_HEIGHT_MM * s
        self.tea_height = (_MEDIAL_CONDYLE[1] + _MEDIAL_CONDYLE[2]) * s + spec.joint_space_mm
        rho_c = (_GROOVE_RHO + _PATELLA_RIDGE_Y) * s + spec.joint_space_mm
        e = math.radians(_PATELLA_ELEVATION_DEG)
        flex = spec.flexion_deg
        canonical = {"tibia": _trans((0.0, 0.0, spec.joint_line_height_mm))}
        T_tibia_femur0 = _trans((0.0, 0.0, self.tea_height))
        canonical["femur"] = canonical["tibia"] @ T_tibia_femur0 @ _rot_x(-flex)
        T_femur_patella0 = _trans(
            (_GROOVE_X * s, -rho_c * math.cos(e), rho_c * math.sin(e))
        ) @ _rot_x(-_PATELLA_ELEVATION_DEG)
        canonical["patella"] = (
            canonical["femur"] @ _rot_x(PATELLA_FEMUR_ROTATION_RATIO * flex) @ T_femur_patella0
        )
        canonical["fibula"] = canonical["tibia"] @ _trans(np.multiply(_FIBULA_HEAD_IN_TIBIA, s))
        mirror = _MIRROR if spec.side == "left" else np.eye(4)
        self.poses = {k: mirror @ canonical[k] @ mirror for k in BONES}
        self.T_femur0_tibia = np.linalg.inv(mirror @ T_tibia_femur0 @ mirror)
        self.T_tibia_fibula = np.linalg.inv(self.poses["tibia"]) @ self.poses["fibula"]

    def canonical(self, local: np.ndarray) -> np.ndarray:
        """Local points of this knee -> canonical right-knee points at scale 1."""
        return np.asarray(local, dtype=np.float64) * np.array([self.sign, 1.0, 1.0]) / self.s

    def femur(self, local: np.ndarray) -> np.ndarray:
        return self.s * _femur_canonical(self.canonical(local))

    def tibia_uncarved(self, local: np.ndarray) -> np.ndarray:
        return self.s * _tibia_canonical(self.canonical(local), self.tibia_length / self.s)

    def tibia(self, local: np.ndarray) -> np.ndarray:
        """Tibia minus the femur (at zero flexion) dilated by the joint space."""
        d = self.tibia_uncarved(local)
        top = local[:, 2] > -30.0 * self.s
        if np.any(top):
            femur = self.femur(_apply(self.T_femur0_tibia, local[top]))
            d[top] = np.maximum(d[top], self.spec.joint_space_mm - femur)
        return d

    def fibula(self, local: np.ndarray) -> np.ndarray:
        """Fibula minus the tibia dilated by the tibiofibular gap."""
        ankle_z = -self.tibia_length / self.s - _FIBULA_HEAD_IN_TIBIA[2]
        d = self.s * _fibula_canonical(self.canonical(local), ankle_z)
        tibia = self.tibia_uncarved(_apply(self.T_tibia_fibula, local))
        return np.maximum(d, _TIBIOFIBULAR_GAP_MM * self.s - tibia)

    def patella(self, local: np.ndarray) -> np.ndarray:
        return self.s * _patella_canonical(self.canonical(local))

    def bone_sdf(self, name: str, local: np.ndarray) -> np.ndarray:
        return getattr(self, name)(local)

    def local_box(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Local axis-aligned box (lo, hi) mm enclosing a bone."""
        s, lt = self.s, self.tibia_length
        lo, hi = {
            "femur": ((-46.0 * s, -42.0 * s, -30.0 * s), (46.0 * s, 34.0 * s, 415.0 * s)),
            "tibia": ((-44.0 * s, -32.0 * s, -lt - 15.0 * s), (44.0 * s, 30.0 * s, 14.0 * s)),
            "fibula": ((-16.0 * s, -20.0 * s, -lt - 15.0 * s), (16.0 * s, 16.0 * s, 20.0 * s)),
            "patella": ((-23.0 * s, -13.0 * s, -24.0 * s), (23.0 * s, 13.0 * s, 24.0 * s)),
        }[name]
        return np.array(lo), np.array(hi)

    def world_box(self, name: str, margin: float) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = self.local_box(name)
        corners = np.stack(np.meshgrid(*zip(lo, hi, strict=True)), axis=-1).reshape(-1, 3)
        w = _apply(self.poses[name], corners)
        return w.min(axis=0) - margin, w.max(axis=0) + margin

    def _envelope_segments(self) -> list[tuple[np.ndarray, np.ndarray, float, float]]:
        """(a, b, radius_a, radius_b) world mm of the shank and thigh tapered capsules."""
        r = self.spec.soft_tissue_radius_mm
        y = _ENVELOPE_OFFSET_Y_MM * self.s
        tibia, femur = self.poses["tibia"], self.poses["femur"]
        knee_in_tibia = (0.0, y, self.tea_height)
        platform_in_tibia = (0.0, y, -self.spec.joint_line_height_mm)
        thigh_top = (0.0, y, 450.0 * self.s)
        return [
            (_apply(tibia, knee_in_tibia), _apply(tibia, platform_in_tibia), r, 0.6 * r),
            (_apply(femur, (0.0, y, 0.0)), _apply(femur, thigh_top), r, 1.4 * r),
        ]

    def envelope(self, world: np.ndarray) -> np.ndarray:
        """Skin surface SDF (world points): shank and thigh, above the platform."""
        (a0, b0, ra0, rb0), (a1, b1, ra1, rb1) = self._envelope_segments()
        d = sdf.smooth_union(
            sdf.tapered_capsule(world, a0, b0, ra0, rb0),
            sdf.tapered_capsule(world, a1, b1, ra1, rb1),
            20.0,
        )
        return np.maximum(d, -world[:, 2])

    def envelope_box(self, margin: float) -> tuple[np.ndarray, np.ndarray]:
        ends = [(p, r) for a, b, ra, rb in self._envelope_segments() for p, r in ((a, ra), (b, rb))]
        lo = np.min([p - r for p, r in ends], axis=0) - margin
        hi = np.max([p + r for p, r in ends], axis=0) + margin
        lo[2] = max(lo[2], -margin)
        return lo, hi

    def marrow_weight(self, name: str, local_z: np.ndarray) -> np.ndarray:
        """Share of marrow (vs cancellous bone) inside a bone: 1 in the diaphyseal canals."""
        start, direction = _MARROW_FROM_MM[name]
        return np.clip((direction * local_z - start * self.s) / (30.0 * self.s), 0.0, 1.0)


# -- public API ------------------------------------------------------------------------------


def knee_bone_poses(spec: KneePhantomSpec) -> dict[str, np.ndarray]:
    """World poses ``T_world_body`` (4x4) of "femur", "tibia", "fibula" and "patella".

    See the module docstring for the bone-local frames. The femur's rotation relative to the
    tibia is ``flexion_deg`` about the TEA (its local x axis).

    Args:
        spec: The knee phantom.
    """
    return {k: v.copy() for k, v in _Knee(spec).poses.items()}


def knee_landmarks(spec: KneePhantomSpec) -> dict[str, np.ndarray]:
    """Landmarks known by construction, world mm (points) or unit vectors ("..._axis", normal).

    Keys: ``medial_epicondyle``, ``lateral_epicondyle`` (TEA end points), ``knee_center``
    (TEA midpoint), ``medial_condyle_lowest``, ``lateral_condyle_lowest`` (lowest femoral
    points at this flexion: the condyles are tori about the TEA, so these do not move),
    ``tibial_plateau_center``, ``tibial_plateau_normal``, ``medial_plateau_lowest``,
    ``lateral_plateau_lowest``, ``femoral_head_center``, ``femoral_mechanical_axis`` (knee
    centre to femoral head), ``femoral_anatomical_axis`` (shaft, proximal), ``ankle_center``,
    ``tibial_mechanical_axis`` (ankle centre to plateau centre), ``patella_center``.

    Args:
        spec: The knee phantom.
    """
    k = _Knee(spec)
    s = k.s
    femur, tibia = k.poses["femur"], k.poses["tibia"]

    def local(point) -> np.ndarray:
        return np.asarray(point, dtype=np.float64) * np.array([k.sign, 1.0, 1.0]) * s

    head_angle = math.radians(_FEMORAL_MECHANICAL_ANGLE_DEG)
    head = local(
        (math.sin(head_angle) * _FEMUR_LENGTH_MM, 0.0, math.cos(head_angle) * _FEMUR_LENGTH_MM)
    )
    lowest = {}
    for name, (x, major, minor) in zip(
        ("medial", "lateral"), (_MEDIAL_CONDYLE, _LATERAL_CONDYLE), strict=True
    ):
        # the torus is invariant under rotation about the TEA: its lowest point in the
        # world is straight below the tube centre at the TEA's height
        lowest[name] = (
            femur[:3, 3]
            + femur[:3, 0] * (k.sign * x * s)
            - np.array([0.0, 0.0, (major + minor) * s])
        )
    out = {
        "medial_epicondyle": _apply(femur, local((_EPICONDYLE_TIP_X[0], 0.0, 0.0))),
        "lateral_epicondyle": _apply(femur, local((_EPICONDYLE_TIP_X[1], 0.0, 0.0))),
        "knee_center": femur[:3, 3].copy(),
        "medial_condyle_lowest": lowest["medial"],
        "lateral_condyle_lowest": lowest["lateral"],
        "tibial_plateau_center": tibia[:3, 3].copy(),
        "tibial_plateau_normal": tibia[:3, 2].copy(),
        "medial_plateau_lowest": _apply(tibia, local((_PLATEAU_X[0], 0.0, 0.0))),
        "lateral_plateau_lowest": _apply(tibia, local((_PLATEAU_X[1], 0.0, 0.0))),
        "femoral_head_center": _apply(femur, head),
        "femoral_anatomical_axis": femur[:3, 2].copy(),
        "ankle_center": _apply(tibia, (0.0, 0.0, -k.tibia_length)),
        "tibial_mechanical_axis": tibia[:3, 2].copy(),
        "patella_center": k.poses["patella"][:3, 3].copy(),
    }
    axis = out["femoral_head_center"] - out["knee_center"]
    out["femoral_mechanical_axis"] = axis / np.linalg.norm(axis)
    return out


def knee_sdf(spec: KneePhantomSpec, part: str, points_mm: np.ndarray) -> np.ndarray:
    """Signed distance (mm, negative inside) of world points to a bone or to the skin.

    Args:
        spec: the phantom.
        part: "femur", "tibia", "fibula", "patella" or "skin".
        points_mm: world points (N, 3).

    Returns:
        (N,) signed distances, exact to first order near the surface.
    """
    k = _Knee(spec)
    pts = np.atleast_2d(np.asarray(points_mm, dtype=np.float64))
    if part == "skin":
        return k.envelope(pts)
    if part not in BONES:
        raise ValueError(f"part must be one of {(*BONES, 'skin')}, got {part!r}")
    return k.bone_sdf(part, _apply(np.linalg.inv(k.poses[part]), pts))


def label_points(spec: KneePhantomSpec, points_mm: np.ndarray) -> np.ndarray:
    """:data:`registration.labels.LABELS` value of world points.

    Args:
        spec: The knee phantom.
        points_mm: World points (mm), shape (N, 3).

    Returns:
        The label of each point, uint8 (N,).
    """
    pts = np.atleast_2d(np.asarray(points_mm, dtype=np.float64))
    labels = np.where(knee_sdf(spec, "skin", pts) < 0.0, LABELS["soft_tissue"], 0)
    for name in BONES:
        labels = np.where(knee_sdf(spec, name, pts) < 0.0, LABELS[name], labels)
    return labels.astype(np.uint8)


def knee_grid(
    spec: KneePhantomSpec,
    spacing_mm: float = 1.0,
    margin_mm: float = 10.0,
    height_mm: float | None = None,
    below_mm: float | None = None,
) -> VolumeGrid:
    """Default field of view: the leg's cross-section plus ``margin_mm`` on each side, and
    ``height_mm`` (default 160 mm x scale) from ``below_mm`` (default 70 mm x scale) below the
    joint line.

    At scale 1 with the default spec this is 140 x 140 x 160 mm.

    Args:
        spec: The knee phantom.
        spacing_mm: Voxel size (mm).
        margin_mm: Margin around the leg's cross-section (mm).
        height_mm: Height of the grid (mm); 160 mm x the phantom's scale when ``None``.
        below_mm: How far the grid reaches below the joint line (mm); 70 mm x scale when
            ``None``.
    """
    if not (spacing_mm > 0 and margin_mm >= 0):
        raise ValueError(f"need spacing_mm > 0 and margin_mm >= 0, got {spacing_mm}, {margin_mm}")
    height = 160.0 * spec.scale if height_mm is None else float(height_mm)
    below = 70.0 * spec.scale if below_mm is None else float(below_mm)
    side = 2.0 * (spec.soft_tissue_radius_mm + margin_mm)
    n_xy = math.ceil(side / spacing_mm)
    n_z = math.ceil(height / spacing_mm)
    center = (
        0.0,
        _ENVELOPE_OFFSET_Y_MM * spec.scale,
        spec.joint_line_height_mm - below + 0.5 * height,
    )
    return VolumeGrid.centered((n_xy, n_xy, n_z), spacing_mm, center)


def rasterize_knee(
    spec: KneePhantomSpec, grid: VolumeGrid, supersample: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """Labels and linear attenuation of the phantom on a grid, with partial volume.

    Each voxel's attenuation is the mean over ``supersample**3`` sub-voxel samples (resolved
    only near surfaces); its label is the bone covering at least half of it, else soft
    tissue if the skin covers at least half of it, else air.

    Args:
        spec: the phantom.
        grid: voxel grid, world mm.
        supersample: sub-samples per voxel edge, >= 1.

    Returns:
        labels uint8 [z, y, x] (registration.labels.LABELS) and mu float32 [z, y, x], 1/mm at
        ``spec.effective_energy_kev``.
    """
    k = _Knee(spec)
    mu_of = attenuation_per_mm(spec.effective_energy_kev)
    margin = float(np.linalg.norm(grid.spacing_mm))
    shell = (0.0, -spec.cortical_thickness_mm)
    labels = np.zeros(grid.shape, dtype=np.uint8)
    bone = np.zeros(grid.shape, dtype=np.float32)
    mu = np.zeros(grid.shape, dtype=np.float32)
    ax, ay, az = grid.axes_mm()
    for name in BONES:
        sl = box_slices(grid, *k.world_box(name, margin))
        if sl is None:
            continue
        T = k.poses[name]
        outer, inner = layer_fractions(
            lambda p, n=name: k.bone_sdf(n, p), T, grid, shell, supersample, sl
        )
        local_z = (
            (ax[sl[2]][None, None, :] - T[0, 3]) * T[0, 2]
            + (ay[sl[1]][None, :, None] - T[1, 3]) * T[1, 2]
            + (az[sl[0]][:, None, None] - T[2, 3]) * T[2, 2]
        )
        w = k.marrow_weight(name, local_z)
        mu_inner = w * mu_of["marrow"] + (1.0 - w) * mu_of["cancellous_bone"]
        mu[sl] += (outer - inner) * mu_of["cortical_bone"] + inner * mu_inner
        bone[sl] += outer
        labels[sl][outer >= 0.5] = LABELS[name]
    mu += (1.0 - bone) * mu_of["air"]
    sl = box_slices(grid, *k.envelope_box(margin))
    if sl is not None:
        skin, muscle = layer_fractions(
            k.envelope, np.eye(4), grid, (0.0, -spec.fat_thickness_mm), supersample, sl
        )
        soft = (skin - muscle) * mu_of["fat"] + muscle * mu_of["muscle"] - skin * mu_of["air"]
        mu[sl] += (1.0 - bone[sl]) * soft
        block = labels[sl]
        block[(block == 0) & (skin >= 0.5)] = LABELS["soft_tissue"]
    return labels, mu
