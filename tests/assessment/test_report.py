"""Flags, plots, the HTML report and its Chromium rendering on synthetic knee kinematics."""

from __future__ import annotations

import base64
import csv
import html
import io
import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest

from assessment.flags import FlagRun, angle_text, describe_flags, flag_runs
from assessment.plots import DPI, PLOTS, save_all
from assessment.report import CSV_COLUMNS, frame_overlays, write_report
from assessment.results import Exclusion, KneeKinematics
from assessment.screening import excluding
from registration.poses import BodyPose

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
N_FRAMES = 30
BUMP = {12: 2.2, 13: 2.4, 14: 2.6, 15: 2.5, 16: 2.3, 17: 2.1}
"""MLD (mm) in the flagged frames; everything else stays within ±0.5 mm."""


def make_kin(mld_mm: np.ndarray | None = None, flexion_deg: np.ndarray | None = None):
    """30 frames of a knee flexing 0 -> 90 -> 0 degrees, MLD bump above 2 mm in frames 12-17."""
    i = np.arange(N_FRAMES)
    if flexion_deg is None:
        flexion_deg = 90.0 * np.sin(np.pi * i / (N_FRAMES - 1))
    if mld_mm is None:
        mld_mm = 0.5 * np.sin(2 * np.pi * i / (N_FRAMES - 1))
        for frame, value in BUMP.items():
            mld_mm[frame] = value
    lateral = 4.0 + 1.5 * np.sin(np.pi * i / (N_FRAMES - 1))
    ap = -12.0 * flexion_deg / 90.0
    return KneeKinematics(
        side="right",
        frames=i,
        flexion_deg=flexion_deg,
        varus_deg=2.0 * np.sin(np.pi * i / (N_FRAMES - 1)),
        internal_rotation_deg=8.0 * flexion_deg / 90.0,
        translation_mm=np.stack([0.2 * np.sin(i / 5), ap / 2, 0.1 * np.cos(i / 7)], axis=1),
        medial_distance_mm=lateral + mld_mm,
        lateral_distance_mm=lateral,
        medial_point_mm=np.stack([20.0 + 0.3 * np.sin(i / 4), ap + 2.0], axis=1),
        lateral_point_mm=np.stack([-20.0 + 0.3 * np.cos(i / 4), 1.5 * ap], axis=1),
    )


@pytest.fixture(scope="module")
def kin() -> KneeKinematics:
    return make_kin()


@pytest.fixture(scope="module")
def report(kin, tmp_path_factory) -> dict[str, Path]:
    return write_report(
        kin, tmp_path_factory.mktemp("report"), title="Knee test", extra_rows={"Scan": "<s1>"}
    )


def test_flag_runs_exact(kin):
    expected_flexion = float(kin.flexion_deg[14])
    assert flag_runs(kin) == [FlagRun(12, 17, pytest.approx(2.6), "medial", expected_flexion)]


def test_flag_runs_split_single_frames_and_sign():
    mld = np.zeros(N_FRAMES)
    mld[[3, 4]] = [2.5, -3.0]  # adjacent but opposite sides: two runs
    mld[10] = -2.1
    mld[-1] = 4.0  # run touching the last frame
    flexion = np.linspace(-5.0, 40.0, N_FRAMES)
    runs = flag_runs(make_kin(mld, flexion))
    assert [(r.first_frame, r.last_frame, r.sign) for r in runs] == [
        (3, 3, "medial"),
        (4, 4, "lateral"),
        (10, 10, "lateral"),
        (29, 29, "medial"),
    ]
    assert runs[1].max_abs_mld_mm == pytest.approx(3.0)
    assert runs[0].flexion_deg == pytest.approx(flexion[3])


def test_angle_text_uses_extension_for_negative_flexion():
    assert angle_text(-8.2) == "8° extension"
    assert angle_text(35.4) == "35° flexion"
    assert angle_text(-0.2) == "0° flexion"


def test_describe_flags_sentences(kin):
    sentences = describe_flags(kin)
    assert len(sentences) == 2
    first = sentences[0]
    assert first.startswith("Medial–lateral difference above 2 mm in frames 12–17")
    assert f"max 2.6 mm at {round(kin.flexion_deg[14])}° flexion" in first
    assert "medial gap larger" in first and "not a diagnosis" in first
    assert "6 of 30 measured frames flagged" in sentences[1]
    assert f"{kin.ddv_mm2:.2f} mm²" in sentences[1]


def test_describe_flags_single_frame_in_extension():
    mld = np.zeros(N_FRAMES)
    mld[5] = -2.4
    flexion = np.linspace(-10.0, 20.0, N_FRAMES)
    first = describe_flags(make_kin(mld, flexion))[0]
    assert "in frame 5 (max 2.4 mm at 5° extension): lateral gap larger" in first


def test_describe_flags_none_flagged():
    clear = make_kin(0.5 * np.sin(np.arange(N_FRAMES) / 3))
    (sentence,) = describe_flags(clear)
    assert sentence == (
        "No medial–lateral difference above 2 mm over the measured frames "
        f"(max |MLD| {np.abs(clear.mld_mm).max():.1f} mm); DDV {clear.ddv_mm2:.2f} mm²."
    )
    assert flag_runs(clear) == []


