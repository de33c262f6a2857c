"""Moving the scanner on the simulated backend: from random rest poses to within the scan's
start tolerance, after which the scan's preflight accepts; refusals before anything moves;
SAFE's order on a fault while moving; park after a fault's SAFE; ``cbct move``."""

from __future__ import annotations

import os
import signal
import threading
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from configs import CONFIGS
from recon.config import ScanProtocol, load_config
from recon.geometry import DetectorSpec
from scanner.corrections import PanelMaps
from scanner.inputs import read_inputs
from scanner.move import MoveFault, move_scanner
from scanner.registry import Rig, nothing_in_the_beam
from scanner.scan import OperatorDeclined, PreflightError, ScanFault, ScanRun, ScanSettings
from scanner.session import run_session
from scanner.stop import StopRequest, stop_signals
from scanner.storage import ScanStore
from scanner.study_folder import Study
from sim.backend import SimBackendSpec, SimFaults, SimStartPose
from study.cli import app
from study.simulator import open_sim
from tests.trajectories.conftest import random_rest_pose
from trajectories.config import ScannerConfig
from trajectories.model import ScannerModel
from trajectories.move import park_pose, plan_move
from trajectories.plan import Plan, plan_scan

TOLERANCE = ScanSettings().start_tolerance


def tiny_protocol() -> ScanProtocol:
    """The demo protocol read out 8x8 binned, two 90-degree passes of 30 views in all."""
    data = yaml.safe_load((CONFIGS / "protocols" / "demo_knee.yaml").read_text(encoding="utf-8"))
    data["detector"] = {"rows": 64, "cols": 64, "pixel_pitch_mm": 9.6}
    data["orbit"].update(views=30, arc_deg=90, z_travel_mm=20)
    return ScanProtocol.model_validate(data)


def start_pose(q: np.ndarray) -> SimStartPose:
    return SimStartPose(
        rotary_deg=q[0],
        lift_mm=q[1],
        source_arm_deg=tuple(q[2:8]),
        detector_arm_deg=tuple(q[8:14]),
    )


@pytest.fixture(scope="module")
def scanner() -> tuple[ScannerModel, ScanProtocol, Plan]:
    model = ScannerModel(load_config(CONFIGS / "scanner.yaml", ScannerConfig))
    protocol = tiny_protocol()
    return model, protocol, plan_scan(model, protocol)


def sim_at(scanner, pose: np.ndarray, **spec):
    """The simulated devices standing at ``pose``, imaging empty air (a move never exposes)."""
    model, protocol, plan = scanner
    d = protocol.detector
    panel = DetectorSpec(rows=d.rows, cols=d.cols, pixel_pitch_mm=d.pixel_pitch_mm)
    rig = Rig(model, plan.q[0], panel, protocol.orbit.sdd_mm, nothing_in_the_beam(panel))
    backend, truth = open_sim(SimBackendSpec(start_pose=start_pose(pose), **spec), rig)
    return backend, truth.simulated


@pytest.mark.parametrize("seed", range(3))
def test_random_pose_moves_to_the_start_and_the_scan_preflight_accepts(scanner, seed, tmp_path):
    model, protocol, plan = scanner
    pose = random_rest_pose(model, np.random.default_rng(100 + seed))
    backend, simulated = sim_at(scanner, pose)
    asked, said = [], []
    try:
        result = move_scanner(
            backend,
            model,
            plan.q[0],
            "the plan's start",
            confirm=lambda q: asked.append(q) or True,
            say=said.append,
        )
        assert result.error <= TOLERANCE
        np.testing.assert_allclose(result.move.start_q, pose, atol=0.05)  # tracking noise
        d = protocol.detector
        panel = DetectorSpec(rows=d.rows, cols=d.cols, pixel_pitch_mm=d.pixel_pitch_mm)
        study = Study.create(tmp_path / "study", {})
        store = ScanStore(study, panel, plan.joint_names, 30, plan.achieved)
        e, shape = protocol.exposure, (d.rows, d.cols)
        maps = PanelMaps(  # maps of this panel and mode (their values do not matter here)
            serial=backend.detector.serial,
            mode=backend.detector.mode,
            offset=np.zeros(shape),
            gain=np.ones(shape),
            defects=np.zeros(shape, bool),
            lag=0.0,
            kv=e.tube_kv,
            mas=e.mas,
            frames=8,
            made=datetime.now(UTC).isoformat(),
            noise_adu=1.0,
        )
        run = ScanRun(backend, model, plan, protocol, store, close_backend=False, maps=maps)
        assert run.preflight().views_to_acquire == 30
    finally:
        backend.close()
    # shown and confirmed once, before it ran: the table and the headline figures
    assert len(asked) == 1 and "minimum clearance" in asked[0] and " s: rotary " in asked[0]
    assert "rotary (deg)" in said[0] and "lift (mm)" in said[0]
    # no X-ray: the generator was never prepared, nothing fired
    events = [what for _, _, who, what in simulated.world.events if who == "generator"]
    assert "prep" not in events and "xray_on" not in events


