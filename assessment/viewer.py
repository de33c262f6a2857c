"""The report's 3D view: the bones (or implant components) moving through the frames, with the
tibial plateau (TP) plane and the lowest medial and lateral condyle points, drawn by three.js
in the page itself.

three.js (MIT, pinned at :data:`THREE_VERSION`) is vendored in ``assessment/vendor/`` with
its licence and inlined in the report, which loads it from the page's own text through a blob
URL: the page makes no request. Each mesh is decimated to at most :data:`MAX_FACES` faces
and embedded as base64 little-endian float32 vertices and uint32 faces; the poses go as
column-major 4x4 matrices per frame (three.js's order).
"""

from __future__ import annotations

import base64
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from assessment.kinematics import MIRROR
from assessment.knee import KneeAssessment
from registration.meshes import decimated
from registration.overlays import COLOURS as OUTLINE_COLOURS
from registration.roles import KNOWN_ROLES, playing

VENDOR = Path(__file__).parent / "vendor"
THREE_JS = VENDOR / "three.module.min.js"
THREE_VERSION = "0.160.1"
"""The vendored three.js (npm ``three``), checked against the file's banner."""

MAX_FACES = 6000
"""Faces per mesh in the 3D view (quadric decimation), a few hundred kB per bone."""
PLANE_HALF_MM = 32.0
"""Half the side of the square drawn for the TP plane, mm."""
COLORS = {
    role: "#" + "".join(f"{round(0.6 * c + 0.4 * 255):02x}" for c in rgb)
    for role, rgb in OUTLINE_COLOURS.items()
}
"""Colours of the bodies playing each role: the overlays' outline colours, lightened for
shading; others grey."""
CONDYLE_COLORS = ("#1f77b4", "#ff7f0e")
"""Medial and lateral condyle points: the plots' medial and lateral colours."""


@dataclass(frozen=True)
class MotionScene:
    """What the 3D view shows, world mm (the static scan's frame, LPS).

    Attributes:
        frames: The frame numbers (F,).
        meshes: Per body its surface in the static pose: vertices (V, 3) and faces (T, 3).
        poses: Per body ``T_world_body`` in every frame (F, 4, 4).
        plane: The TP plane's square in the static pose (4, 3 corners), moved by ``tibia``.
        tibia: The body that carries the plane.
        condyles: The lowest medial and lateral condyle points in every frame (F, 2, 3);
            NaN in a frame not measured.
        side: "right" or "left".
    """

    frames: np.ndarray
    meshes: dict[str, tuple[np.ndarray, np.ndarray]]
    poses: dict[str, np.ndarray]
    plane: np.ndarray
    tibia: str
    condyles: np.ndarray
    side: str


def motion_scene(
    assessment: KneeAssessment,
    frames: np.ndarray,
    poses: dict[str, np.ndarray],
    meshes: dict[str, trimesh.Trimesh],
) -> MotionScene:
    """The 3D view's scene of an assessed motion.

    Args:
        assessment: The assessment (its kinematics' frames are the scene's).
        frames: The frame numbers of ``poses`` (F',), a superset of the assessed ones.
        poses: Per body ``T_world_body`` in each of ``frames`` (F', 4, 4).
        meshes: Per body its surface in the static pose, world mm.

    Returns:
        The scene, meshes decimated to :data:`MAX_FACES`.
    """
    kin = assessment.kinematics
    index = {int(f): i for i, f in enumerate(frames)}
    rows = [index[int(f)] for f in kin.frames]
    (tibia,) = playing(poses, "tibia")
    anatomy = assessment.tibia  # of the mirrored knee for a left one
    medial, anterior = anatomy.plane_axes
    normal, center = anatomy.plateau_normal, anatomy.plateau_center_mm
    mirror = MIRROR[:3, :3] if kin.side == "left" else np.eye(3)
    corners = [
        center + PLANE_HALF_MM * (a * medial + b * anterior)
        for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))
    ]
    condyles = np.empty((len(rows), 2, 3))
    tibia_poses = poses[tibia][rows]
    sides = (
        (kin.medial_point_mm, kin.medial_distance_mm),
        (kin.lateral_point_mm, kin.lateral_distance_mm),
    )
    for j, (point, distance) in enumerate(sides):
        local = center + point[:, :1] * medial + point[:, 1:] * anterior
        static = (local + distance[:, None] * normal) @ mirror.T
        condyles[:, j] = np.einsum("fij,fj->fi", tibia_poses[:, :3, :3], static)
        condyles[:, j] += tibia_poses[:, :3, 3]
    shown = {}
    for name, mesh in meshes.items():
        small = decimated(mesh, MAX_FACES)
        shown[name] = (
            np.asarray(small.vertices, dtype=np.float32),
            np.asarray(small.faces, dtype=np.uint32),
        )
    return MotionScene(
        np.asarray(kin.frames),
        shown,
        {name: poses[name][rows] for name in meshes},
        np.array(corners) @ mirror.T,
        tibia,
        condyles,
        kin.side,
    )


