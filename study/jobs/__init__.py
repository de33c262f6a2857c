"""File-level jobs of the study pipeline, one module each: calibrate (a steel-ball scan, the
fluoroscopy panel's distortion), reconstruct, segment, register (``cbct register``) and
assess files, and simulate a scan of a digital phantom.

Each job validates everything it reads before the long work starts and refuses to overwrite:
outputs go to new files or to a folder that does not exist yet (or is empty).
"""

from study.jobs.assess import assess_files, export_files, write_assessment
from study.jobs.calibrate import calibrate_to_study, fit_fluoro_distortion
from study.jobs.reconstruct import (
    PLAN_TOLERANCE_MM,
    MotionBeyondCompensation,
    check_is_plan,
    compensable_motion,
    reconstruct_files,
    write_motion,
)
from study.jobs.register import (
    CameraFiles,
    ImplantSpec,
    RegisterInputs,
    RegisterOptions,
    register_files,
)
from study.jobs.segment import segment_files
from study.jobs.simulate import simulate_to_folder

__all__ = [
    "PLAN_TOLERANCE_MM",
    "CameraFiles",
    "ImplantSpec",
    "MotionBeyondCompensation",
    "RegisterInputs",
    "RegisterOptions",
    "assess_files",
    "calibrate_to_study",
    "check_is_plan",
    "compensable_motion",
    "export_files",
    "fit_fluoro_distortion",
    "reconstruct_files",
    "register_files",
    "segment_files",
    "simulate_to_folder",
    "write_assessment",
    "write_motion",
]
