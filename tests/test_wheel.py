"""The project built as an sdist and a wheel (``python -m build``), the wheel installed into a
fresh virtual environment outside the checkout: ``cbct --version`` and the quick demo run from
another folder, with the configs found as package data (slow: .ci/run runs it after the
default suite)."""

from __future__ import annotations

import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def run(*cmd: str | Path, cwd: Path, timeout: float = 900) -> str:
    out = subprocess.run(
        [str(c) for c in cmd], cwd=cwd, capture_output=True, text=True, timeout=timeout
    )
    assert out.returncode == 0, f"{cmd}\n{out.stdout[-2000:]}\n{out.stderr[-2000:]}"
    return out.stdout + out.stderr


@pytest.mark.slow
def test_the_wheel_installs_and_runs_outside_the_checkout(tmp_path):
    dist = tmp_path / "dist"
    run(sys.executable, "-m", "build", "--outdir", dist, ROOT, cwd=tmp_path)  # sdist, then wheel
    assert len(list(dist.glob("dualarm_cbct-*.tar.gz"))) == 1
    wheel = next(dist.glob("dualarm_cbct-*.whl"))
    fresh = tmp_path / "fresh"
    run(sys.executable, "-m", "venv", fresh, cwd=tmp_path)
    # the dependencies come from this environment: its package folders (Pinocchio's prefix
    # among them) go on the fresh one's path after the wheel's own packages
    purelib = Path(sysconfig.get_path("purelib", vars={"base": str(fresh), "platbase": str(fresh)}))
    ours = [p for p in sys.path if p.startswith(sys.prefix) and p.endswith("site-packages")]
    (purelib / "zz_dependencies.pth").write_text("\n".join(ours) + "\n", encoding="utf-8")
    run(fresh / "bin" / "python", "-m", "pip", "install", "--no-deps", "-q", wheel, cwd=tmp_path)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    cbct = fresh / "bin" / "cbct"
    assert run(cbct, "--version", cwd=elsewhere).strip().startswith("dualarm-cbct ")
    where = run(
        fresh / "bin" / "python", "-c", "import recon; print(recon.__file__)", cwd=elsewhere
    )
    assert str(fresh) in where and str(ROOT) not in where  # the wheel's code, not the checkout's
    output = run(cbct, "demo", "--quick", "--out", elsewhere / "demo", cwd=elsewhere)
    assert "demo finished" in output
    assert (elsewhere / "demo" / "assessment" / "report.html").is_file()
