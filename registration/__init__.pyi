"""``registration``'s public names for type checkers and IDEs (they load lazily: __init__.py)."""

from registration.drr import BoneModel as BoneModel
from registration.drr import bone_models as bone_models
from registration.frames import Frames as Frames
from registration.frames import read_frames as read_frames
from registration.implants import ImplantModel as ImplantModel
from registration.implants import implant_body as implant_body
from registration.implants import implant_model as implant_model
from registration.jointtrack import read_jointtrack_poses as read_jointtrack_poses
from registration.meshes import MATERIALS as MATERIALS
from registration.meshes import read_mesh as read_mesh
from registration.objective import BodyModel as BodyModel
from registration.poses import BodyPose as BodyPose
from registration.poses import read_poses as read_poses
from registration.poses import write_poses as write_poses
from registration.results import BodyResult as BodyResult
from registration.results import FrameResult as FrameResult
from registration.roles import roles_of as roles_of
from registration.segment import bone_surfaces as bone_surfaces
from registration.segment import segment_bones as segment_bones
from registration.settings import Settings as Settings
from registration.tracker import Tracker as Tracker
from registration.tracking import read_view as read_view
from registration.tracking import track as track
