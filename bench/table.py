"""Markdown tables for the docs' benchmarks page (docs/benchmarks.md) from ``bench/out/all.json``.

One table per benchmark in the file (the columns of the page's tables), followed by a line
with the date, commit, machine and command measured. Without ``--write-readme`` the blocks are
printed between their markers; with it, each replaces the text between
``<!-- bench:begin NAME -->`` and ``<!-- bench:end NAME -->`` in the page (``--readme PATH``:
another file). Benchmarks absent from the file (or failed there) keep their current text.

Usage: ``python bench/table.py [ALL_JSON] [--write-readme] [--readme PATH]``.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from collections.abc import Callable, Iterable
from decimal import ROUND_HALF_UP, Decimal
from pathlib import Path

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
ALL_JSON = BENCH / "out" / "all.json"
README = ROOT / "docs" / "benchmarks.md"

# -- number formats -----------------------------------------------------------------------------


def fixed(x: float, decimals: int) -> str:
    """``x`` with ``decimals`` decimals, rounding its shortest decimal form half up (so a value
    the benchmark already rounded, e.g. 9.35, rounds as written, 9.4, not as stored, 9.3)."""
    return str(Decimal(repr(float(x))).quantize(Decimal(1).scaleb(-decimals), ROUND_HALF_UP))


def sig(x: float, digits: int) -> str:
    """``x`` to ``digits`` significant figures, trailing zeros kept (41.0, 0.040)."""
    if x == 0 or not math.isfinite(x):
        return str(x)
    decimals = max(0, digits - 1 - math.floor(math.log10(abs(x))))
    text = fixed(x, decimals)
    if decimals and len(text.lstrip("-0.").replace(".", "")) > digits:  # rounded up to 10^k
        text = fixed(x, decimals - 1)
    return text


def reg(x: float) -> str:
    """Registration errors: 3 significant figures, 2 below 1 (2.42, 0.76, 0.040)."""
    return sig(x, 3 if abs(x) >= 1 else 2)


def sci1(x: float) -> str:
    """One significant figure in short scientific notation: 3e-6."""
    if x == 0:
        return "0"
    mantissa, exponent = f"{x:.0e}".split("e")
    return f"{mantissa}e{int(exponent)}"


def table(header: Iterable[str], rows: Iterable[Iterable[object]]) -> str:
    """A markdown table."""
    header = list(header)
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["|" + "|".join(f" {c} " if str(c) else " " for c in row) + "|" for row in rows]
    return "\n".join(lines)


# -- one table per benchmark --------------------------------------------------------------------

REGIMES = ("matched", "independent", "cross_renderer")
BONES = ("femur", "tibia_fibula", "patella")


def registration_table(result: dict) -> str:
    """One row per regime x method (matched first, methods in the order run); the implant
    regimes (real_tka, tka: docs/implants.md) have their own tables there."""
    entries = sorted(
        (e for e in result["regimes"] if "method" in e),
        key=lambda e: REGIMES.index(e["regime"]) if e["regime"] in REGIMES else len(REGIMES),
    )
    rows = []
    for e in entries:
        by_bone = e.get("rsr_pct_by_body", e.get("rsr_pct_by_bone", {}))  # older runs: _bone
        bones = " / ".join(fixed(by_bone[b], 0) if b in by_bone else "–" for b in BONES)
        rows.append(
            [
                e["regime"],
                e["method"],
                e["sequences"],
                f"{reg(e['tre_mm'])} / {reg(e['tre_mm_median'])}",
                reg(e["in_plane_mm_median"]),
                reg(e["out_of_plane_mm_median"]),
                reg(e["out_of_plane_mm_rms"]),
                f"{fixed(e['rsr_pct'], 1)} ({bones})",
                f"{reg(e['mtrans_mm'])} / {reg(e['mrot_deg'])}",
                sig(e["s_per_frame"], 2) if "s_per_frame" in e else "",
                fixed(e["s_first_frame"], 1) if "s_first_frame" in e else "",
                fixed(e["drr_ms_256"], 2),
            ]
        )
    header = (
        "regime",
        "method",
        "seq",
        "TRE mean / median mm",
        "in-plane median mm",
        "out-of-plane median mm",
        "out-of-plane RMS mm",
        "RSR % (femur / tibia / patella)",
        "mTrans mm / mRot °",
        "s per frame",
        "s first frame",
        "DRR ms 256²",
    )
    return table(header, rows)


def calibration_table(r: dict) -> str:
    """Measure, value and target."""

    def e3(x: float) -> str:
        return f"{fixed(x * 1e3, 3)}e-3"

    rows = [
        (
            "ball reprojection RMS, median / max per view",
            f"{fixed(r['reproj_px_median'], 3)} / {fixed(r['reproj_px_max'], 3)} px",
            "",
        ),
        (
            "hold-out reprojection (5³ grid, ±40 mm), mean / p95",
            f"{fixed(r['holdout_reproj_px_mean'], 3)} / {fixed(r['holdout_reproj_px_p95'], 3)} px"
            f" ({fixed(r['holdout_reproj_mm_mean'], 3)} mm at the panel)",
            "≤ 0.08 px mean",
        ),
        (
            "same, planned (uncalibrated) geometry",
            f"{fixed(r['uncalibrated_holdout_px_mean'], 2)} px",
            "",
        ),
        (
            "free 11-parameter DLT: hold-out / source error",
            f"{fixed(r['free_dlt_holdout_px_mean'], 3)} px"
            f" / {fixed(r['free_dlt_source_err_mm_median'], 1)} mm",
            "",
        ),
        (
            "source error, median / max",
            f"{fixed(r['source_err_mm_median'], 2)} / {fixed(r['source_err_mm_max'], 2)} mm",
            "≤ 0.4 mm",
        ),
        (
            "panel centre error median / panel angle error median",
            f"{fixed(r['detector_center_err_mm_median'], 2)} mm"
            f" / {fixed(r['detector_angle_err_deg_median'], 3)}°",
            "≤ 0.2°",
        ),
        (
            "knee recon RMSE (256³ @ 0.5 mm): planned / calibrated / true",
            f"{e3(r['recon_rmse_nominal'])} / {e3(r['recon_rmse_calibrated'])}"
            f" / {e3(r['recon_rmse_true'])} /mm",
            "calibrated within 2 % of true",
        ),
        ("time", f"{fixed(r['s_per_view'], 3)} s per view", ""),
    ]
    return table(("measure", "value", "target"), rows)


def plan_table(result: dict) -> str:
    """One row per protocol; the ratio from the durations (more digits than the rounded
    ``duration_ratio``, which would round 1.02046 via 1.0205 to 1.021)."""
    rows = [
        (
            p["protocol"],
            p["views"],
            fixed(p["plan_s"], 2),
            fixed(p["duration_s"], 1),
            fixed(p["duration_lower_bound_s"], 1),
            fixed(p["duration_s"] / p["duration_lower_bound_s"], 3),
            f"{fixed(p['min_clearance_mm'], 1)} ({p['clearance_margin_mm']:g})",
            f"{sci1(p['max_pose_error_mm'])} mm, {sci1(p['max_pose_error_deg'])}°",
            p["limit_violations"],
        )
        for p in result["protocols"]
    ]
    header = (
        "protocol",
        "views",
        "plan s",
        "scan s",
        "lower bound s",
        "ratio",
        "min clearance mm (margin)",
        "max pose error",
        "limit violations",
    )
    return table(header, rows)


INPUTS = {"shepp_logan": ("Shepp–Logan", " (RTK analytic)"), "knee": ("knee", " (our projector)")}
"""Input label, and the note its first row carries."""


def recon_table(result: dict) -> str:
    """One row per orbit x input; RMSE to 3 significant figures of the input's smallest."""
    cases = result["cases"]
    half_travel = result.get("config", {}).get("travel_mm", 200.0) / 2
    orbits = {
        "circular": "circular",
        "short": "short scan",
        "helix": f"reverse spiral ±{half_travel:g} mm",
    }
    decimals = {}
    for kind in {c["input"] for c in cases}:
        smallest = min(
            x for c in cases if c["input"] == kind for x in (c["ours_rmse"], c["rtk_rmse"])
        )
        decimals[kind] = max(0, 2 - math.floor(math.log10(smallest))) if smallest > 0 else 4
    rows, seen = [], set()
    for c in cases:
        label, note = INPUTS.get(c["input"], (c["input"], ""))
        label += "" if c["input"] in seen else note
        seen.add(c["input"])
        d = decimals[c["input"]]
        drop = ""
        if "ours_axial_drop" in c:
            drop = (
                f"{fixed(100 * c['ours_axial_drop'], 1)} %"
                f" / {fixed(100 * c['rtk_axial_drop'], 1)} %"
            )
        rows.append(
            (
                orbits.get(c["case"], c["case"]),
                label,
                fixed(c["ours_s"], 1),
                fixed(c["rtk_s"], 1),
                fixed(c["speed_ratio"], 2),
                f"{fixed(c['ours_rmse'], d)} / {fixed(c['rtk_rmse'], d)}",
                f"{fixed(c['ours_peak_mb'], 0)} / {fixed(c['rtk_peak_mb'], 0)}",
                drop,
            )
        )
    header = (
        "orbit",
        "input",
        "ours s",
        "RTK s",
        "speed ratio",
        "RMSE ours / RTK",
        "peak MB ours / RTK",
        "axial drop ours / RTK",
    )
    return table(header, rows)


