"""The hot kernels stay fast in the ways a test can see without a clock: each compiles once per
process, for C-contiguous arrays, in nopython mode with its parallel loops; and OpenMP threads
wait passively, so a run beside another degrades gracefully (docs/design.md, "Threads")."""

from __future__ import annotations

import inspect
import os
import re
import subprocess
import sys

import numba
import numpy as np
import pytest
from numba.core.caching import NullCache
from numba.core.types import Array

from recon import fdk as fdk_module
from recon import motion, project, ramp
from recon.fdk import fdk_reconstruct
from recon.geometry import DetectorSpec, circular_orbit
from recon.volume import VolumeGrid

PARALLEL = {
    "backprojection": project._backproject_kernel,
    "upright backprojection": project._upright_kernel,
    "forward projection": project._joseph_kernel,
    "pixel quads": project.quads_kernel,
    "row filter's weighting": ramp._pack_kernel,
    "normalisation": fdk_module._normalise_kernel,
    "coverage": fdk_module._coverage_kernel,
    "motion field's backprojection": motion._field_kernel,
    "rays' lengths through the grid": project._chords_kernel,
}
"""The FDK's, the projector's and SART's parallel kernels, by what they do."""


@pytest.fixture(scope="module")
def ran() -> None:
    """A small FDK (plain and through a motion field), a forward projection and the rays'
    lengths: every kernel of :data:`PARALLEL` compiled."""
    views = circular_orbit(24, 600.0, 1000.0, DetectorSpec(rows=32, cols=32, pixel_pitch_mm=2.0))
    grid = VolumeGrid.centered((16, 16, 16), 2.0, (0.0, 0.0, 0.0))
    sino = project.forward_project(np.ones(grid.shape, np.float32), grid, views)
    project.centre_chords(views, grid)
    assert fdk_reconstruct(sino, views, grid).coverage_deg.max() > 0
    poses = np.tile(np.eye(4), (len(views), 2, 1, 1))
    weights = np.full((2, *grid.shape), 0.5, np.float32)
    fdk_reconstruct(sino, views, grid, motion=motion.BodyMotion(("a", "b"), poses, weights, grid))


@pytest.mark.parametrize("name", sorted(PARALLEL))
def test_a_hot_kernel_compiles_once_for_contiguous_arrays(ran, name):
    """One signature per kernel in the process (a second means a second compilation and a
    slower layout somewhere), and every array argument C-contiguous ('A' arrays cost the
    vectoriser its unit strides)."""
    kernel = PARALLEL[name]
    assert len(kernel.signatures) == 1, (name, kernel.signatures)
    arrays = [t for t in kernel.signatures[0] if isinstance(t, Array)]
    assert arrays and all(t.layout == "C" for t in arrays), (name, kernel.signatures[0])
    assert kernel.targetoptions.get("parallel") and kernel.targetoptions.get("fastmath"), name
    assert not isinstance(kernel._cache, NullCache), f"{name}: compiled again in every process"


@pytest.mark.parametrize("name", sorted(PARALLEL))
def test_a_hot_kernel_keeps_its_parallel_loops_in_nopython_mode(ran, name):
    """Its ``prange`` loops are parallel loops (parfors), read from the compiled kernel's type
    annotation, which the cache keeps (a ``prange`` numba could not parallelise runs serially
    with a warning nobody reads); nopython mode, no lifted loop nor reflected list."""
    kernel = PARALLEL[name]
    signature = kernel.signatures[0]
    result = kernel.overloads[signature]
    assert not result.objectmode and not result.lifted, name
    assert not any("reflected" in str(t) for t in signature), name
    lines, first = inspect.getsourcelines(kernel.py_func)
    pranges = {first + k for k, line in enumerate(lines) if "prange(" in line}
    annotation = str(result.type_annotation)
    parfors = {int(n) for n in re.findall(r"Var\(parfor_index\.\d+, [\w.]+:(\d+)\)", annotation)}
    assert pranges and pranges <= parfors, (name, sorted(pranges), sorted(parfors))


_POLICY = """
import ctypes, sys
import trajectories.model  # Pinocchio loads libgomp before any kernel runs
import numpy as np
from recon.project import pixel_quads
pixel_quads(np.ones((2, 8, 8), np.float32))
sys.stdout.flush()
ctypes.CDLL("libgomp.so.1").omp_display_env(1)
"""


@pytest.mark.parametrize(("given", "spins"), [(None, "0"), ("active", "30000000000")])
def test_openmp_threads_wait_passively_unless_told_otherwise(given, spins):
    """A process that loads Pinocchio (and its libgomp) first and then runs a numba kernel has
    its OpenMP threads sleep between parallel regions (libgomp's spin count 0; unset, it spins
    300,000 times at every barrier); OMP_WAIT_POLICY set by the user wins."""
    if numba.config.THREADING_LAYER not in ("default", "omp"):
        pytest.skip(f"numba's threading layer is {numba.config.THREADING_LAYER}, not OpenMP")
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if given is not None:
        env["OMP_WAIT_POLICY"] = given
    run = subprocess.run(
        [sys.executable, "-c", _POLICY], capture_output=True, text=True, env=env, check=True
    )
    shown = run.stdout + run.stderr
    if "GOMP_SPINCOUNT" not in shown:
        pytest.skip("this libgomp does not display its spin count")
    assert f"GOMP_SPINCOUNT = '{spins}'" in shown
