"""Clinical knee assessment from per-frame bone poses: joint angles, tibial-plateau-condyle
distances, medial-lateral differences, trajectories, plots and a report.

The public names below load their module on first use.
"""

from recon._exports import lazy

_EXPORTS = {
    "KneeAssessment": "assessment.knee",
    "assess_knee": "assessment.knee",
    "knee_kinematics": "assessment.kinematics",
    "write_report": "assessment.report",
    "write_metrics_csv": "assessment.report",
    "KneeKinematics": "assessment.results",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy(__name__, _EXPORTS)
