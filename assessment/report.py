"""The knee-assessment report: per-frame metrics CSV, plot PNGs and a self-contained HTML page.

The HTML holds everything it shows: the plots and the registered frames as base64 data URIs,
inline CSS, and, where there is motion to play, its own scripts (a player, the 3D view with
three.js inlined, the plots' markers). Its content security policy lets it load nothing else,
so it opens offline and no request leaves the file.
"""

from __future__ import annotations

import base64
import csv
import html
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from assessment.flags import angle_text, describe_flags, insufficient_text, measured_text
from assessment.plots import Plot, frames_beside_4d_png, motion_frames_png, save_all
from assessment.results import KneeKinematics
from assessment.viewer import MotionScene, json_points, view_html
from registration.poses import BodyPose

CSV_COLUMNS = (
    "frame",
    "status",
    "flexion_deg",
    "varus_deg",
    "internal_rotation_deg",
    "tx_mm",
    "ty_mm",
    "tz_mm",
    "medial_distance_mm",
    "lateral_distance_mm",
    "mld_mm",
    "flagged",
    "medial_ml_mm",
    "medial_ap_mm",
    "lateral_ml_mm",
    "lateral_ap_mm",
)
"""Header of metrics.csv; status is "measured" or why the frame is not (its numbers are then
empty), tx/ty/tz are the JCS translations (medial-lateral shift, anterior drawer,
distraction), *_ml/*_ap the projection points on the TP plane."""

_CAPTIONS = {
    "distance_scatter": "Medial vs lateral TP–condyle distance per frame; the band marks "
    "|MLD| within the flag threshold around y = x (equal gaps).",
    "mld": "Medial–lateral difference per frame; flagged frames in red, frames not measured "
    "shaded grey (a gap in the line).",
    "extension_distance": "Medial and lateral TP–condyle distances against the extension angle.",
    "trajectories": "Medial and lateral condyle points projected on the TP plane, joined per "
    "frame, light to dark over time (Feng's method).",
    "angles": "Joint angles per frame (Grood–Suntay); frames not measured shaded grey.",
    "motion_frames": "Motion frames with their joint angles: registered frames evenly spaced "
    "over the motion, outlines at the registered poses; flagged frames titled in red, frames "
    "not measured in grey.",
    "frames_beside_4d": "The registered frames (top) beside the 4D rendering at the same "
    "instants (bottom): the bodies at their registered poses, the tibial plateau plane and "
    "the lowest medial and lateral condyle points.",
}

_CSS = """
body { font-family: "DejaVu Sans", Arial, sans-serif; color: #222; margin: 24px 32px;
       max-width: 1336px; }
h1 { font-size: 26px; margin: 0 0 16px 0; }
h2 { font-size: 20px; margin: 28px 0 10px 0; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; font-size: 14px; }
th, td { border: 1px solid #ccc; padding: 4px 10px; text-align: right; }
th { background: #f0f0f0; }
table.summary th, table.summary td { text-align: left; }
tr.flagged td { background: #fde2e1; }
tr.excluded td { background: #eeeeee; color: #777; font-style: italic; }
.flags { border: 2px solid #d9822b; background: #fff4e5; padding: 10px 16px; font-size: 16px; }
.flags.clear { border-color: #3d8b40; background: #eaf6ea; }
.flags.insufficient, .banner { border: 2px solid #5b6770; background: #e9edf0; }
.banner { padding: 10px 16px; font-size: 18px; font-weight: bold; margin-bottom: 12px; }
.flags p { margin: 6px 0; }
.note { font-size: 13px; color: #555; }
.plots { display: grid; grid-template-columns: 1fr 1fr; gap: 16px; }
figure { margin: 0; }
figure img { width: 100%; height: auto; border: 1px solid #ddd; }
figcaption { font-size: 13px; color: #444; margin-top: 4px; }
.player .panes { display: flex; flex-wrap: wrap; gap: 12px; align-items: flex-start; }
.player img.view { width: 520px; border: 1px solid #ddd; display: block; }
.player canvas { width: 640px; height: 520px; border: 1px solid #ddd; cursor: grab; }
.marked { position: relative; }
.marker { position: absolute; width: 14px; height: 14px; margin: -9px 0 0 -9px;
          border: 2px solid #d62728; border-radius: 50%; pointer-events: none; }
.player .controls { display: flex; gap: 12px; align-items: center; margin: 8px 0;
                    font-size: 14px; }
.player input[type=range] { width: 320px; }
.filmstrip { display: flex; flex-wrap: wrap; gap: 4px; }
.filmstrip img { height: 72px; border: 3px solid transparent; cursor: pointer; }
.filmstrip img.flagged { border-color: #c0392b; }
.filmstrip img.excluded { border: 3px dashed #7f8c8d; opacity: 0.6; }
.filmstrip img.current { outline: 2px solid #2c7be5; }
"""