def view_direction(side: str) -> np.ndarray:
    """Unit vector from the knee towards the 3D view's eye: anterolateral, a little from
    above (world LPS, where +x is the patient's left).

    Args:
        side: "right" or "left": the knee.

    Returns:
        The direction (3,).
    """
    lateral = -1.0 if side == "right" else 1.0
    direction = np.array([lateral, -0.7, 0.3])
    return direction / np.linalg.norm(direction)


def _b64(array: np.ndarray, dtype: str) -> str:
    """``array`` as base64 of its little-endian bytes of ``dtype``."""
    return base64.b64encode(np.ascontiguousarray(array, dtype=dtype).tobytes()).decode("ascii")


def json_points(points: np.ndarray, decimals: int) -> list[list[float] | None]:
    """Points (N, D) as JSON lists rounded to ``decimals``, None for a point with a NaN (a
    frame not measured: the page hides its mark).

    Args:
        points: The points.
        decimals: Decimals kept.
    """
    return [
        np.round(p, decimals).tolist() if np.isfinite(p).all() else None
        for p in np.asarray(points, dtype=np.float64)
    ]


def scene_json(scene: MotionScene) -> str:
    """The scene as the view's JSON: bodies (base64 arrays, colour, column-major poses), the
    plane's corners and carrier, the condyle points per frame, and where to look from.

    Args:
        scene: The scene (:func:`motion_scene`).

    Returns:
        Compact JSON text.
    """
    bodies = []
    for name, (vertices, faces) in scene.meshes.items():
        bodies.append(
            {
                "name": name,
                "color": COLORS.get(KNOWN_ROLES.get(name), "#b0b0b0"),
                "vertices": _b64(vertices, "<f4"),
                "faces": _b64(faces, "<u4"),
                "poses": np.round(scene.poses[name].transpose(0, 2, 1).reshape(-1, 16), 4).tolist(),
            }
        )
    points = np.concatenate([v for v, _ in scene.meshes.values()]).astype(np.float64)
    center = 0.5 * (points.min(axis=0) + points.max(axis=0))
    payload = {
        "bodies": bodies,
        "plane": {
            "corners": np.round(scene.plane, 3).tolist(),
            "carrier": scene.tibia,
        },
        "condyles": {
            "colors": list(CONDYLE_COLORS),
            "points": [json_points(frame, 3) for frame in scene.condyles],
        },
        "center": np.round(center, 3).tolist(),
        "radius": round(float(np.linalg.norm(points.max(axis=0) - points.min(axis=0))) / 2, 3),
        "from": view_direction(scene.side).round(4).tolist(),
    }
    return json.dumps(payload, separators=(",", ":"))


def three_js() -> str:
    """The vendored three.js module's text (ValueError if it is not :data:`THREE_VERSION`)."""
    text = THREE_JS.read_text(encoding="utf-8")
    release = THREE_VERSION.split(".")[1]
    if f'const t="{release}"' not in text[:400]:
        raise ValueError(f"{THREE_JS}: not three.js r{release} ({THREE_VERSION})")
    return text


