"""The searches a body's pose goes through, each on one objective (registration.objective) in
the step ``x = (t mm, r deg)`` of registration.se3: differential evolution in a box along the
body's principal axes, Powell in a box, Nelder-Mead, Levenberg-Marquardt, and the KPM's line
search along the kinematic direction."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

import numba
import numpy as np
from scipy.optimize import differential_evolution, least_squares, minimize, minimize_scalar

from registration.objective import Searched
from registration.priors import KPM_LAMBDA
from registration.settings import Settings

Result = TypeVar("Result")

STEP_TOLERANCE = 1e-3
"""Least squares with Broyden's update stops once a step is this small in every coordinate,
in units of ``ls_step`` (2.5e-4 mm and deg at 0.25)."""


def at_once(searches: list[Callable[[], Result]]) -> list[Result]:
    """Each of ``searches`` run in a thread of its own, numba's threads shared out among them
    (at least one each); their results in order, or the first one's error. A search on small
    renders keeps two threads only partly busy: the Python between its renders (scipy's
    optimizer, the similarity) runs while another search renders. Results equal those of the
    searches run one by one, the renders being the same to the bit on any number of threads."""
    workers = min(len(searches), numba.config.NUMBA_NUM_THREADS)
    if workers <= 1:
        return [run() for run in searches]
    threads = max(1, numba.get_num_threads() // workers)

    def run(search: Callable[[], Result]) -> Result:
        numba.set_num_threads(threads)  # this thread's share: numba's setting is per thread
        return search()

    with ThreadPoolExecutor(workers, thread_name_prefix="search") as pool:
        return list(pool.map(run, searches))


def principal_axes(points_mm: np.ndarray) -> np.ndarray:
    """Columns: the body's principal axes (PCA of its points, (N, 3) mm), the longest first."""
    centered = points_mm - points_mm.mean(axis=0)
    _, _, vt = np.linalg.svd(centered[:: max(1, len(centered) // 20000)], full_matrices=False)
    return vt.T


def global_search(
    objective: Searched, axes: np.ndarray, settings: Settings, scale: float = 1.0
) -> np.ndarray:
    """Differential evolution (seeded, Sobol start, no polish) in a box of ``scale`` times the
    settings' ``de_*`` half-widths, its rotations about ``axes`` (columns: the body's
    principal axes at its current pose, the longest first); returns the step x."""
    s = settings

    def in_axes(y: np.ndarray) -> np.ndarray:
        x = np.empty(6)
        x[:3] = y[:3]
        x[3:] = axes @ y[3:]  # rotation vector (deg) about the principal axes
        return x

    t, rl, ro = (
        s.de_translation_mm * scale,
        s.de_long_axis_deg * scale,
        s.de_other_axes_deg * scale,
    )
    bounds = [(-t, t)] * 3 + [(-rl, rl), (-ro, ro), (-ro, ro)]
    result = differential_evolution(
        lambda y: objective(in_axes(y)),
        bounds,
        seed=s.seed,
        popsize=s.de_popsize,
        maxiter=s.de_maxiter,
        tol=1e-6,
        polish=False,
        init="sobol",
    )
    return in_axes(result.x)


def powell(objective: Searched, box: tuple[float, float], settings: Settings) -> np.ndarray:
    """Powell from the start, bounded to ``box`` (mm, deg) about it; returns the step x."""
    t_max, r_max = box
    return minimize(
        objective,
        np.zeros(6),
        method="Powell",
        bounds=[(-t_max, t_max)] * 3 + [(-r_max, r_max)] * 3,
        options={"maxfev": settings.powell_maxfev, "xtol": settings.powell_xtol, "ftol": 1e-5},
    ).x


def nelder_mead(objective: Searched, x0: np.ndarray, step: float, settings: Settings) -> np.ndarray:
    """Nelder-Mead from ``x0``, its simplex ``step`` (mm, deg) along each axis; returns x."""
    return minimize(
        objective,
        x0,
        method="Nelder-Mead",
        options={
            "maxfev": settings.nelder_mead_maxfev,
            "initial_simplex": np.vstack((x0, x0 + step * np.eye(6))),
            "xatol": 1e-2,
            "fatol": 1e-6,
        },
    ).x


def _central_jacobian(objective: Searched, scale: np.ndarray, x: np.ndarray) -> np.ndarray:
    """d residuals / d x at ``x`` by central differences of ``scale`` (mm, deg): 12 renders,
    made together (:meth:`Objective.residuals_many`)."""
    steps = np.diag(scale)
    r = objective.residuals_many(np.vstack((x + steps, x - steps)))
    # C order, as a Jacobian built column by column: BLAS then rounds J'J and J dz alike
    return np.ascontiguousarray(((r[:6] - r[6:]) / (2 * scale[:, None])).T)


def _damped_step(
    J: np.ndarray, r: np.ndarray, damping: float | None
) -> tuple[np.ndarray, float, float]:
    """Marquardt's step from residuals ``r`` on the Jacobian ``J`` (scaled step units):
    ``(J'J + damping diag(J'J)) dz = -J'r``; the damping starts at 1e-3 of the largest
    diagonal term. Returns dz, the decrease of half the squared norm it predicts, and the
    damping."""
    A, g = J.T @ J, J.T @ r
    diagonal = np.maximum(np.diag(A), 1e-12 * max(float(np.max(np.diag(A))), 1e-300))
    if damping is None:
        damping = 1e-3 * float(np.max(diagonal))
    dz = np.linalg.solve(A + damping * np.diag(diagonal), -g)
    return dz, float(-(g @ dz) - 0.5 * dz @ A @ dz), damping


def levenberg_marquardt(
    objective: Searched, settings: Settings, max_steps: int, broyden: bool
) -> np.ndarray:
    """Levenberg-Marquardt on :meth:`Objective.residuals` from the start; returns the step x.

    The Jacobian by central differences of the settings' ``ls_step`` (12 renders) at every step
    (scipy's MINPACK, ``max_steps`` residual evaluations as it counts them), or, with
    ``broyden``, at the start only: each of at most ``max_steps`` trial steps (one render)
    updates it by Broyden's rank-one formula, and a last central-difference Jacobian at the
    end takes one more step if that lowers the cost (Nielsen's damping; scipy's least squares
    recomputes the Jacobian at every step and offers no such update).
    """
    scale = np.repeat(np.asarray(settings.ls_step, dtype=np.float64), 3)
    if not broyden:
        return least_squares(
            objective.residuals,
            np.zeros(6),
            jac=lambda x: _central_jacobian(objective, scale, x),
            method="lm",
            x_scale=scale,
            xtol=1e-4,
            ftol=1e-8,
            max_nfev=max_steps,
        ).x
    x = np.zeros(6)
    r = objective.residuals(x)
    J = _central_jacobian(objective, scale, x) * scale  # per step unit, ls_step
    damping, grow = None, 2.0
    for _ in range(max_steps):
        dz, predicted, damping = _damped_step(J, r, damping)
        if predicted <= 0.0 or np.max(np.abs(dz)) < STEP_TOLERANCE:
            break
        trial = x + dz * scale
        r_trial = objective.residuals(trial)
        J += np.outer(r_trial - r - J @ dz, dz) / (dz @ dz)
        gain = 0.5 * (r @ r - r_trial @ r_trial) / predicted
        if gain > 0.0:
            x, r = trial, r_trial
            damping *= max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
            grow = 2.0
        else:
            damping *= grow
            grow *= 2.0
    dz, predicted, _ = _damped_step(_central_jacobian(objective, scale, x) * scale, r, damping)
    if predicted > 0.0:
        trial = x + dz * scale
        r_trial = objective.residuals(trial)
        if r_trial @ r_trial < r @ r:
            x = trial
    return x


def kinematic_line_search(
    objective: Searched,
    at: Callable[[float], np.ndarray],
    line: np.ndarray,
) -> tuple[np.ndarray, int]:
    """The KPM's search along the kinematic direction: the poses ``line`` (at each of
    :data:`registration.priors.KPM_LAMBDA`'s steps, (L, 4, 4) mm) scored together by the
    ``objective``'s cost, then Brent between the best one's neighbours on ``at`` (step ->
    pose). Returns the best pose and the evaluations it took."""
    costs = objective.costs(line)
    k = int(np.argmin(costs))
    lo, hi = KPM_LAMBDA[max(k - 1, 0)], KPM_LAMBDA[min(k + 1, len(KPM_LAMBDA) - 1)]
    best = minimize_scalar(
        lambda lam: objective.cost(at(lam)),
        bounds=(lo, hi),
        method="bounded",
        options={"xatol": 0.02, "maxiter": 15},
    )
    return (at(best.x) if best.fun < costs[k] else line[k]), len(costs) + best.nfev