_MOTION_JS = """
window.reportMotion = (() => {
  const el = (id) => document.getElementById(id);
  const steps = JSON.parse(el('motion-steps').textContent);
  const thumbs = [...document.querySelectorAll('.filmstrip img')];
  const view = el('overlay-view');
  const slider = el('motion-slider');
  const caption = el('motion-caption');
  const button = el('motion-play');
  const listeners = [];
  let current = 0, timer = null;
  function show(k) {
    current = k;
    slider.value = k;
    caption.textContent = steps[k].caption;
    const image = steps[k].image;
    if (view) {
      view.style.visibility = image >= 0 ? 'visible' : 'hidden';
      if (image >= 0) view.src = thumbs[image].src;
    }
    thumbs.forEach((t, j) => t.classList.toggle('current', j === image));
    listeners.forEach((f) => f(k));
  }
  slider.addEventListener('input', () => show(Number(slider.value)));
  thumbs.forEach((t) => t.addEventListener('click', () => show(Number(t.dataset.step))));
  button.addEventListener('click', () => {
    if (timer === null) {
      timer = setInterval(() => show((current + 1) % steps.length), 250);
      button.textContent = 'Pause';
    } else {
      clearInterval(timer);
      timer = null;
      button.textContent = 'Play';
    }
  });
  const asked = new URLSearchParams(location.hash.slice(1));
  const start = steps.findIndex((s) => String(s.frame) === asked.get('frame'));
  show(Math.max(start, 0));
  if (asked.has('play')) button.click();
  return {listen(f) { listeners.push(f); f(current); }};
})();
"""

_MARKERS_JS = """
(() => {
  const marks = [...document.querySelectorAll('.marker')].map((m) => [m, JSON.parse(m.dataset.xy)]);
  window.reportMotion.listen((k) => marks.forEach(([m, xy]) => {
    m.style.display = xy[k] === null ? 'none' : '';  // a frame not measured has no point
    if (xy[k] === null) return;
    m.style.left = `${100 * xy[k][0]}%`;
    m.style.top = `${100 * xy[k][1]}%`;
  }));
})();
"""

_CSP = (
    "default-src 'none'; img-src data: blob:; style-src 'unsafe-inline'; "
    "script-src 'unsafe-inline' blob:"
)
"""The page's content security policy: it may load nothing but what it holds."""


@dataclass(frozen=True)
class FrameOverlay:
    """One registered frame for the report's player.

    Attributes:
        frame: The frame's number in the sequence.
        png: The frame with each tracked body's outline at its registered pose.
        caption: What the registration and the assessment said of it (NCC per body, flags).
        flagged: Whether the assessment flagged the frame.
        excluded: Whether the assessment left the frame out (failed or implausible).
    """

    frame: int
    png: Path
    caption: str
    flagged: bool
    excluded: bool = False


def frame_overlays(
    folder: Path, kin: KneeKinematics, poses: Sequence[BodyPose]
) -> list[FrameOverlay]:
    """The registration's overlays (``frame_NNNN.png`` in ``folder``) of the assessed frames,
    captioned with each body's NCC and the frame's flag; frames without one are left out.

    Args:
        folder: The registration's ``overlays/``.
        kin: The assessed motion (its frames and flags).
        poses: The registered poses, whose similarity is each body's NCC.
    """
    ncc: dict[int, list[str]] = {}
    for pose in poses:
        ncc.setdefault(pose.frame, []).append(f"{pose.body} {pose.similarity:.3f}")
    out = []
    for k, frame in enumerate(int(f) for f in kin.frames):
        png = folder / f"frame_{frame:04d}.png"
        if not png.is_file():
            continue
        caption = f"frame {frame}: NCC " + ", ".join(ncc.get(frame, ["not recorded"]))
        out.append(
            FrameOverlay(
                frame,
                png,
                caption + _flag_note(kin, k),
                bool(kin.flagged[k]),
                not kin.measured[k],
            )
        )
    return out


def _flag_note(kin: KneeKinematics, k: int) -> str:
    """What a caption says of the ``k``-th assessed frame: not measured and why, or its flag
    ("" when it is measured and not flagged)."""
    if not kin.measured[k]:
        return f"; not measured: {_status(kin, k)}"
    if not kin.flagged[k]:
        return ""
    return f"; flagged (|MLD| {abs(kin.mld_mm[k]):.2f} mm > {kin.flag_mm:g} mm)"