def scan_table(r: dict) -> str:
    """One row: the simulated scan with live reconstruction, and the UR fake scan's time."""
    row = (
        r["views"],
        r["panel"],
        fixed(r["sim_wall_s"], 1),
        fixed(r["render_s"], 1),
        fixed(r["per_view_overhead_ms"], 1),
        fixed(r["projections_per_s"], 1),
        f"{r['recon_backlog_max_views']} / {r['recon_backlog_at_last_view']} views",
        fixed(r["recon_ready_after_last_view_s"], 2),
        fixed(r["offline_recon_s"], 2),
        f"{sci1(r['streaming_max_abs_diff'])} /mm ({sci1(r['streaming_max_abs_diff_rel'])})",
        fixed(r["ur_fake_wall_s"], 1) if "ur_fake_wall_s" in r else "",
    )
    header = (
        "views",
        "panel",
        "sim wall s",
        "panel rendering s",
        "per-view overhead ms",
        "projections/s",
        "recon backlog max / at last view",
        "volume on disk after the last view s",
        "offline recon s",
        "live vs offline max abs (rel.)",
        "UR fake scan s",
    )
    return table(header, [row])


KIND_NAMES = {"controller_silent": "silent controller", "disk_full": "disk full"}
"""Fault kinds as the docs write them (others: underscores to spaces, signals upper case)."""


