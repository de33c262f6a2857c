"""Typed planning errors: each names the view (or motion phase), the joint or link pair, the
value and the limit, and is raised before anything is written."""

from __future__ import annotations


class PlanningError(ValueError):
    """A protocol that cannot be planned on this scanner."""


class UnreachableError(PlanningError):
    """An arm cannot place its tool at a view's pose."""


class JointLimitError(PlanningError):
    """A view needs a joint beyond its position limit."""


class ContinuityError(PlanningError):
    """Consecutive views need a jump in an arm joint (an IK branch change)."""


class CollisionError(PlanningError):
    """A planned configuration or motion comes closer to an obstacle than the margin."""


class TimingError(PlanningError):
    """No timing satisfies the joint velocity and acceleration limits."""