def _fmt(value: float, digits: int) -> str:
    """A float with fixed decimals, without a minus sign on values that round to zero."""
    text = f"{value:.{digits}f}"
    return text[1:] if text.startswith("-") and float(text) == 0 else text


def _status(kin: KneeKinematics, i: int) -> str:
    """The ``i``-th frame's status: "measured", or why it is not."""
    return "measured" if kin.measured[i] else str(kin.excluded[i])


def _metric_rows(kin: KneeKinematics) -> list[dict[str, str]]:
    """Per-frame rows keyed by CSV_COLUMNS (distances and angles to 4 decimals; empty for a
    frame not measured)."""
    mld, flagged = kin.mld_mm, kin.flagged
    rows = []
    for i, frame in enumerate(kin.frames):
        if not kin.measured[i]:
            rows.append(
                {c: "" for c in CSV_COLUMNS} | {"frame": str(int(frame)), "status": _status(kin, i)}
            )
            continue
        values = (
            kin.flexion_deg[i],
            kin.varus_deg[i],
            kin.internal_rotation_deg[i],
            *kin.translation_mm[i],
            kin.medial_distance_mm[i],
            kin.lateral_distance_mm[i],
            mld[i],
        )
        points = (*kin.medial_point_mm[i], *kin.lateral_point_mm[i])
        rows.append(
            {
                "frame": str(int(frame)),
                "status": "measured",
                **dict(zip(CSV_COLUMNS[2:11], (_fmt(v, 4) for v in values), strict=True)),
                "flagged": str(int(flagged[i])),
                **dict(zip(CSV_COLUMNS[12:], (_fmt(v, 4) for v in points), strict=True)),
            }
        )
    return rows


