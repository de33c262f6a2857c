"""bench/table.py: README tables from the JSON the benchmarks print, written between markers."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _load(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(f"bench_{name}", ROOT / "bench" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


table = _load("table")

PLAN = {
    "benchmark": "plan",
    "protocols": [
        {
            "protocol": "knee_reverse_spiral_360",
            "views": 360,
            "plan_s": 1.498,
            "duration_s": 26.532,
            "total_duration_s": 34.201,
            "duration_lower_bound_s": 26.0,
            "duration_ratio": 1.0205,
            "min_clearance_mm": 25.0,
            "min_clearance_at": {"phase": "approach", "time_s": 0.0, "pair": ["a", "floor"]},
            "clearance_margin_mm": 20.0,
            "max_pose_error_mm": 2.871535036030304e-06,
            "max_pose_error_deg": 5.8205941466014714e-08,
            "limit_violations": 0,
            "trajectory_samples": 23996,
        }
    ],
}
CALIBRATION = {
    "benchmark": "calibration",
    "views": 360,
    "balls": 24,
    "vibration": {"source_mm": 0.5, "detector_mm": 0.5, "detector_deg": 0.2},
    "centroid_noise_px": 0.1,
    "calibrated_views": 360,
    "reproj_px_median": 0.13169893826554918,
    "reproj_px_max": 0.16886548686480343,
    "holdout_reproj_px_mean": 0.053312740731989945,
    "holdout_reproj_px_p95": 0.11541448036193729,
    "holdout_reproj_mm_mean": 0.03198764443919397,
    "uncalibrated_holdout_px_mean": 0.6390685846126412,
    "free_dlt_holdout_px_mean": 0.121350182691994,
    "free_dlt_source_err_mm_median": 2.5154336802269905,
    "source_err_mm_median": 0.37012237056879604,
    "source_err_mm_max": 1.4684457747865094,
    "detector_center_err_mm_median": 0.27671806567487783,
    "detector_angle_err_deg_median": 0.1961985188147134,
    "gauge_offset_mm": 0.5221839919776267,
    "s_per_view": 0.14791882389722055,
    "recon_rmse_nominal": 0.0012814677320420742,
    "recon_rmse_calibrated": 0.0008565958123654127,
    "recon_rmse_true": 0.0008544284501112998,
}


def _recon_case(case: str, kind: str, ours_rmse: float, rtk_rmse: float, **extra) -> dict:
    return {
        "case": case,
        "input": kind,
        "ours_s": 11.45,
        "rtk_s": 38.9,
        "speed_ratio": 3.397,
        "ours_rmse": ours_rmse,
        "rtk_rmse": rtk_rmse,
        "ours_ssim": 0.92,
        "rtk_ssim": 0.92,
        "ours_peak_mb": 915.8,
        "rtk_peak_mb": 2054.6,
        "max_abs_diff_vs_rtk": 3e-5,
        **extra,
    }


RECON = {
    "benchmark": "recon",
    "config": {
        "size": 256,
        "voxel_mm": 0.5,
        "views": 360,
        "panel": 512,
        "pitch_mm": 0.8,
        "knee_voxel_mm": 0.4,
        "travel_mm": 200.0,
    },
    "cases": [
        _recon_case("circular", "shepp_logan", 0.09307, 0.09307),
        _recon_case(
            "helix", "shepp_logan", 0.10761, 0.11662, ours_axial_drop=0.008, rtk_axial_drop=0.1131
        ),
        _recon_case("circular", "knee", 0.000927, 0.000927),
        _recon_case("short", "knee", 0.0010243, 0.0010243),
    ],
}


def _registration(regime: str, method: str, sequences: int, **floor) -> dict:
    return {
        "regime": regime,
        "method": method,
        "tx_mm": 1.1,
        "ty_mm": 1.3,
        "tz_mm": 0.8,
        "ra_deg": 0.13,
        "rb_deg": 0.7,
        "rg_deg": 0.19,
        "in_plane_mm_median": 0.04041933511799267,
        "out_of_plane_mm_median": 0.7508888405116112,
        "out_of_plane_mm_rms": 29.818647212805576,
        "tre_mm": 41.03713582429238,
        "tre_mm_median": 0.7587517679762024,
        "rsr_pct": 90.74074074074075,
        "rsr_pct_by_bone": {"femur": 100.0, "patella": 77.77777777777779, "tibia_fibula": 94.4},
        "mtrans_mm": 1.0825708124740927,
        "mrot_deg": 0.34413381947772065,
        "registrations": 270,
        "s_per_frame": 7.050458120310196,
        "s_first_frame": 7.365881835667096,
        "drr_ms_256": 3.43,
        "sequences": sequences,
        "frames": 30,
        **floor,
    }


REGISTRATION = {
    "benchmark": "registration",
    "regimes": [
        _registration("independent", "boneaxis_kpm", 3),
        _registration(
            "matched",
            "boneaxis_kpm",
            3,
            floor_start_at_truth=[
                {
                    "distortion_px": 0.0,
                    "tre_mm": 0.25,
                    "in_plane_mm_median": 0.008,
                    "out_of_plane_mm_median": 0.07,
                }
            ],
        ),
    ],
}
SCAN = {
    "views": 360,
    "panel": "512x512",
    "recon_grid": [194, 194, 444],
    "sim_wall_s": 36.14,
    "render_s": 17.71,
    "per_view_overhead_ms": 15.24,
    "projections_per_s": 15.7,
    "recon_backlog_max_views": 31,
    "recon_backlog_at_last_view": 24,
    "recon_ready_after_last_view_s": 0.95,
    "offline_recon_s": 6.93,
    "streaming_max_abs_diff": 1.1e-08,
    "streaming_max_abs_diff_rel": 2.04e-07,
    "ur_fake_wall_s": 17.2,
}
SOAK = {
    "benchmark": "soak",
    "scans": 20,
    "scans_complete": 20,
    "seed": 0,
    "faults": 14,
    "faults_by_kind": {"controller_silent": 3, "disk_full": 2, "interlock": 3, "sigint": 6},
    "views_lost": 0,
    "corrupt_files": 0,
    "x_ray_on_after_fault": 0,
    "exp_after_stop": 0,
    "max_time_to_safe_ms": 12.8,
    "max_time_to_safe_ms_by_kind": {
        "controller_silent": 102.34,
        "disk_full": 318.2,
        "interlock": 3.1,
        "sigint": 12.8,
    },
    "time_to_safe_bound_ms": {
        "signalled": 100.0,
        "generator_timeout": 2100.0,
        "controller_silent": 220.0,
        "disk_full_ur_backend": 842.3,
    },
    "faults_over_bound": 0,
    "wall_s": 693.4,
}
META = {
    "date": "2026-11-23T10:00:00+00:00",
    "commit": "abc1234",
    "dirty": False,
    "cpu_count": 2,
    "cpu_model": "AMD EPYC 9B14",
    "machine": "x86_64",
}


def _all(**results: dict) -> dict:
    data = {
        name: {"command": f"python bench/{name}.py", "seconds": 21.4, "result": result}
        for name, result in results.items()
    }
    return data | {"_meta": META}


def test_tables_carry_the_readme_columns_and_formats():
    blocks = table.blocks(
        _all(plan=PLAN, calibration=CALIBRATION, recon=RECON, registration=REGISTRATION)
    )
    assert (
        "| knee_reverse_spiral_360 | 360 | 1.50 | 26.5 | 26.0 | 1.020 | 25.0 (20)"
        " | 3e-6 mm, 6e-8° | 0 |" in blocks["plan"]
    )
    assert (
        "Measured 2026-11-23 at commit abc1234 (2 CPUs, AMD EPYC 9B14, x86_64): `python "
        "bench/plan.py`, 21 s." in (blocks["plan"])
    )
    calibration = blocks["calibration"]
    assert "| measure | value | target |" in calibration
    assert "| ball reprojection RMS, median / max per view | 0.132 / 0.169 px | |" in calibration
    assert "| 0.053 / 0.115 px (0.032 mm at the panel) | ≤ 0.08 px mean |" in calibration
    assert "| 1.281e-3 / 0.857e-3 / 0.854e-3 /mm | calibrated within 2 % of true |" in calibration
    assert "| 0.28 mm / 0.196° | ≤ 0.2° |" in calibration
    recon = blocks["recon"].splitlines()
    assert recon[2] == (
        "| circular | Shepp–Logan (RTK analytic) | 11.5 | 38.9 | 3.40 | 0.0931 / 0.0931"
        " | 916 / 2055 | |"
    )
    assert recon[3].startswith("| reverse spiral ±100 mm | Shepp–Logan | ")
    assert recon[3].endswith("| 0.1076 / 0.1166 | 916 / 2055 | 0.8 % / 11.3 % |")
    assert "| circular | knee (our projector) |" in recon[4]
    assert "| short scan | knee | 11.5 |" in recon[5] and "0.001024 / 0.001024" in recon[5]
    rows = blocks["registration"].splitlines()
    assert rows[0].startswith("| regime | method | seq | TRE mean / median mm |")
    assert rows[0].endswith("| s per frame | s first frame | DRR ms 256² |")
    assert rows[2] == (  # matched first, whatever order the regimes ran in
        "| matched | boneaxis_kpm | 3 | 41.0 / 0.76 | 0.040 | 0.75 | 29.8 | 90.7 (100 / 94 / 78)"
        " | 1.08 / 0.34 | 7.1 | 7.4 | 3.43 |"
    )
    assert rows[3].startswith("| independent | boneaxis_kpm | 3 |")


def test_scan_and_soak_tables():
    blocks = table.blocks(_all(scan=SCAN, soak=SOAK))
    assert blocks["scan"].splitlines()[2] == (
        "| 360 | 512x512 | 36.1 | 17.7 | 15.2 | 15.7 | 31 / 24 views | 0.95 | 6.93"
        " | 1e-8 /mm (2e-7) | 17.2 |"
    )
    soak = blocks["soak"].splitlines()
    assert "| time to SAFE ms, signalled (target 100) |" in soak[0]
    assert soak[2] == (  # kinds by count, then name; deadline faults with their bounds
        "| 20 | 0 | 693 | 14: SIGINT 6, interlock 3, silent controller 3, disk full 2 | 0 | 0 | 0"
        " | 12.8 | silent controller 102.3 (220), disk full 318.2 (842) | 0, 0 |"
    )


def test_failed_and_unknown_benchmarks_are_skipped():
    data = _all(plan=PLAN) | {
        "recon": {"command": "python bench/recon.py", "seconds": 3.0, "error": "exit status 1"},
        "newbench": {"command": "python bench/newbench.py", "seconds": 1.0, "result": {}},
    }
    assert list(table.blocks(data)) == ["plan"]


@pytest.mark.parametrize(
    ("x", "digits", "text"), [(41.0371, 3, "41.0"), (0.0404, 2, "0.040"), (0.0996, 2, "0.10")]
)
def test_significant_figures_keep_trailing_zeros(x, digits, text):
    assert table.sig(x, digits) == text


README = """# Project

