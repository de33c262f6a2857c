"""What the tracker finds: one body in one frame, and one frame's bodies (frozen)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class BodyResult:
    """One tracked body (a bone or an implant component) in one frame.

    Attributes:
        T_world_body: the body's pose, 4x4 (mm): from where the static scan (or its mesh's
            frame) has it to where it is in the frame.
        ncc: normalised cross-correlation of the frame and the render over the body's mask,
            in [-1, 1] (NaN when it was not scored).
        gradient_ncc: the same of their gradients, in [-1, 1] (NaN when not scored).
        seconds: time spent registering it, s.
        evaluations: renders of the body the search took.
        failed: the tracker marks the pose failed (nothing is measured from it).
        reason: why it failed (empty when it did not).
    """

    T_world_body: np.ndarray
    ncc: float
    gradient_ncc: float
    seconds: float
    evaluations: int
    failed: bool
    reason: str = ""

    def scored(self, ncc: float, gradient_ncc: float, fail_ncc: float) -> BodyResult:
        """This result with its similarity, and its failure flag set against ``fail_ncc``.

        Args:
            ncc: Normalised cross-correlation of the frame and the render, in [-1, 1].
            gradient_ncc: The same of their gradients, in [-1, 1].
            fail_ncc: The NCC below which the body counts as failed.
        """
        failed = ncc < fail_ncc
        reason = f"NCC {ncc:.3f} below {fail_ncc}" if failed else ""
        return replace(self, ncc=ncc, gradient_ncc=gradient_ncc, failed=failed, reason=reason)

    def spent(self, seconds: float, evaluations: int) -> BodyResult:
        """This result with more time and renders spent on it.

        Args:
            seconds: The time to add, s.
            evaluations: The renders to add.
        """
        return replace(
            self, seconds=self.seconds + seconds, evaluations=self.evaluations + evaluations
        )


@dataclass(frozen=True)
class FrameResult:
    """Every tracked body in one frame.

    Attributes:
        frame: the frame's index in the sequence (0-based).
        bodies: each body's result, by name, in the order they were registered.
    """

    frame: int
    bodies: Mapping[str, BodyResult]