def kind_name(kind: str) -> str:
    """A fault kind as the docs write it: SIGINT, protective stop, silent controller."""
    if kind.startswith("sig"):
        return kind.upper()
    return KIND_NAMES.get(kind, kind.replace("_", " "))


DEADLINE_BOUNDS = {
    "generator_timeout": "generator_timeout",
    "controller_silent": "controller_silent",
    "disk_full": "disk_full_ur_backend",
    "camera_gone": "camera_gone",
    "dropped_frame": "dropped_frame_over_gige",
}
"""Faults found by a deadline, and the key of their bound in ``time_to_safe_bound_ms``."""


def soak_table(r: dict) -> str:
    """One row: faults, pulses after them, time to SAFE (signalled, and each deadline fault
    against its bound), views lost and corrupt files."""
    by_kind = sorted(r["faults_by_kind"].items(), key=lambda kv: (-kv[1], kind_name(kv[0]).lower()))
    faults = f"{r['faults']}: " + ", ".join(f"{kind_name(k)} {n}" for k, n in by_kind)
    bounds = r["time_to_safe_bound_ms"]
    deadline = ", ".join(
        f"{kind_name(k)} {fixed(ms, 1)} ({fixed(bounds[DEADLINE_BOUNDS[k]], 0)})"
        for k, ms in r["max_time_to_safe_ms_by_kind"].items()
        if DEADLINE_BOUNDS.get(k) in bounds
    )
    signalled = r["max_time_to_safe_ms"]
    row = (
        r["scans_complete"],
        r["seed"],
        fixed(r["wall_s"], 0),
        faults,
        r["x_ray_on_after_fault"],
        r["exp_after_stop"],
        r["faults_over_bound"],
        "" if signalled is None else fixed(signalled, 1),
        deadline,
        f"{r['views_lost']}, {r['corrupt_files']}",
    )
    header = (
        "scans",
        "seed",
        "wall s",
        "faults (by kind)",
        "pulses after a fault",
        "`EXP` after a stop",
        "faults over their bound",
        f"time to SAFE ms, signalled (target {fixed(bounds['signalled'], 0)})",
        "deadline faults ms (bound)",
        "views lost, corrupt",
    )
    return table(header, [row])


