"""bench/scan.py in small (slow: a minute): the simulated scan with its live reconstruction, and
the UR backend's scan against the fake controllers, each to its end."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.slow
def test_the_scan_bench_runs_to_its_end():
    out = subprocess.run(
        [sys.executable, str(ROOT / "bench" / "scan.py"), "--small"],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    result = json.loads(out.stdout)
    assert result["views"] == 90 and result["recon_backlog_at_last_view"] >= 0
    # the live volume equals the offline one but for the order of float32 sums over 90 views:
    # at most ~90 float32 epsilons (1.2e-7) relative
    assert result["streaming_max_abs_diff_rel"] < 1e-5, result
    assert 0 < result["ur_fake_wall_s"] < 120, result  # the UR scan ran through, not refused
