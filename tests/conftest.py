"""Shared fixtures: small analytic phantoms that build in milliseconds; a page opened in
headless Chromium; the machine the suite runs on, in its header (CPU, cores, numba's and
BLAS's threads and code paths), so that a failure on another machine can be read."""

from __future__ import annotations

import base64
import importlib.util
import io
import itertools
import json
import os
import platform
import re
import subprocess
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from recon.volume import VolumeGrid


def ball(
    grid: VolumeGrid, center_mm, radius_mm: float, value: float = 1.0, supersample: int = 3
) -> np.ndarray:
    """A ball rasterised with partial-volume (supersampled) edges, float32 [z, y, x]."""
    out = np.zeros(grid.shape, dtype=np.float32)
    x, y, z = grid.axes_mm()
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    cx, cy, cz = center_mm
    for ox in offsets:
        for oy in offsets:
            for oz in offsets:
                dx = (x + ox * grid.spacing_mm[0] - cx) ** 2
                dy = (y + oy * grid.spacing_mm[1] - cy) ** 2
                dz = (z + oz * grid.spacing_mm[2] - cz) ** 2
                out += (dz[:, None, None] + dy[None, :, None] + dx[None, None, :]) < radius_mm**2
    return out * np.float32(value / supersample**3)


def cylinder(
    grid: VolumeGrid,
    center_mm,
    radius_mm: float,
    half_height_mm: float,
    value: float = 1.0,
    supersample: int = 3,
) -> np.ndarray:
    """An upright (z) cylinder with partial-volume edges, float32 [z, y, x]."""
    out = np.zeros(grid.shape, dtype=np.float32)
    x, y, z = grid.axes_mm()
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    cx, cy, cz = center_mm
    for ox in offsets:
        for oy in offsets:
            r2 = (x[None, :] + ox * grid.spacing_mm[0] - cx) ** 2 + (
                y[:, None] + oy * grid.spacing_mm[1] - cy
            ) ** 2
            inside_xy = r2 < radius_mm**2
            for oz in offsets:
                inside_z = np.abs(z + oz * grid.spacing_mm[2] - cz) < half_height_mm
                out += inside_z[:, None, None] & inside_xy[None, :, :]
    return out * np.float32(value / supersample**3)


@pytest.fixture(scope="session")
def make_ball():
    return ball


@pytest.fixture(scope="session")
def make_cylinder():
    return cylinder


RENDER_SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "render_report.py"


@pytest.fixture(scope="session")
def artefacts() -> Path:
    """Where tests keep what a person may want to look at (screenshots), for CI to collect:
    ``CBCT_TEST_ARTIFACTS``, else build/test-artifacts."""
    default = Path(__file__).resolve().parents[1] / "build" / "test-artifacts"
    folder = Path(os.environ.get("CBCT_TEST_ARTIFACTS", default))
    folder.mkdir(parents=True, exist_ok=True)
    return folder