def detector_table(r: dict) -> str:
    """Two rows: the panel over GigE Vision (frames, lost, rate, a dead camera's time to the
    error), and the corrections (RMSE and rings of the demo knee)."""
    gige = (
        ""
        if "gige_skipped" in r
        else (
            f"{r['gige_frames']}/{r['gige_frames_requested']} frames, {r['gige_lost']} lost, "
            f"{fixed(r['gige_fps'], 0)} frames/s; camera gone -> error in "
            f"{fixed(r['gige_camera_gone_to_error_s'] * 1e3, 0)} ms = "
            f"{fixed(r['gige_camera_gone_frame_periods'], 1)} frame periods at "
            f"{fixed(r['gige_camera_gone_fps'], 0)} frames/s (target <= 3)"
        )
    )
    rows = [("GigE Vision, 512² Mono16 on loopback", gige or r.get("gige_skipped", ""))]
    if "rmse_ideal_panel" in r:
        rows.append(
            (
                f"demo knee, {r['recon']['views']} views of {r['recon']['pixels']}², "
                f"{r['recon']['voxel_mm']} mm voxels",
                f"RMSE ideal / corrected / uncorrected {sig(r['rmse_ideal_panel'], 4)} / "
                f"{sig(r['rmse_corrected'], 4)} / {sig(r['rmse_uncorrected'], 4)} /mm "
                f"(corrected {fixed(100 * (r['rmse_corrected_over_ideal'] - 1), 2)} % above "
                f"ideal, target 2 %); rings {fixed(r['ring_amplitude_ideal_panel'], 2)} / "
                f"{fixed(r['ring_amplitude_corrected'], 2)} / "
                f"{fixed(r['ring_amplitude_uncorrected'], 0)} noise SDs (target < 1)",
            )
        )
    return table(("case", "measured"), rows)


