"""2D-3D registration of bones and implant components to fluoroscopy frames; poses and their
files.

The public names below load their module on first use (``__init__.pyi`` lists them for type
checkers): ``registration.track`` tracks bodies through frames in memory
(``registration.read_frames``, ``registration.read_view``, ``registration.implant_body``,
``registration.bone_models``); what ``cbct register`` runs from files is
``study.jobs.register_files``.
"""

from recon._exports import lazy

_EXPORTS = {
    "Settings": "registration.settings",
    "Tracker": "registration.tracker",
    "BodyResult": "registration.results",
    "FrameResult": "registration.results",
    "track": "registration.tracking",
    "read_view": "registration.tracking",
    "Frames": "registration.frames",
    "read_frames": "registration.frames",
    "read_jointtrack_poses": "registration.jointtrack",
    "BoneModel": "registration.drr",
    "BodyModel": "registration.objective",
    "bone_models": "registration.drr",
    "ImplantModel": "registration.implants",
    "MATERIALS": "registration.meshes",
    "implant_model": "registration.implants",
    "implant_body": "registration.implants",
    "read_mesh": "registration.meshes",
    "BodyPose": "registration.poses",
    "read_poses": "registration.poses",
    "write_poses": "registration.poses",
    "roles_of": "registration.roles",
    "segment_bones": "registration.segment",
    "bone_surfaces": "registration.segment",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy(__name__, _EXPORTS)
