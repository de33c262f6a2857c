"""``assessment``'s public names for type checkers and IDEs (they load lazily: __init__.py)."""

from assessment.kinematics import knee_kinematics as knee_kinematics
from assessment.knee import KneeAssessment as KneeAssessment
from assessment.knee import assess_knee as assess_knee
from assessment.report import write_metrics_csv as write_metrics_csv
from assessment.report import write_report as write_report
from assessment.results import KneeKinematics as KneeKinematics
