"""registration.overlays: the overlay images stand upright where the view says where up is."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk

from recon.geometry import View
from registration.overlays import write_overlays
from registration.results import FrameResult


@pytest.mark.parametrize(("e_v", "flipped"), [((0, 0, 1), True), ((0, 0, -1), False)])
def test_an_overlay_puts_the_worlds_up_at_its_top(tmp_path, e_v, flipped):
    """A lateral view whose rows go up (+z, the scanner's up) is flipped for the reader; one
    whose rows go down keeps the frame's row order."""
    view = View(
        np.array([-800.0, 0.0, 0.0]), np.array([400.0, -10.0, 10.0 * -e_v[2]]),
        np.array([0.0, 1.0, 0.0]), np.array(e_v, float), 1.0, 1.0, 20, 20,
    )  # fmt: skip
    frame = np.tile(np.linspace(0.0, 1.0, 20)[:, None], (1, 20))  # row 0 clear, row 19 dark
    (path,) = write_overlays(tmp_path / "o", frame[None], view, {}, [FrameResult(7, {})])
    image = sitk.GetArrayFromImage(sitk.ReadImage(str(path)))
    assert path.name == "frame_0007.png"
    top_darker = image[0].mean() < image[-1].mean()
    assert top_darker == flipped