def test_plots_decode_and_mark_every_frame_where_it_is_drawn(kin, tmp_path):
    """Each plot's PNG is drawn; its markers (a point per frame and series) lie inside the
    image, and on a dark pixel of the drawn series where the series is a line through the
    frames' points (the MLD: 0.2 grey, its frames' points on it)."""
    written = save_all(kin, tmp_path / "plots")
    assert list(written) == list(PLOTS)
    for path, plot in written.values():
        image = matplotlib.image.imread(path)
        height, width = image.shape[:2]
        assert 6 * DPI <= width <= 8 * DPI and 4 * DPI <= height <= 7 * DPI
        assert image[..., :3].std() > 0.05  # drawn, not blank
        assert plot.markers.shape[1:] == (N_FRAMES, 2)
        assert ((plot.markers > 0.0) & (plot.markers < 1.0)).all()
    path, plot = written["mld"]
    image = matplotlib.image.imread(path)[..., :3].mean(axis=2)
    for x, y in plot.markers[0]:
        row, col = round(y * image.shape[0]), round(x * image.shape[1])
        assert image[row - 1 : row + 2, col - 1 : col + 2].min() < 0.4


def test_report_html_self_contained(report):
    text = report["report"].read_text(encoding="utf-8")
    payloads = re.findall(r'<img src="data:image/png;base64,([A-Za-z0-9+/=]+)"', text)
    assert len(payloads) == len(PLOTS)
    for payload in payloads:
        png = base64.b64decode(payload, validate=True)
        assert png.startswith(PNG_SIGNATURE)
        assert matplotlib.image.imread(io.BytesIO(png)).shape[0] > 100
    assert "Medial–lateral difference above 2 mm in frames 12–17" in text
    assert "&lt;s1&gt;" in text  # extra rows are escaped
    assert not re.search(r"https?:", text)
    assert "<script" not in text.lower()
    assert "<td>-0.00</td>" not in text  # no negative zeros in the per-frame table
    for name in PLOTS:
        assert report[name].read_bytes().startswith(PNG_SIGNATURE)


def test_the_registered_frames_play_in_the_report(kin, tmp_path, browse):
    """Overlays of three frames (13 flagged, the others without a PNG): a player, a slider over
    every frame, a filmstrip embedding each image once, the flagged frame marked, captions
    with every body's NCC, a marker per plotted series; Chromium shows the first frame, plays,
    and opens at the frame asked for."""
    overlays = tmp_path / "overlays"
    overlays.mkdir()
    for frame in (0, 13, 29):
        image = np.full((8, 8, 3), frame / 29.0)
        matplotlib.image.imsave(overlays / f"frame_{frame:04d}.png", image)
    poses = [
        BodyPose(frame, bone, np.eye(4), similarity=0.9 + frame / 1000)
        for frame in range(N_FRAMES)
        for bone in ("femur", "tibia_fibula")
    ]
    frames = frame_overlays(overlays, kin, poses)
    assert [f.frame for f in frames] == [0, 13, 29]
    assert [f.flagged for f in frames] == [False, True, False]
    assert frames[1].caption.startswith("frame 13: NCC femur 0.913, tibia_fibula 0.913; flagged")
    written = write_report(kin, tmp_path / "r", title="t", overlays=frames)
    page = written["report"]
    figure = matplotlib.image.imread(written["motion_frames"])  # the three frames, titled
    assert figure.shape[1] == 3 * 230 and figure[..., :3].std() > 0.05
    text = page.read_text(encoding="utf-8")
    start = text.index('<div class="filmstrip">')
    strip = text[start : text.index("</div>", start)]
    assert strip.count("data:image/png;base64,") == 3 and strip.count('class="flagged"') == 1
    assert f'id="motion-slider" type="range" min="0" max="{N_FRAMES - 1}"' in text
    assert "Play</button>" in text and "flagged (|MLD|" in text
    assert text.count('class="marker"') == sum(len(p(kin).markers) for p in PLOTS.values())
    assert not re.search(r"https?:", text)
    shown = {}
    for fragment in ("", "play", "frame=13"):  # as it is, playing (Chromium's clock), at 13
        dom = browse(page, fragment, budget_ms=1100).dom
        caption = re.search(r'<span id="motion-caption">([^<]*)</span>', dom).group(1)
        shown[fragment] = html.unescape(caption)
    assert shown[""] == frames[0].caption  # the script ran: the first frame is shown
    assert shown["play"].startswith("frame ") and shown["play"] != shown[""]  # it advanced
    assert shown["frame=13"] == frames[1].caption


