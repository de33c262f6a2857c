"""Benchmark: a scan on the simulated backend, its overhead per view, the UR backend against
the protocol-level fake controllers, and the volume reconstructed during the scan.

The simulated scan is the 360-view knee protocol (configs/protocols/knee_reverse_spiral_360.yaml,
a two-pass reverse spiral) read out 2x2 binned to 512^2, on the knee phantom rasterised at 1 mm,
reconstructed while it acquires (study.live_recon) onto the recon stage's box (140 x 140 x 320
mm) at 0.72 mm, about 256^3 voxels. Its clock is virtual: the wall time is the software's own
(planning, rasterising, rendering every view, the state machine, storage, the reconstruction
competing for the same two cores).

- ``per_view_overhead_ms``: wall time per view between the first and the last stored view,
  less the simulated panel's image formation (the phantom's projection and its quantum noise,
  ``SimDetector.read_frame`` timed around each call): the state machine, the other device
  models, the conversion to line integrals and the storage, on cores the reconstruction's
  and the recording's worker threads share.
  A view's storage runs alongside the next view's exposure and image formation
  (scanner.scan.VIEWS_STORING_AT_A_PULSE): on two cores its CPU then slows the rendering,
  which this figure leaves out; ``projections_per_s`` counts everything.
- ``storage_wait_ms``: of that, the exposure loop's mean wait per view for earlier views' files
  to be on disk (written, fsynced, renamed) before the next pulse: all but the view before.
- ``disk_view_store_ms``: the same storage of one view's files (two images of the panel and
  their record, :meth:`scanner.study_folder.Study.write_with_record`) on the same disk with nothing
  else running, the median of 30, measured just before the scan: how fast the disk is today
  (the figures above move with it; this virtual disk took from 1.4 to 3.3 ms within an hour).
- ``recon_ready_after_last_view_s``: from the moment the last view is stored to the volume on
  disk (``recon/volume.mha`` written; the NIfTI, the DICOM series and the rest of the stage
  follow).
- ``offline_recon_s``: the same views reconstructed afterwards from the stored stack, as the
  recon stage does without a live reconstruction; ``streaming_max_abs_diff`` the largest
  voxel difference between the two volumes (1/mm), also relative to the volume's maximum.
- ``ur_fake_wall_s``: a 30-view scan of 64^2 through the UR backend (ur-rtde against two fake
  UR controllers, the stage and the generator over serial), the test suite's small scan.

Prints one JSON object. Usage: ``python bench/scan.py [--small]`` (``--small``: 90 views of
128^2 at 2 mm, to check the harness in a minute).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from recon.config import ScanProtocol, load_config, load_protocol  # noqa: E402
from recon.io import encode_projections, read_projections, read_volume  # noqa: E402
from scanner.detector_calibration import calibrate_session  # noqa: E402
from scanner.inputs import read_inputs  # noqa: E402
from scanner.scan import ScanRun, ScanSettings  # noqa: E402
from scanner.session import run_session  # noqa: E402
from scanner.study_folder import Study  # noqa: E402
from sim.detector import SimDetector  # noqa: E402
from sim.generator import MockGenerator  # noqa: E402
from sim.stage import MockStage  # noqa: E402
from sim.ur_controller import FakeURController  # noqa: E402
from study.live_recon import LiveRecon  # noqa: E402
from study.stages import ScanGeometry, recon_grid, recon_stage, scan_protocol  # noqa: E402
from trajectories.config import ScannerConfig  # noqa: E402
from trajectories.model import ScannerModel  # noqa: E402
from trajectories.plan import plan_scan  # noqa: E402

CONFIGS = ROOT / "configs"
FULL = {"views": 360, "panel": 512, "recon_voxel_mm": 0.72, "phantom_voxel_mm": 1.0}
SMALL = {"views": 90, "panel": 128, "recon_voxel_mm": 2.0, "phantom_voxel_mm": 2.0}


def knee_protocol(cfg: dict) -> ScanProtocol:
    """The 360-view knee protocol, its panel binned to ``cfg["panel"]`` pixels a side."""
    protocol = load_protocol(CONFIGS / "protocols" / "knee_reverse_spiral_360.yaml")
    d = protocol.detector
    n = cfg["panel"]
    panel = d.model_copy(update={"rows": n, "cols": n, "pixel_pitch_mm": d.width_mm / n})
    data = protocol.model_copy(update={"detector": panel}).model_dump()
    data["orbit"]["views"] = cfg["views"]
    if cfg["views"] != 360:  # keep the lift travel of the clinical protocol
        data["orbit"]["z_step_mm"] = 1.5 * 360 / cfg["views"]
    return ScanProtocol.model_validate(data)


def disk_view_store_ms(tmp: Path, panel: int, repeats: int = 30) -> float:
    """Median wall time to store one view's files in a study on ``tmp``'s disk, ms."""
    study = Study.create(tmp, {})
    rng = np.random.default_rng(0)
    images = [encode_projections(rng.random((1, panel, panel), np.float32), 1.0) for _ in "ab"]
    times = []
    for k in range(repeats):
        started = time.perf_counter()
        study.write_with_record(
            {f"views/{k}.mha": images[0], f"views/{k}_counts.mha": images[1]},
            f"views/{k}.json",
            lambda digests: json.dumps(digests).encode("utf-8"),
        )
        times.append(time.perf_counter() - started)
    return 1e3 * float(np.median(times))


def sim_scan(tmp: Path, cfg: dict, log) -> dict:
    """The knee scan on the simulated backend with the reconstruction during acquisition."""
    tmp.mkdir()
    backend = tmp / "sim.yaml"
    backend.write_text(yaml.safe_dump({"seed": 0}))
    inputs = read_inputs(
        knee_protocol(cfg),
        CONFIGS / "scanner.yaml",
        "sim",
        backend,
        CONFIGS / "phantoms" / "knee.yaml",
        phantom_voxel_mm=cfg["phantom_voxel_mm"],
    )
    render_s: list[float] = []
    stored_at: list[float] = []
    read_frame = SimDetector.read_frame

    def timed_read_frame(self, timeout_s):  # the panel's image formation, timed per view
        started = time.perf_counter()
        frame = read_frame(self, timeout_s)
        render_s.append(time.perf_counter() - started)
        return frame

    waits_s: list[float] = []
    finish_storing = ScanRun._finish_storing

    def timed_finish_storing(self, keep=0):  # the wait for earlier views' files, per view
        started = time.perf_counter()
        finish_storing(self, keep)
        waits_s.append(time.perf_counter() - started)

    disk_ms = disk_view_store_ms(tmp / "disk_probe", cfg["panel"])
    SimDetector.read_frame = timed_read_frame
    ScanRun._finish_storing = timed_finish_storing
    live = LiveRecon(cfg["recon_voxel_mm"])
    backlog: list[int] = []

    def progress(p) -> None:
        stored_at.append(time.time())
        backlog.append(live.backlog)
        if p.views_done % 60 == 0:
            log(f"  {p.views_done}/{p.views} views, recon backlog {live.backlog}")

    started = time.perf_counter()
    try:
        study = run_session(tmp / "study", inputs, progress=progress, sink=live)
    finally:
        SimDetector.read_frame = read_frame
        ScanRun._finish_storing = finish_storing
    sim_wall = time.perf_counter() - started
    recon_stage(
        study,
        cfg["recon_voxel_mm"],
        result=live.finish(),
        written=live.volume_path,
        say=lambda _m: None,
    )
    ready = (tmp / "study" / "recon" / "volume.mha").stat().st_mtime - stored_at[-1]
    n = len(stored_at)
    between = stored_at[-1] - stored_at[0]
    overhead = (between - sum(render_s[1:])) / (n - 1)
    log("reconstructing the same views offline")
    stack = read_projections(tmp / "study" / "scan" / "projections.mha")
    views = ScanGeometry.of(study, scan_protocol(study), stack.header)
    grid = recon_grid(scan_protocol(study), cfg["recon_voxel_mm"])
    started = time.perf_counter()
    offline = views.fdk(stack.data, grid).volume.data
    offline_s = time.perf_counter() - started
    streamed = read_volume(tmp / "study" / "recon" / "volume.mha", unit="1/mm").data
    diff = float(np.abs(streamed - offline).max())
    return {
        "views": n,
        "panel": f"{cfg['panel']}x{cfg['panel']}",
        "recon_grid": list(grid.size_xyz),
        "sim_wall_s": round(sim_wall, 2),
        "render_s": round(sum(render_s), 2),
        "per_view_overhead_ms": round(1e3 * overhead, 2),
        "storage_wait_ms": round(1e3 * sum(waits_s) / n, 2),
        "disk_view_store_ms": round(disk_ms, 2),
        "projections_per_s": round((n - 1) / between, 2),
        "recon_backlog_max_views": max(backlog),
        "recon_backlog_at_last_view": backlog[-1],
        "recon_ready_after_last_view_s": round(ready, 2),
        "offline_recon_s": round(offline_s, 2),
        "streaming_max_abs_diff": diff,
        "streaming_max_abs_diff_rel": diff / float(np.abs(offline).max()),
    }


def ur_fake_scan(tmp: Path) -> float:
    """Wall time of the test suite's small scan through the UR backend against fakes, s."""
    data = yaml.safe_load((CONFIGS / "protocols" / "demo_knee.yaml").read_text(encoding="utf-8"))
    data["detector"] = {"rows": 64, "cols": 64, "pixel_pitch_mm": 9.6}
    data["orbit"].update(views=30, arc_deg=90, z_travel_mm=20)
    protocol = ScanProtocol.model_validate(data)
    scanner = load_config(CONFIGS / "scanner.yaml", ScannerConfig)
    q0 = plan_scan(ScannerModel(scanner), protocol).q[0]
    with (
        MockStage.of_scanner(scanner, q0[:2], servo_lag_s=0.004) as stage,
        MockGenerator(time_scale=0.0, warmup_s=0.05) as generator,
        FakeURController("127.0.0.2", q0[2:8]),
        FakeURController("127.0.0.3", q0[8:14]),
    ):
        config = tmp / "ur.yaml"
        config.write_text(
            yaml.safe_dump(
                {
                    "source_host": "127.0.0.2",
                    "detector_host": "127.0.0.3",
                    "stage_port": stage.port,
                    "generator_port": generator.port,
                    "detector_maps": str(tmp / "maps"),
                }
            )
        )
        inputs = read_inputs(
            protocol,
            CONFIGS / "scanner.yaml",
            "ur",
            config,
            CONFIGS / "phantoms" / "knee.yaml",
            phantom_voxel_mm=2.0,
        )
        calibrate_session(inputs, tmp / "maps", 8)  # a scan refuses a panel without its maps
        started = time.perf_counter()
        run_session(tmp / "ur", inputs, settings=ScanSettings(device_timeout_s=2.0))
        return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--small", action="store_true", help="90 views of 128^2")
    parser.add_argument("--keep", type=Path, help="keep the studies in this new folder")
    args = parser.parse_args()
    cfg = SMALL if args.small else FULL

    def log(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    with tempfile.TemporaryDirectory(prefix="bench-scan-") as tmp:
        root = Path(tmp) if args.keep is None else args.keep
        root.mkdir(exist_ok=True)
        log(f"simulated scan: {cfg['views']} views of {cfg['panel']}^2")
        result = sim_scan(root / "sim", cfg, log)
        log("UR backend against the fake controllers")
        result["ur_fake_wall_s"] = round(ur_fake_scan(root), 2)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
