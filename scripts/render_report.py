"""Render an HTML report to a PNG screenshot with Debian's headless Chromium.

Usage: ``python scripts/render_report.py REPORT.html OUT.png``

Chromium runs with a fresh temporary profile, no sandbox (works as root in containers), no GPU
and no background networking, so the render depends only on the HTML file.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

WINDOW_PX = (1400, 4000)
"""Screenshot width and height, pixels."""

INSTALL_HINT = "install Debian's chromium: apt-get install -y chromium"


def find_chromium() -> str | None:
    """The Chromium executable: /usr/bin/chromium, else ``chromium`` on PATH, else None."""
    if Path("/usr/bin/chromium").is_file():
        return "/usr/bin/chromium"
    return shutil.which("chromium")


def render(
    html: Path | str,
    png: Path | str,
    *,
    window_px: tuple[int, int] = WINDOW_PX,
    timeout_s: float = 120.0,
) -> Path:
    """Screenshot ``html`` into ``png`` (``window_px`` wide x high) with headless Chromium.

    Args:
        html: the HTML file to render.
        png: the screenshot to write (overwritten).
        window_px: viewport width and height, pixels.
        timeout_s: how long Chromium may run, seconds.

    Returns:
        The screenshot path.

    Raises:
        FileNotFoundError: if ``html`` does not exist or Chromium is not installed.
        RuntimeError: if Chromium fails or writes no screenshot.
    """
    html = Path(html).resolve()
    png = Path(png).resolve()
    if not html.is_file():
        raise FileNotFoundError(f"no such HTML file: {html}")
    chromium = find_chromium()
    if chromium is None:
        raise FileNotFoundError(f"chromium not found; {INSTALL_HINT}")
    png.parent.mkdir(parents=True, exist_ok=True)
    png.unlink(missing_ok=True)
    with tempfile.TemporaryDirectory(prefix="render-report-") as profile:
        cmd = [
            chromium,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            f"--user-data-dir={profile}",
            f"--screenshot={png}",
            f"--window-size={window_px[0]},{window_px[1]}",
            html.as_uri(),
        ]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, check=False)
    if proc.returncode != 0 or not png.is_file():
        raise RuntimeError(
            f"chromium exited with {proc.returncode} and "
            f"{'wrote' if png.is_file() else 'did not write'} {png}:\n{proc.stderr.strip()}"
        )
    return png


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point; returns the process exit status."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("html", type=Path, help="report HTML file")
    parser.add_argument("png", type=Path, help="screenshot PNG to write")
    args = parser.parse_args(argv)
    try:
        out = render(args.html, args.png)
    except (FileNotFoundError, RuntimeError, subprocess.TimeoutExpired) as exc:
        print(f"render_report: {exc}", file=sys.stderr)
        return 1
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