_VIEW_JS = """
(async () => {
  const el = (id) => document.getElementById(id);
  const data = JSON.parse(el('scene-data').textContent);
  const source = new Blob([el('three-src').textContent], {type: 'text/javascript'});
  const THREE = await import(URL.createObjectURL(source));
  const canvas = el('view3d');
  const renderer = new THREE.WebGLRenderer({canvas, antialias: true, preserveDrawingBuffer: true});
  renderer.setPixelRatio(1);
  renderer.setSize(canvas.width, canvas.height, false);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0xffffff);
  const bytes = (b64) => Uint8Array.from(atob(b64), (c) => c.charCodeAt(0)).buffer;
  function placed(geometry, material) {
    const mesh = new THREE.Mesh(geometry, material);
    mesh.matrixAutoUpdate = false;
    scene.add(mesh);
    return mesh;
  }
  const carriers = {};
  const bodies = data.bodies.map((b) => {
    const g = new THREE.BufferGeometry();
    g.setAttribute('position', new THREE.BufferAttribute(new Float32Array(bytes(b.vertices)), 3));
    g.setIndex(new THREE.BufferAttribute(new Uint32Array(bytes(b.faces)), 1));
    g.computeVertexNormals();
    const material = new THREE.MeshLambertMaterial({color: b.color, side: THREE.DoubleSide});
    carriers[b.name] = b.poses;
    return {mesh: placed(g, material), poses: b.poses};
  });
  const plane = new THREE.BufferGeometry();
  const c = data.plane.corners;
  plane.setAttribute('position', new THREE.BufferAttribute(new Float32Array(
    [...c[0], ...c[1], ...c[2], ...c[0], ...c[2], ...c[3]]), 3));
  bodies.push({
    mesh: placed(plane, new THREE.MeshBasicMaterial({
      color: 0x3d8b40, transparent: true, opacity: 0.35, side: THREE.DoubleSide,
      depthWrite: false})),
    poses: carriers[data.plane.carrier],
  });
  const points = data.condyles.colors.map((color) => {
    const ball = new THREE.Mesh(new THREE.SphereGeometry(3, 16, 12),
                                new THREE.MeshBasicMaterial({color, depthTest: false}));
    ball.renderOrder = 1;  // drawn over the bones: the points lie on the condyles' surface
    scene.add(ball);
    return ball;
  });
  const camera = new THREE.PerspectiveCamera(30, canvas.width / canvas.height,
                                             data.radius / 20, data.radius * 40);
  camera.up.set(0, 0, 1);
  scene.add(new THREE.AmbientLight(0xffffff, 0.9));
  const light = new THREE.DirectionalLight(0xffffff, 2.2);
  camera.add(light);
  scene.add(camera);
  const center = new THREE.Vector3(...data.center);
  let azimuth = Math.atan2(data.from[1], data.from[0]);
  let elevation = Math.asin(data.from[2]);
  let distance = data.radius * 3.4;
  let current = 0;
  const probe = location.hash.includes('probe');
  function draw() {
    const k = current;
    bodies.forEach((b) => {
      b.mesh.matrix.fromArray(b.poses[k]);
      b.mesh.matrixWorldNeedsUpdate = true;
    });
    points.forEach((ball, j) => {
      const at = data.condyles.points[k][j];  // null in a frame not measured
      ball.visible = at !== null;
      if (at !== null) ball.position.set(...at);
    });
    camera.position.set(
      center.x + distance * Math.cos(elevation) * Math.cos(azimuth),
      center.y + distance * Math.cos(elevation) * Math.sin(azimuth),
      center.z + distance * Math.sin(elevation));
    camera.lookAt(center);
    renderer.render(scene, camera);
    document.body.dataset.view3dFrame = String(k);
    if (probe) document.body.dataset.view3d = canvas.toDataURL('image/png');
  }
  let drag = null;
  canvas.addEventListener('pointerdown', (e) => { drag = [e.clientX, e.clientY]; });
  window.addEventListener('pointerup', () => { drag = null; });
  canvas.addEventListener('pointermove', (e) => {
    if (drag === null) return;
    azimuth -= 0.01 * (e.clientX - drag[0]);
    elevation = Math.max(-1.5, Math.min(1.5, elevation + 0.01 * (e.clientY - drag[1])));
    drag = [e.clientX, e.clientY];
    draw();
  });
  canvas.addEventListener('wheel', (e) => {
    e.preventDefault();
    distance *= Math.exp(0.001 * e.deltaY);
    draw();
  }, {passive: false});
  window.reportMotion.listen((k) => { current = k; draw(); });
})();
"""


def view_html(scene: MotionScene) -> str:
    """The 3D view's canvas, its data and its code (three.js inlined), for the report.

    Args:
        scene: The scene (:func:`motion_scene`).

    Returns:
        HTML: the canvas and three scripts (the data, three.js as text, the view's module).
    """
    data = scene_json(scene).replace("</", "<\\/")  # no end of the script in its text
    return f"""<canvas id="view3d" width="640" height="520"
 title="Drag to turn, scroll to zoom"></canvas>
<script type="application/json" id="scene-data">{data}</script>
<script type="text/plain" id="three-src">{three_js()}</script>
<script type="module">{_VIEW_JS}</script>
"""