## Benchmarks

`python bench/plan.py` (20 seconds): planning.

<!-- bench:begin plan -->

| protocol | old |
|---|---|
| x | 1 |

<!-- bench:end plan -->

`python bench/recon.py`: prose that stays.

<!-- bench:begin recon -->

| orbit | old recon |

<!-- bench:end recon -->

## After
"""


def test_write_readme_replaces_only_the_marked_blocks(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text(README, encoding="utf-8")
    path = tmp_path / "all.json"
    path.write_text(json.dumps(_all(plan=PLAN)), encoding="utf-8")  # recon missing: its block stays
    assert table.main([str(path), "--write-readme", "--readme", str(readme)]) == 0
    text = readme.read_text(encoding="utf-8")
    before, _, rest = text.partition("<!-- bench:begin plan -->")
    inside, _, after = rest.partition("<!-- bench:end plan -->")
    old_before, _, old_rest = README.partition("<!-- bench:begin plan -->")
    assert before == old_before
    assert after == old_rest.partition("<!-- bench:end plan -->")[2]
    assert "| x | 1 |" not in inside and "| knee_reverse_spiral_360 | 360 | 1.50 |" in inside
    assert inside.startswith("\n\n| protocol | views |") and inside.endswith("21 s.\n\n")
    assert "| orbit | old recon |" in after
    # idempotent
    assert table.main([str(path), "--write-readme", "--readme", str(readme)]) == 0
    assert readme.read_text(encoding="utf-8") == text


def test_write_readme_without_markers_reports_and_leaves_the_file(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text("# Project\n", encoding="utf-8")
    path = tmp_path / "all.json"
    path.write_text(json.dumps(_all(plan=PLAN)), encoding="utf-8")
    assert table.main([str(path), "--write-readme", "--readme", str(readme)]) == 1
    assert readme.read_text(encoding="utf-8") == "# Project\n"


def _iterative_row(case, method, views, mas, rmse, seconds, dice=None):
    return {
        "case": case,
        "method": method,
        "views": views,
        "mas_fraction": mas,
        "iterations": 4,
        "rmse": rmse,
        "ssim": 0.9,
        "bone_dice": dice,
        "seconds": seconds,
        "seconds_per_iteration": seconds / 4,
        "peak_mb": 300.0,
    }


def test_iterative_table_rmse_per_method_seconds_against_rtk_and_one_iteration():
    rows = [
        _iterative_row("knee", m, 90, 0.25, r, s, d)
        for m, r, s, d in (
            ("fdk", 0.00241, 0.1, 0.89),
            ("sart", 0.00157, 0.6, None),
            ("tv", 0.00163, 0.6, 0.92),
            ("rtk_sart", 0.00185, 3.6, None),
            ("rtk_cg", 0.00164, 2.6, None),
            ("rtk_tv", 0.00156, 5.2, None),
        )
    ]
    rows += [
        {**_iterative_row("speed", "sart", 360, None, 0.01, 30.0), "seconds_per_iteration": 30.0},
        {
            **_iterative_row("speed", "rtk_sart", 360, None, 0.01, 150.0),
            "seconds_per_iteration": 150.0,
        },
    ]
    config = {"iterations": 4, "photons_full": 2e4, "voxel_mm": 2.0, "panel": 160, "pitch_mm": 2.4}
    lines = table.iterative_table({"config": config, "rows": rows}).splitlines()
    assert (
        "| knee | 90 | 0.25 | 2.410 | 1.570 | 1.630 | 1.850 | 1.640 | 1.560 | 0.890 / 0.920 |"
        in lines
    )
    assert "| knee | 90 | 0.25 | 0.6 / 3.6 (6.0x) | 0.6 / 5.2 (8.7x) |" in lines
    assert lines[-1].endswith("ours 30.0 s, RTK 150.0 s (5.0x).")