def test_a_move_beyond_a_limit_is_refused_before_anything_moves(scanner):
    _, _, plan = scanner
    pose = park_pose(scanner[0])
    pose[0] = 380.0  # a turn and a bit: beyond the cable wrap
    backend, simulated = sim_at(scanner, pose)
    try:
        with pytest.raises(PreflightError, match=r"stands with joint rotary at 380.*nothing moved"):
            move_scanner(backend, scanner[0], plan.q[0], "the plan's start")
    finally:
        backend.close()
    assert simulated.world.t == 0.0  # not one set-point was streamed
    np.testing.assert_allclose(simulated.world.filtered, pose)


def test_open_interlock_or_no_refuses_before_anything_moves(scanner):
    model, _, plan = scanner
    pose = random_rest_pose(model, np.random.default_rng(7))
    backend, simulated = sim_at(scanner, pose)
    try:
        simulated.generator.set_interlock("door", False)
        with pytest.raises(PreflightError, match=r"interlocks open: \['door'\]"):
            move_scanner(backend, model, plan.q[0], "the plan's start")
        simulated.generator.set_interlock("door", True)
        with pytest.raises(OperatorDeclined, match="nothing moved"):
            move_scanner(backend, model, plan.q[0], "the plan's start", confirm=lambda _q: False)
    finally:
        backend.close()
    assert simulated.world.t == 0.0


def test_standing_at_the_goal_moves_nothing_and_asks_nothing(scanner):
    model, _, plan = scanner
    backend, simulated = sim_at(scanner, plan.q[0])
    try:
        result = move_scanner(
            backend, model, plan.q[0], "the plan's start", confirm=lambda q: pytest.fail(q)
        )
    finally:
        backend.close()
    assert result.move is None and result.error <= TOLERANCE
    assert simulated.world.t == 0.0


def test_a_fault_while_moving_turns_the_xray_off_then_stops_every_group(scanner):
    model, _, plan = scanner
    pose = random_rest_pose(model, np.random.default_rng(8))
    backend, simulated = sim_at(scanner, pose, faults=SimFaults(protective_stop_at_view=0))
    try:
        with pytest.raises(MoveFault, match=r"protective stop .*\(X-ray off, arms stopped"):
            move_scanner(backend, model, plan.q[0], "the plan's start")
    finally:
        backend.close()
    events = [(seq, who, what) for seq, _, who, what in simulated.world.events]
    abort = min(seq for seq, who, what in events if who == "generator" and what == "abort")
    stops = {who: seq for seq, who, what in events if what == "stop"}
    assert set(stops) >= {"stage", "source_arm", "detector_arm"}
    assert abort < min(stops.values())


def test_a_stop_signal_while_moving_stops_every_group_and_streams_nothing_more(scanner):
    """SIGTERM sent to this process a fifth of the way through a move: MoveFault naming it,
    ABORT then every group stopped, and no set-point after the request (the virtual clock, which
    only the stream advances, stands still from the stops on)."""
    model, _, plan = scanner
    pose = random_rest_pose(model, np.random.default_rng(8))
    backend, simulated = sim_at(scanner, pose)
    world = simulated.world
    stop = StopRequest()
    goal = plan.q[0]

    def signal_on_the_way() -> None:
        while world.t < 0.2 * duration:
            time.sleep(0.0002)
        os.kill(os.getpid(), signal.SIGTERM)

    duration = plan_move(model, pose, goal, "start").duration_s
    watcher = threading.Thread(target=signal_on_the_way)
    try:
        with stop_signals(stop):
            watcher.start()
            with pytest.raises(MoveFault, match=r"stopped by SIGTERM.*\(X-ray off, arms stopped"):
                move_scanner(backend, model, goal, "the plan's start", stop=stop)
    finally:
        watcher.join()
        backend.close()
    events = [(seq, t, who, what) for seq, t, who, what in world.events]
    abort = min(seq for seq, _, who, what in events if who == "generator" and what == "abort")
    stops = [(seq, t) for seq, t, _, what in events if what == "stop" and seq > abort]
    assert len(stops) >= 3 and max(t for _, t in stops) < 0.5 * duration
    assert world.t == max(t for _, t in stops)  # nothing streamed after the stop
    assert np.abs(world.filtered - goal).max() > 10 * TOLERANCE  # stopped short of the goal


