"""The quick demo, made once per session: tests/study/test_demo.py checks it, and the batch
tests take hard-linked copies of its acquisitions (study files are replaced by rename, never
rewritten in place, so a copy's changes leave it as it was)."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from study.cli import app


@pytest.fixture(scope="session")
def demo(tmp_path_factory, seed) -> Path:
    out = tmp_path_factory.mktemp("demo") / "study"
    result = CliRunner().invoke(app, ["demo", "--out", str(out), "--quick", "--seed", str(seed)])
    assert result.exit_code == 0, result.output
    assert "demo finished" in result.output and f"rerun {out}/recording.rrd" in result.output
    return out