def mar_table(r: dict) -> str:
    """One row per reconstruction of the knee replacement: metal-free, uncorrected, NMAR."""
    rows = []
    for name in ("metal_free", "uncorrected", "mar"):
        e = r[name]
        dice = e.get("dice_near_metal")
        cell = (
            "segmentation failed"
            if dice is None
            else f"{fixed(dice['bone'], 3)} (femur {fixed(dice['femur'], 2)}, tibia "
            f"{fixed(dice['tibia'], 2)}, fibula {fixed(dice['fibula'], 2)}, patella "
            f"{fixed(dice['patella'], 2)})"
        )
        ratio = e.get("rmse_vs_metal_free")
        rmse = f"{sig(e['rmse_outside_metal_per_mm'], 3)}" + (
            f" ({fixed(ratio, 2)} x metal-free; target 1.10)" if ratio is not None else ""
        )
        rows.append((name.replace("_", "-"), rmse, cell))
    header = ("volume", "RMSE outside the metal, 1/mm", "bone Dice within 20 mm of metal")
    return table(header, rows) + (
        f"\n\n{r['views']} views of {r['panel']}², {r['voxel_mm']} mm voxels, {r['tube_kv']:g} kV; "
        f"metal {fixed(r['metal_cm3'], 0)} cm³ found (Dice {fixed(r['metal_dice'], 2)} with the "
        f"truth's), NMAR {fixed(r['nmar_s'], 0)} s."
    )


ITERATIVE_METHODS = ("fdk", "sart", "tv", "rtk_sart", "rtk_cg", "rtk_tv")


def iterative_table(r: dict) -> str:
    """RMSE per scan and method (and the knee's bone Dice), then seconds against RTK's, then
    one SART iteration at 256^3."""
    rows = [x for x in r["rows"] if x["case"] != "speed"]
    scans = sorted(
        {(x["case"], x["views"], x["mas_fraction"]) for x in rows},
        key=lambda k: (k[0], -k[1], -k[2]),
    )
    cell = {(x["case"], x["views"], x["mas_fraction"], x["method"]): x for x in rows}
    accuracy = []
    for case, views, mas in scans:
        got = [cell.get((case, views, mas, m)) for m in ITERATIVE_METHODS]
        dice = [cell.get((case, views, mas, m), {}).get("bone_dice") for m in ("fdk", "tv")]
        accuracy.append(
            (
                case.replace("_", "-"),
                views,
                fixed(mas, 2),
                *(f"{1e3 * g['rmse']:.3f}" if g else "" for g in got),
                " / ".join("-" if d is None else fixed(d, 3) for d in dice),
            )
        )
    header = ("object", "views", "mAs", "FDK", "SART", "TV", "RTK SART", "RTK CG", "RTK ADMM-TV")
    first = table((*header, "bone Dice FDK / TV"), accuracy)
    speed = []
    for case, views, mas in scans:
        pairs = [
            (cell.get((case, views, mas, a)), cell.get((case, views, mas, b)))
            for a, b in (("sart", "rtk_sart"), ("tv", "rtk_tv"))
        ]
        if not all(a and b for a, b in pairs):
            continue
        speed.append(
            (
                case.replace("_", "-"),
                views,
                fixed(mas, 2),
                *(
                    f"{fixed(a['seconds'], 1)} / {fixed(b['seconds'], 1)} "
                    f"({fixed(b['seconds'] / a['seconds'], 1)}x)"
                    for a, b in pairs
                ),
            )
        )
    second = table(
        ("object", "views", "mAs", "SART s, ours / RTK", "TV s, ours / RTK ADMM-TV"), speed
    )
    cfg = r["config"]
    text = (
        f"RMSE x 10^3 (1/mm) against the truth; {cfg['iterations']} iterations of every "
        f"iterative method from the same FDK volume; {cfg['photons_full']:.0e} photons per "
        f"pixel at full mAs; {cfg['voxel_mm']} mm voxels, {cfg['panel']}² pixels of "
        f"{cfg['pitch_mm']} mm.\n\n{first}\n\n{second}"
    )
    one = {x["method"]: x for x in r["rows"] if x["case"] == "speed"}
    if "sart" in one and "rtk_sart" in one:
        ours, theirs = (
            one["sart"]["seconds_per_iteration"],
            one["rtk_sart"]["seconds_per_iteration"],
        )
        text += (
            f"\n\nOne SART iteration at 256³ (0.5 mm) from 360 views of 512²: ours "
            f"{fixed(ours, 1)} s, RTK {fixed(theirs, 1)} s ({fixed(theirs / ours, 1)}x)."
        )
    return text