def session_inputs(tmp: Path, pose: np.ndarray, **faults):
    path = tmp / "sim.yaml"
    path.write_text(
        yaml.safe_dump(
            {"seed": 3, "faults": faults, "start_pose": start_pose(pose).model_dump(mode="json")}
        )
    )
    inputs = read_inputs(
        tiny_protocol(),
        CONFIGS / "scanner.yaml",
        "sim",
        path,
        CONFIGS / "phantoms" / "knee.yaml",
        phantom_voxel_mm=2.0,
    )
    return inputs, path


def test_scan_moves_to_its_start_and_parks_after_a_fault(scanner, tmp_path):
    """``cbct scan --move-to-start --park`` on a scanner left elsewhere: the move, the scan up
    to an injected fault (SAFE), then park; ``cbct move --to park`` from another pose."""
    model = scanner[0]
    pose = random_rest_pose(model, np.random.default_rng(11))
    inputs, config = session_inputs(tmp_path, pose, dropped_frame_at_view=8)
    said = []
    with pytest.raises(ScanFault, match="frame of exposure"):
        run_session(tmp_path / "study", inputs, move_to_start=True, park=True, say=said.append)
    study = Study.open(tmp_path / "study")
    assert study.stage("scan")["views_stored"] == 8 and study.verify() == []
    start, park = study.manifest["moves"]
    assert start["target"] == "the plan's start" and start["status"] == "done"
    assert park["target"] == "park" and park["status"] == "done"
    assert start["error"] <= TOLERANCE and park["error"] <= TOLERANCE
    np.testing.assert_allclose(park["reached"], park_pose(model), atol=TOLERANCE)
    events = (tmp_path / "study" / "scan" / "device_events-1.csv").read_text(encoding="utf-8")
    assert events.count("xray_on") == 9  # the 8 stored views and the one whose frame dropped

    # the operator's command, on the study's backend config with the scanner left elsewhere
    other = random_rest_pose(model, np.random.default_rng(12))
    config.write_text(
        yaml.safe_dump({"seed": 3, "start_pose": start_pose(other).model_dump(mode="json")})
    )
    run = CliRunner().invoke(
        app,
        [
            "move",
            "--study",
            str(tmp_path / "study"),
            "--to",
            "park",
            "--yes",
            "--backend-config",
            str(config),
        ],
    )
    assert run.exit_code == 0, run.output
    assert "Move the scanner to park?" in run.output and "at park" in run.output
    moves = Study.open(tmp_path / "study").manifest["moves"]
    assert len(moves) == 3 and moves[-1]["status"] == "done"
    np.testing.assert_allclose(moves[-1]["from"], other, atol=0.05)

    # resume from yet another pose: to the start, the missing views, park after DONE
    again = random_rest_pose(model, np.random.default_rng(13))
    run_session(
        tmp_path / "study",
        None,
        resume=True,
        backend_override=SimBackendSpec(seed=3, start_pose=start_pose(again)),
        move_to_start=True,
        park=True,
    )
    study = Study.open(tmp_path / "study")
    assert study.stage("scan")["status"] == "complete" and study.verify() == []
    moves = study.manifest["moves"]
    # the retreat ends where every plan starts, at park: nothing left to move or to ask
    assert [(m["target"], m["status"]) for m in moves[3:]] == [
        ("the plan's start", "done"),
        ("park", "already there"),
    ]
    assert all(m["error"] <= TOLERANCE for m in moves)


def test_park_after_a_protective_stop_is_refused_and_recorded(scanner, tmp_path):
    """A protective stop is the operator's to clear on the pendant: park refuses to move, says
    so, records it, and the scan's fault stands."""
    inputs, _ = session_inputs(tmp_path, park_pose(scanner[0]), protective_stop_at_view=3)
    said = []
    with pytest.raises(ScanFault, match="protective stop"):
        run_session(tmp_path / "study", inputs, park=True, say=said.append)
    (park,) = Study.open(tmp_path / "study").manifest["moves"]
    assert park["target"] == "park" and park["status"] == "failed"
    assert "nothing moved" in park["reason"] and "source_arm: protective stop" in park["reason"]
    assert any(line.startswith("PARK NOT DONE") for line in said)