def test_frames_not_measured_are_marked_apart_from_the_flags(tmp_path, browse):
    """Frames 20-22 left out (the tibia not tracked): their metrics are gaps, the Flags box and
    the summary name them; the filmstrip frames them dashed grey and the flagged frame red; the
    table greys their rows; in Chromium their caption gives the reason and every plot's ring
    is hidden there, shown on a measured frame; metrics.csv gives the reason, no number."""
    lost = Exclusion("tibia not tracked", "NCC 0.210 below 0.5")
    kin = excluding(make_kin(), tuple(lost if 20 <= k <= 22 else None for k in range(N_FRAMES)))
    assert np.isnan(kin.mld_mm[20:23]).all() and kin.flagged.sum() == len(BUMP)
    overlays = tmp_path / "overlays"
    overlays.mkdir()
    for frame in (0, 13, 21):
        matplotlib.image.imsave(overlays / f"frame_{frame:04d}.png", np.full((8, 8, 3), 0.5))
    poses = [
        BodyPose(frame, bone, np.eye(4), similarity=0.21 if 20 <= frame <= 22 else 0.8)
        for frame in range(N_FRAMES)
        for bone in ("femur", "tibia_fibula")
    ]
    frames = frame_overlays(overlays, kin, poses)
    assert [(f.flagged, f.excluded) for f in frames] == [
        (False, False),
        (True, False),
        (False, True),
    ]
    written = write_report(kin, tmp_path / "r", title="t", overlays=frames)
    text = written["report"].read_text(encoding="utf-8")
    start = text.index('<div class="filmstrip">')
    strip = text[start : text.index("</div>", start)]
    assert strip.count('class="flagged"') == 1 and strip.count('class="excluded"') == 1
    assert ".filmstrip img.excluded { border: 3px dashed #7f8c8d;" in text
    assert text.count('<tr class="excluded">') == 3 and text.count('<tr class="flagged">') == 6
    assert "Not measured: tibia not tracked in frames 20–22." in html.unescape(text)
    assert "tibia not tracked in frames 20–22: metrics from 27 of 30 frames" in html.unescape(text)
    for fragment, hidden in (("frame=21", True), ("frame=13", False)):
        dom = browse(written["report"], fragment, budget_ms=1100).dom
        caption = html.unescape(re.search(r'<span id="motion-caption">([^<]*)</span>', dom)[1])
        rings = re.findall(r'<i class="marker"[^>]*style="([^"]*)"', dom)
        assert len(rings) == sum(len(p(kin).markers) for p in PLOTS.values())
        if hidden:
            assert caption == frames[2].caption
            assert caption.endswith("not measured: tibia not tracked (NCC 0.210 below 0.5)")
            assert all("display: none" in r for r in rings)
        else:
            assert caption == frames[1].caption and "flagged" in caption
            assert not any("display: none" in r for r in rings)
    with written["metrics"].open(newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    assert rows[21]["status"] == "tibia not tracked (NCC 0.210 below 0.5)"
    assert rows[21]["mld_mm"] == rows[21]["flagged"] == "" and rows[13]["flagged"] == "1"


def test_unloaded_frames_are_shown_not_flagged():
    """The MLD bump's frames with both condyles 3 mm above their rest (a knee in swing): no
    flag, and the Flags box says why."""
    kin = make_kin()
    gaps = np.where(np.isin(np.arange(N_FRAMES), list(BUMP)), 3.0, 0.2)
    swinging = replace(kin, medial_gap_mm=gaps, lateral_gap_mm=gaps + 0.5)
    assert kin.flagged.sum() == len(BUMP) and not swinging.flagged.any()
    assert describe_flags(swinging)[-1] == (
        "Frames 12–17: |MLD| above 2 mm with neither condyle within 1.5 mm of the plateau (the "
        "knee bears no weight there): not flagged."
    )


def test_metrics_csv(report, kin):
    with report["metrics"].open(newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    assert tuple(rows[0]) == CSV_COLUMNS
    assert len(rows) == N_FRAMES
    assert [int(r["flagged"]) for r in rows] == kin.flagged.astype(int).tolist()
    np.testing.assert_allclose([float(r["mld_mm"]) for r in rows], kin.mld_mm, atol=1e-4)


def test_overwrite_refused(report, kin):
    before = report["report"].read_bytes()
    with pytest.raises(FileExistsError, match=re.escape(str(report["report"]))):
        write_report(kin, report["report"].parent, title="again")
    assert report["report"].read_bytes() == before


def test_render_without_chromium_says_how_to_install(
    report, tmp_path, monkeypatch, capsys, render_report
):
    monkeypatch.setattr(render_report, "find_chromium", lambda: None)
    assert render_report.main([str(report["report"]), str(tmp_path / "out.png")]) == 1
    assert "apt-get install -y chromium" in capsys.readouterr().err


def test_render_with_chromium(report, tmp_path, render_report):
    if render_report.find_chromium() is None:
        pytest.skip("chromium not installed (" + render_report.INSTALL_HINT + ")")
    out = tmp_path / "report.png"
    proc = subprocess.run(
        [sys.executable, render_report.__file__, str(report["report"]), str(out)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    image = matplotlib.image.imread(out)
    assert image.shape[:2] == (render_report.WINDOW_PX[1], render_report.WINDOW_PX[0])
    assert image[..., :3].std() > 0.05
    top = image[: render_report.WINDOW_PX[1] // 2, :, :3]
    assert (top.std(axis=(0, 1)) > 0.02).all()  # content (text, plots) in the top half