def write_metrics_csv(kin: KneeKinematics, path: Path | str) -> Path:
    """Write one row per frame with the CSV_COLUMNS header ("flagged" is 0 or 1; a frame not
    measured has its reason as status and no numbers).

    Args:
        kin: per-frame knee metrics.
        path: output file.

    Returns:
        The written path.
    """
    path = Path(path)
    with path.open("w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        writer.writerows(_metric_rows(kin))
    return path


def summary_rows(kin: KneeKinematics) -> dict[str, str]:
    """The report's summary table: frames and which are measured, flexion range, max |MLD| and
    where, DDV, flags (over the measured frames).

    Args:
        kin: per-frame knee metrics.

    Returns:
        Plain-text values by row label.
    """
    rows = {
        "Side": kin.side,
        "Frames": f"{len(kin.frames)} ({int(kin.frames[0])}–{int(kin.frames[-1])})",
        "Measured": measured_text(kin),
    }
    if not kin.measured.any():
        return rows | {"Flagged frames": "none: no frame measured"}
    mld = kin.mld_mm
    peak = int(np.nanargmax(np.abs(mld)))
    side = "medial" if mld[peak] > 0 else "lateral"
    n_flagged = int(np.count_nonzero(kin.flagged))
    flagged = f"{n_flagged} of {int(kin.measured.sum())} measured (|MLD| > {kin.flag_mm:g} mm)"
    return rows | {
        "Flexion range": f"{np.nanmin(kin.flexion_deg):.1f}° to {np.nanmax(kin.flexion_deg):.1f}°",
        "Max |MLD|": f"{abs(mld[peak]):.2f} mm, {side} gap larger, frame {int(kin.frames[peak])} "
        f"({angle_text(kin.flexion_deg[peak])})",
        "DDV (variance of MLD)": f"{kin.ddv_mm2:.2f} mm²",
        "Flagged frames": flagged if kin.sufficient else "none: tracking insufficient",
    }


def _table(
    rows: list[list[str]],
    header: list[str] | None = None,
    css_class: str = "",
    flagged: np.ndarray | None = None,
    excluded: np.ndarray | None = None,
) -> str:
    """An HTML table with escaped cells; rows where ``flagged`` is true are shaded red, those
    where ``excluded`` is true grey."""
    out = [f'<table class="{css_class}">' if css_class else "<table>"]
    if header:
        out.append("<tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in header) + "</tr>")
    for i, row in enumerate(rows):
        cls = ' class="flagged"' if flagged is not None and flagged[i] else ""
        if excluded is not None and excluded[i]:
            cls = ' class="excluded"'
        out.append(f"<tr{cls}>" + "".join(f"<td>{html.escape(c)}</td>" for c in row) + "</tr>")
    out.append("</table>")
    return "\n".join(out)


def _frame_table(kin: KneeKinematics) -> str:
    """Per-frame HTML table (angles and distances to 1-2 decimals), flagged rows shaded."""
    header = [
        "Frame",
        "Flexion (°)",
        "Varus (°)",
        "Int. rot. (°)",
        "ML shift (mm)",
        "AP drawer (mm)",
        "Distraction (mm)",
        "Medial (mm)",
        "Lateral (mm)",
        "MLD (mm)",
        "Flagged",
        "Status",
    ]
    rows = []
    for i, frame in enumerate(kin.frames):
        if not kin.measured[i]:
            rows.append([str(int(frame)), *["—"] * (len(header) - 2), _status(kin, i)])
            continue
        rows.append(
            [
                str(int(frame)),
                _fmt(kin.flexion_deg[i], 1),
                _fmt(kin.varus_deg[i], 1),
                _fmt(kin.internal_rotation_deg[i], 1),
                *(_fmt(t, 2) for t in kin.translation_mm[i]),
                _fmt(kin.medial_distance_mm[i], 2),
                _fmt(kin.lateral_distance_mm[i], 2),
                _fmt(kin.mld_mm[i], 2),
                "yes" if kin.flagged[i] else "",
                "measured",
            ]
        )
    return _table(rows, header, flagged=kin.flagged, excluded=~kin.measured)


def _steps(kin: KneeKinematics, overlays: Sequence[FrameOverlay]) -> list[dict]:
    """Per assessed frame: its number, caption and overlay's place in the filmstrip (-1: none)."""
    by_frame = {item.frame: (j, item) for j, item in enumerate(overlays)}
    steps = []
    for k, frame in enumerate(int(f) for f in kin.frames):
        j, item = by_frame.get(frame, (-1, None))
        caption = item.caption if item is not None else f"frame {frame}" + _flag_note(kin, k)
        steps.append({"frame": frame, "caption": caption, "image": j})
    return steps


def _motion(
    kin: KneeKinematics, overlays: Sequence[FrameOverlay], scene: MotionScene | None
) -> str:
    """The motion section: the registered frame beside the 3D view, play/pause, a frame
    slider, a caption, and a filmstrip of the overlays (each image embedded once, as the
    filmstrip's; the view shows the current one)."""
    steps = _steps(kin, overlays)
    step_of = {step["frame"]: k for k, step in enumerate(steps)}
    thumbs = []
    for item in overlays:
        data = base64.b64encode(item.png.read_bytes()).decode("ascii")
        cls = ' class="flagged"' if item.flagged else ' class="excluded"' if item.excluded else ""
        thumbs.append(
            f'<img{cls} src="data:image/png;base64,{data}" alt="frame {item.frame}" '
            f'data-step="{step_of.get(item.frame, 0)}">'
        )
    panes = []
    if overlays:
        panes.append(
            '<img class="view" id="overlay-view" alt="the current frame with the registered '
            'outlines">'
        )
    if scene is not None:
        panes.append(view_html(scene))
    strip = f'<div class="filmstrip">\n{"".join(thumbs)}\n</div>' if thumbs else ""
    steps_json = json.dumps(steps).replace("</", "<\\/")  # no end of the script in its text
    return f"""<h2>Motion</h2>
<div class="player">
<div class="panes">
{"".join(panes)}
</div>
<div class="controls"><button id="motion-play" type="button">Play</button>
<input id="motion-slider" type="range" min="0" max="{len(steps) - 1}" step="1" value="0">
<span id="motion-caption"></span></div>
{strip}
<p class="note">Left, each frame with every tracked body's outline at its registered pose
(frames the assessment flagged are framed in red, frames it did not measure dashed grey: their
registration failed or is implausible); right, the bodies at their registered
poses in 3D (drag to turn, scroll to zoom), the tibial plateau plane in green and the lowest
medial (blue) and lateral (orange) condyle points. The red rings on the plots mark the frame
shown. Click a frame of the strip to show it; open the report with <code>#play</code> after
its name to start playing, <code>#frame=N</code> to start at frame N.</p>
</div>
<script type="application/json" id="motion-steps">{steps_json}</script>
<script>{_MOTION_JS}</script>
"""


def _figure(name: str, path: Path, plot: Plot | None) -> str:
    """One plot as a figure; with ``plot``, a ring per marked series the player moves."""
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    rings = ""
    if plot is not None:
        rings = "".join(
            f'<i class="marker" data-xy="{json.dumps(json_points(xy, 4))}"></i>'
            for xy in plot.markers
        )
    return (
        f'<figure><div class="marked"><img src="data:image/png;base64,{data}" '
        f'alt="{html.escape(name)}">{rings}</div>'
        f"<figcaption>{html.escape(_CAPTIONS[name])}</figcaption></figure>"
    )


def _html(
    kin: KneeKinematics,
    title: str,
    extra_rows: dict[str, str],
    plots: dict[str, tuple[Path, Plot | None]],
    overlays: Sequence[FrameOverlay] = (),
    scene: MotionScene | None = None,
) -> str:
    """The complete report page."""
    summary = {**summary_rows(kin), **extra_rows}
    sentences = describe_flags(kin)
    box_class = "flags" if kin.flagged.any() else "flags clear"
    banner = ""
    if not kin.sufficient:
        box_class = "flags insufficient"
        banner = f'<div class="banner">{html.escape(insufficient_text(kin))}</div>\n'
    moving = bool(overlays) or scene is not None
    figures = [
        _figure(name, path, plot if moving else None) for name, (path, plot) in plots.items()
    ]
    flags = "\n".join(f"<p>{html.escape(s)}</p>" for s in sentences)
    motion = _motion(kin, overlays, scene) if moving else ""
    markers = f"<script>{_MARKERS_JS}</script>" if moving else ""
    return f"""<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta http-equiv="Content-Security-Policy" content="{_CSP}">
<title>{html.escape(title)}</title>
<style>{_CSS}</style>
</head>
<body>
<h1>{html.escape(title)}</h1>
{banner}<h2>Summary</h2>
{_table([[k, v] for k, v in summary.items()], css_class="summary")}
<h2>Flags</h2>
<div class="{box_class}">
{flags}
</div>
<p class="note">TP–condyle distances: lowest medial / lateral femoral condyle point to the tibial
plateau plane (Scarvell's method). MLD = medial − lateral distance; a frame is flagged when
|MLD| &gt; {kin.flag_mm:g} mm while a condyle rests on the plateau. DDV = variance of the MLD
over the measured frames. A frame whose registration failed or is implausible (a condyle deep
inside the plateau, both lifted far off it, a jump between frames) is not measured: no number,
no flag, a gap in the plots. Flags are cues for review of alignment and ligament balance, not
a diagnosis.</p>
{motion}<h2>Plots</h2>
<div class="plots">
{"".join(figures)}
</div>
<h2>Per-frame metrics</h2>
{_frame_table(kin)}
{markers}
</body>
</html>
"""


def write_report(
    kin: KneeKinematics,
    folder: Path | str,
    *,
    title: str,
    extra_rows: dict[str, str] | None = None,
    overlays: Sequence[FrameOverlay] = (),
    scene: MotionScene | None = None,
) -> dict[str, Path]:
    """Write metrics.csv, the plot PNGs and a self-contained report.html into ``folder``.

    Args:
        kin: per-frame knee metrics.
        folder: output folder (created if missing).
        title: page title and heading.
        extra_rows: more summary-table rows (label -> text), e.g. subject or scan id; shown
            after the computed rows, escaped.
        overlays: the registered frames with their outlines (:func:`frame_overlays`): a
            player and a filmstrip in the report, flagged frames marked.
        scene: the motion in 3D (:func:`assessment.viewer.motion_scene`): a 3D view the
            player drives, and the figure of the frames beside it. With overlays or a scene,
            a ring on each plot marks the frame shown; with neither, the page has no script.

    Returns:
        Paths by name: "report", "metrics" and one per plot (see ``assessment.plots.PLOTS``;
        "motion_frames" too when there are overlays, and "frames_beside_4d" with a scene).

    Raises:
        FileExistsError: if ``folder/report.html`` exists; nothing is written then.
    """
    folder = Path(folder)
    report = folder / "report.html"
    if report.exists():
        raise FileExistsError(f"{report} exists; refusing to overwrite the report")
    plots: dict[str, tuple[Path, Plot | None]] = dict(save_all(kin, folder))
    images = {item.frame: item.png for item in overlays}
    if images:
        path = folder / "motion_frames.png"
        path.write_bytes(motion_frames_png(kin, images))
        plots["motion_frames"] = (path, None)
    if images and scene is not None:
        path = folder / "frames_beside_4d.png"
        path.write_bytes(frames_beside_4d_png(kin, images, scene))
        plots["frames_beside_4d"] = (path, None)
    metrics = write_metrics_csv(kin, folder / "metrics.csv")
    with report.open("x", encoding="utf-8") as f:
        f.write(_html(kin, title, extra_rows or {}, plots, overlays, scene))
    return {"report": report, "metrics": metrics, **{k: p for k, (p, _) in plots.items()}}
