"""Levenberg-Marquardt with Broyden's update (registration.search) on residuals whose optimum
is known: the update must reach it in the renders it is allotted, and MINPACK's path must
stay what the implant settings take; searches run at once share numba's threads."""

from __future__ import annotations

import threading

import numba
import numpy as np
import pytest

from registration.search import at_once, levenberg_marquardt
from registration.settings import Settings

TRUTH = np.array([0.4, -0.3, 0.2, 0.5, -0.6, 0.25])  # mm, deg: a KPM prediction's error


class Curved:
    """Residuals of a smooth non-linear fit (a 40 x 6 linear map with a quadratic bend and a
    floor that is not zero), counting evaluations as the tracker's objectives do."""

    def __init__(self, seed: int) -> None:
        rng = np.random.default_rng(seed)
        self.A = rng.normal(size=(40, 6)) * np.array([1.0, 1.0, 0.05, 1.0, 1.0, 0.3])
        self.B = rng.normal(size=(40, 6)) * 0.05
        self.floor = rng.normal(size=40) * 1e-3
        self.evaluations = 0

    def residuals(self, x: np.ndarray) -> np.ndarray:
        self.evaluations += 1
        d = np.asarray(x) - TRUTH
        return self.A @ d + self.B @ d**2 + self.floor

    def residuals_many(self, xs: np.ndarray) -> np.ndarray:
        return np.array([self.residuals(x) for x in xs])

    def optimum(self) -> np.ndarray:
        """The least-squares optimum, by Gauss-Newton with the exact Jacobian."""
        x = TRUTH.copy()
        for _ in range(50):
            d = x - TRUTH
            J = self.A + 2 * self.B * d
            x = x - np.linalg.lstsq(J, self.residuals(x), rcond=None)[0]
        return x


@pytest.mark.parametrize("seed", range(6))
def test_broyden_reaches_the_optimum_in_its_render_budget(seed) -> None:
    """10 steps from the start reach the optimum of a fit whose depth-like coordinate (the
    third) the residuals constrain 20x less than the others, to 1e-4 of a step unit (0.25
    mm/deg; seeds 0-7: 1e-5 at most), in at most 1 + 12 + 10 + 13 evaluations. Without the
    update (the start's Jacobian throughout) two of the six seeds stop short, up to 6e-4 mm."""
    objective = Curved(seed)
    x = levenberg_marquardt(objective, Settings(), 10, broyden=True)
    assert objective.evaluations <= 1 + 12 + 10 + 13
    np.testing.assert_allclose(x, objective.optimum(), atol=2.5e-5)


def test_minpack_stays_for_the_implant_settings() -> None:
    """Without Broyden's update every step takes a central-difference Jacobian: 5 residual
    evaluations as MINPACK counts them cost at least 12 renders each but the last."""
    objective = Curved(0)
    x = levenberg_marquardt(objective, Settings(), 5, broyden=False)
    assert objective.evaluations >= 5 + 12 * 4
    np.testing.assert_allclose(x, objective.optimum(), atol=2.5e-3)


def test_searches_at_once_share_the_threads_and_return_in_order() -> None:
    """Searches run at once each get their share of numba's threads (at least one) in a
    thread of their own, return in the order given, leave the caller's threads as they were,
    and a search's error reaches the caller."""
    caller = numba.get_num_threads()

    def search(k: int):
        return lambda: (k, numba.get_num_threads(), threading.get_ident())

    results = at_once([search(k) for k in range(3)])
    assert [k for k, _, _ in results] == [0, 1, 2]
    workers = min(3, numba.config.NUMBA_NUM_THREADS)
    assert {n for _, n, _ in results} == {max(1, caller // workers)}
    assert len({ident for _, _, ident in results}) == workers
    assert (workers > 1) == (threading.get_ident() not in {i for _, _, i in results})
    assert numba.get_num_threads() == caller

    def failing() -> None:
        raise ValueError("femur leaves the field of view")

    with pytest.raises(ValueError, match="femur leaves"):
        at_once([search(0), failing])