@pytest.fixture
def tmpfs(tmp_path) -> Iterator[Callable[[str], Path]]:
    """``tmpfs(options)``: a new folder with a tmpfs of its own mounted on it (``options`` as
    mount's ``-o``, e.g. ``size=8m`` or ``ro,size=64k``), unmounted after the test; skips
    where mounting is not allowed (it needs root)."""
    mounted = []

    def mount(options: str) -> Path:
        folder = tmp_path / f"tmpfs-{len(mounted)}"
        folder.mkdir()
        command = ["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)]
        if subprocess.run(command, capture_output=True, check=False).returncode != 0:
            pytest.skip("cannot mount a tmpfs here (needs root)")
        mounted.append(folder)
        return folder

    yield mount
    for folder in mounted:
        subprocess.run(["umount", "-l", str(folder)], check=False)


@pytest.fixture(scope="session")
def render_report():
    """scripts/render_report.py imported as a module (scripts is not a package)."""
    spec = importlib.util.spec_from_file_location("render_report", RENDER_SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@dataclass(frozen=True)
class Browsed:
    """A page as headless Chromium left it: its DOM, and the URLs the page itself asked the
    network for (from Chromium's net log: not file:, data: or blob:; the browser's own
    background requests, which have no origin, left out)."""

    dom: str
    requests: list[str]

    def canvas(self) -> np.ndarray:
        """The 3D view's canvas as the page wrote it into its DOM (``#probe``), RGB 0..1."""
        import matplotlib.image

        data = re.search(r'data-view3d="data:image/png;base64,([^"]+)"', self.dom).group(1)
        return matplotlib.image.imread(io.BytesIO(base64.b64decode(data)))[..., :3]


@pytest.fixture
def browse(render_report, tmp_path) -> Callable[..., Browsed]:
    """``browse(page, fragment="", budget_ms=4000)``: ``page#fragment`` once its scripts
    have run for ``budget_ms`` of Chromium's virtual clock (:class:`Browsed`); skips without
    Chromium."""
    chromium = render_report.find_chromium()
    if chromium is None:
        pytest.skip("chromium not installed (" + render_report.INSTALL_HINT + ")")
    runs = itertools.count()

    def open_page(page: Path, fragment: str = "", budget_ms: int = 4000) -> Browsed:
        netlog = tmp_path / f"chromium-net-{next(runs)}.json"
        dom = subprocess.run(
            [
                chromium,
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--enable-unsafe-swiftshader",  # WebGL on the CPU
                "--no-first-run",
                f"--user-data-dir={tmp_path / 'chromium-profile'}",
                f"--log-net-log={netlog}",
                f"--virtual-time-budget={budget_ms}",
                "--dump-dom",
                f"{page.as_uri()}#{fragment}" if fragment else page.as_uri(),
            ],
            capture_output=True,
            encoding="utf-8",  # the page's dashes, whatever the locale
            timeout=120,
            check=True,
        ).stdout
        log = json.loads(netlog.read_text(encoding="utf-8"))
        start = log["constants"]["logEventTypes"]["URL_REQUEST_START_JOB"]
        requests = [
            e["params"]["url"]
            for e in log["events"]
            if e["type"] == start
            and "url" in e.get("params", {})
            and e["params"].get("initiator") != "not an origin"
            and not e["params"]["url"].startswith(("file:", "data:", "blob:"))
        ]
        return Browsed(dom, requests)

    return open_page


def pytest_report_header(config) -> list[str]:
    """The CPU, and the threads and code paths the numerical libraries chose on it."""
    import llvmlite.binding
    import numba
    import threadpoolctl

    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            model = next(line for line in fh if line.startswith("model name")).split(":")[1]
    except (OSError, StopIteration):
        pass
    blas = ", ".join(
        f"{lib['internal_api']} {lib['version']} {lib.get('architecture', '')} "
        f"{lib['num_threads']} threads"
        for lib in threadpoolctl.threadpool_info()
        if lib["user_api"] == "blas"
    )
    cpu_name = numba.config.CPU_NAME or llvmlite.binding.get_host_cpu_name()
    return [
        f"machine: {model.strip()}, {os.cpu_count()} cores, {platform.machine()}",
        f"numba: {numba.config.NUMBA_NUM_THREADS} threads, code for {cpu_name}; BLAS: {blas}",
    ]


def pytest_addoption(parser) -> None:
    parser.addoption(
        "--seed",
        type=int,
        default=0,
        help="seed of the accuracy tests' random cases (noise, motion, starting poses); their "
        "spread over seeds, threads and CPUs is measured by scripts/test_spread.py",
    )


REALTIME = (
    "scanner/test_serial_devices.py",
    "scanner/test_stop.py",
    "scanner/test_stop_signals_scan.py",
    "scanner/test_ur.py",
    "scanner/test_ur_move.py",
    "scanner/test_ur_scan.py",
    "scanner/test_gige.py",
    "scanner/test_gige_realtime.py",
    "scanner/test_gige_scan.py",
    "scanner/test_spellman.py",
    "test_bench_soak.py",
)
"""Tests (folders or files under tests/) that drive devices on real clocks and bound their
times (time to SAFE, timeouts, pacing): marked ``realtime``. ``make test`` hands them to one
worker as one unit, first (:func:`pytest_xdist_make_scheduler`), so that beside them runs at
most one other test, single-threaded, on a machine of two cores or more: never enough work to
stretch their clocks. Every module that starts a fake GigE Vision panel is here: two fakes
streaming at once on one loopback cross-talk (a datagram of one reaches the other's stream or
discovery socket, and the driver rightly refuses it as a late or foreign frame)."""


RTK_PEER = (
    "recon/test_fdk.py",
    "recon/test_io.py",
    "recon/test_project.py",
    "recon/test_rtk_xml.py",
    "study/test_cli.py",
)
"""Test files that compare with the peer itk-rtk: loading RTK's wrapping takes 17 s in each
process, so ``make test`` hands them to one worker as one unit."""


FIRST_UNITS = ("realtime", "itk-rtk", "study/test_demo.py")
"""The longest units of ``make test`` (about 2 minutes each on one core), given out first so
that the two workers end together."""


def pytest_xdist_make_scheduler(config, log):
    """``--dist loadfile`` with the files of :data:`REALTIME` as one unit and those of
    :data:`RTK_PEER` as another, :data:`FIRST_UNITS` given out first; None (xdist's own
    scheduler) for the other modes."""
    if config.getoption("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class Units(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            where = super()._split_scope(nodeid).removeprefix("tests/")
            if where.startswith(REALTIME):
                return "realtime"
            return "itk-rtk" if where.startswith(RTK_PEER) else where

        def _assign_work_unit(self, node) -> None:
            for unit in reversed(FIRST_UNITS):
                if unit in self.workqueue:
                    self.workqueue.move_to_end(unit, last=False)
            super()._assign_work_unit(node)

    return Units(config, log)


def pytest_collection_modifyitems(config, items) -> None:
    """Tests that check an accuracy figure (they use ``measured``) are marked ``accuracy``;
    the tests of :data:`REALTIME` are marked ``realtime``."""
    tests = Path(__file__).resolve().parent
    for item in items:
        where = Path(str(item.path)).resolve().relative_to(tests).as_posix()
        if where.startswith(REALTIME):
            item.add_marker(pytest.mark.realtime)
        fixtures = getattr(item, "fixturenames", ())
        if "measured" in fixtures:
            item.add_marker(pytest.mark.accuracy)


@pytest.fixture(scope="session")
def seed(request) -> int:
    """The seed of the random test cases (``--seed``, 0 by default)."""
    return request.config.getoption("--seed")


@pytest.fixture
def measured(request, seed):
    """Check an accuracy figure against its bound, and record it (to the JSON-lines file
    ``CBCT_TEST_FIGURES`` names, when set) for scripts/test_spread.py.

    ``measured(name, value, below=None, above=None)``: fails unless ``value < below`` and
    ``value > above`` (whichever are given); with ``CBCT_TEST_FIGURES_ONLY`` set it only
    records, so that a test's later figures are measured too (scripts/test_spread.py judges
    them)."""
    path = os.environ.get("CBCT_TEST_FIGURES")
    record_only = bool(os.environ.get("CBCT_TEST_FIGURES_ONLY"))

    def check(name: str, value: float, *, below: float | None = None, above: float | None = None):
        value = float(value)
        if path:
            import json

            import numba

            row = {
                "test": request.node.nodeid,
                "figure": name,
                "value": value,
                "below": below,
                "above": above,
                "seed": seed,
                "numba_threads": numba.config.NUMBA_NUM_THREADS,
                "cpu": numba.config.CPU_NAME or "host",
                "blas": os.environ.get("OPENBLAS_CORETYPE", "auto"),
            }
            with open(path, "a", encoding="utf-8") as fh:
                fh.write(json.dumps(row) + "\n")
        if record_only:
            return
        if below is not None:
            assert value < below, f"{name} = {value:.6g}, not below {below:g}"
        if above is not None:
            assert value > above, f"{name} = {value:.6g}, not above {above:g}"

    return check


@pytest.fixture(scope="session")
def panel_maps(tmp_path_factory) -> Callable[..., Path]:
    """``panel_maps(protocol)``: a folder holding the simulated panel's maps in ``protocol``'s
    read-out mode, made once per mode by ``cbct detector-calibrate``'s code on the simulated
    backend (the UR backend's simulated panel is the same panel: same serial number)."""
    from configs import CONFIGS
    from scanner.detector_calibration import calibrate_session
    from scanner.inputs import read_inputs

    folder = tmp_path_factory.mktemp("detector-maps")
    made: set[tuple[int, int]] = set()

    def maps_for(protocol) -> Path:
        mode = (protocol.detector.rows, protocol.detector.cols)
        if mode not in made:
            inputs = read_inputs(
                protocol,
                CONFIGS / "scanner.yaml",
                "sim",
                CONFIGS / "backends" / "sim.yaml",
                CONFIGS / "phantoms" / "knee.yaml",
            )
            calibrate_session(inputs, folder, 8)
            made.add(mode)
        return folder

    return maps_for