TABLES: dict[str, Callable[[dict], str]] = {
    "calibration": calibration_table,
    "detector": detector_table,
    "iterative": iterative_table,
    "mar": mar_table,
    "plan": plan_table,
    "recon": recon_table,
    "registration": registration_table,
    "scan": scan_table,
    "soak": soak_table,
}


# -- blocks and the README ----------------------------------------------------------------------


def duration(seconds: float) -> str:
    """Wall time for the measured line: 21 s, 17 min."""
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.0f} min"


def measured_line(record: dict, meta: dict) -> str:
    """Date, commit, machine and command of one benchmark's run."""
    date = str(meta.get("date", "?"))[:10]
    commit = meta.get("commit") or "?"
    if meta.get("dirty"):
        commit += " with uncommitted changes"
    cpus = meta.get("cpu_count")
    facts = (f"{cpus} CPUs" if cpus else "", meta.get("cpu_model") or "", meta.get("machine") or "")
    where = ", ".join(x for x in facts if x)
    where = f" ({where})" if where else ""
    return (
        f"Measured {date} at commit {commit}{where}: `{record['command']}`,"
        f" {duration(record['seconds'])}."
    )


def blocks(data: dict) -> dict[str, str]:
    """Markdown (table and measured line) per benchmark that has a result and a table."""
    meta = data.get("_meta", {})
    out = {}
    for name, record in data.items():
        if name.startswith("_"):
            continue
        if "result" not in record:
            error = record.get("error")
            print(f"[bench/table] {name}: no result ({error}), skipped", file=sys.stderr)
        elif name not in TABLES:
            print(f"[bench/table] {name}: no table for this benchmark, skipped", file=sys.stderr)
        else:
            out[name] = f"{TABLES[name](record['result'])}\n\n{measured_line(record, meta)}"
    return out


def markers(name: str) -> tuple[str, str]:
    """The README markers around one benchmark's block."""
    return f"<!-- bench:begin {name} -->", f"<!-- bench:end {name} -->"


def wrapped(name: str, block: str) -> str:
    """A block between its markers, blank lines inside so the markdown renders alike."""
    begin, end = markers(name)
    return f"{begin}\n\n{block}\n\n{end}"


def replace_blocks(text: str, new: dict[str, str]) -> tuple[str, list[str]]:
    """``text`` with each named block's marked part replaced; also the names without markers
    (exactly one begin and one end marker, in that order) in ``text``."""
    missing = []
    for name, block in new.items():
        begin, end = markers(name)
        pattern = re.compile(re.escape(begin) + r".*?" + re.escape(end), re.DOTALL)
        if text.count(begin) != 1 or text.count(end) != 1 or not pattern.search(text):
            missing.append(name)
            continue
        text = pattern.sub(lambda _m, n=name, b=block: wrapped(n, b), text)
    return text, missing


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("path", nargs="?", type=Path, default=ALL_JSON, help="all.json")
    parser.add_argument("--write-readme", action="store_true", help="update the README")
    parser.add_argument("--readme", type=Path, default=README)
    args = parser.parse_args(argv)
    new = blocks(json.loads(args.path.read_text(encoding="utf-8")))
    if not args.write_readme:
        print("\n\n".join(wrapped(n, b) for n, b in new.items()))
        return 0
    original = args.readme.read_text(encoding="utf-8")
    text, missing = replace_blocks(original, new)
    if text != original:
        args.readme.write_text(text, encoding="utf-8")
    for name in new:
        state = "NOT updated (markers missing)" if name in missing else "updated"
        print(f"[bench/table] {args.readme}: {name} {state}", file=sys.stderr)
    return 1 if missing else 0


if __name__ == "__main__":
    sys.exit(main())
