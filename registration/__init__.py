"""2D-3D registration of bones and implant components to fluoroscopy frames; poses and their
files.

The public names below load their module on first use: ``registration.register_files`` runs
what ``cbct register`` runs; ``registration.Tracker`` tracks models through frames in memory.
"""

from recon._exports import lazy

_EXPORTS = {
    "Settings": "registration.boneaxis",
    "Tracker": "registration.boneaxis",
    "BoneResult": "registration.boneaxis",
    "FrameResult": "registration.boneaxis",
    "ImplantSpec": "registration.track",
    "register_files": "registration.track",
    "BoneModel": "registration.drr",
    "bone_models": "registration.drr",
    "ImplantModel": "registration.implants",
    "MATERIALS": "registration.implants",
    "implant_model": "registration.implants",
    "read_mesh": "registration.implants",
    "BonePose": "registration.poses",
    "read_poses": "registration.poses",
    "write_poses": "registration.poses",
    "segment_bones": "registration.segment",
    "bone_surfaces": "registration.segment",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy(__name__, _EXPORTS)
