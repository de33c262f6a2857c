"""A 3D Slicer scene of the tracked motion: the static volume, each bone's model and its motion as
a sequence the Sequences module plays.

Files (all beside ``scene.mrml``, referenced by relative name):

- the static volume (NIfTI; its own header places it);
- ``models/<bone>.stl``: the bone in the static scan's pose, LPS mm (stated twice, as Slicer
  reads it: ``SPACE=LPS`` in the STL header and ``coordinateSystem="LPS"`` on the storage);
- ``motion/<bone>.seq.mha``: Slicer's linear transform sequence file (a MetaImage header with
  no pixels, read by ``vtkMRMLLinearTransformSequenceStorageNode``): one line per frame,
  ``Seq_Frame<k>_<Bone>ToWorldTransform = 16 numbers``, row-major, in Slicer's RAS world, the
  "to parent" matrix: ``C T_world_body C`` with ``C = diag(-1, -1, 1, 1)`` (LPS -> RAS). Its
  ``Timestamp`` (Slicer's index value) is the frame number.

In the scene every model sits under its bone's proxy transform, which one sequence browser
sets from the sequences, all bones in step: Sequences' play button shows the motion.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path
from urllib.parse import quote, unquote

import numpy as np

from registration.roles import KNOWN_ROLES

LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])
"""DICOM/ITK patient frame (LPS) to Slicer's world (RAS), and back: its own inverse."""
SLICER_VERSION = "Slicer 5.8.1 33241"
"""The scene's version: Slicer 5.10+ reads STL files of a scene without a modern version as
RAS whatever the storage says."""
STL_HEADER = b"SPACE=LPS dualarm-cbct bone surface, mm"
IDENTITY = "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1"
"""A proxy transform's matrix before the browser sets it (row-major 4x4)."""
COLORS = {"femur": "0.95 0.85 0.55", "tibia": "0.55 0.80 0.95", "patella": "0.90 0.55 0.55"}
"""Model colours (RGB 0..1) of the body playing each role (registration.roles); others grey."""


def ras_to_parent(T_world_body: np.ndarray) -> np.ndarray:
    """Slicer's "to parent" matrix (RAS) of a pose (LPS)."""
    return LPS_TO_RAS @ T_world_body @ LPS_TO_RAS


def transform_name(bone: str) -> str:
    """``femur`` -> ``FemurToWorld`` (the sequence file's transform name)."""
    return "".join(part.capitalize() for part in bone.split("_")) + "ToWorld"


def write_sequence(path: Path, bone: str, frames: np.ndarray, poses: np.ndarray) -> Path:
    """``<bone>.seq.mha``: the bone's pose in every frame (``poses`` (F, 4, 4), LPS)."""
    name = transform_name(bone)
    lines = [
        "ObjectType = Image",
        "NDims = 3",
        "AnatomicalOrientation = RAI",
        "BinaryData = True",
        "CompressedData = False",
        f"DimSize = 0 0 {len(frames)}",
        "ElementSpacing = 1 1 1",
        "Offset = 0 0 0",
        "TransformMatrix = 1 0 0 0 1 0 0 0 1",
        "ElementType = MET_UCHAR",
        "Kinds = domain domain list",
    ]
    for k, (frame, T) in enumerate(zip(frames, poses, strict=True)):
        numbers = " ".join(repr(float(x)) for x in ras_to_parent(T).ravel())
        lines += [
            f"Seq_Frame{k:04d}_{name}Transform = {numbers}",
            f"Seq_Frame{k:04d}_{name}TransformStatus = OK",
            f"Seq_Frame{k:04d}_Timestamp = {int(frame)}",
        ]
    lines.append("ElementDataFile = LOCAL")
    path.write_text("\n".join(lines) + "\n", encoding="ascii")
    return path


def read_sequence(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Frame numbers and poses (F, 4, 4, LPS) of a file :func:`write_sequence` wrote."""
    frames, poses = [], []
    for line in path.read_text(encoding="ascii").splitlines():
        key, _, value = (part.strip() for part in line.partition("="))
        if key.startswith("Seq_Frame") and key.endswith("Timestamp"):
            frames.append(int(value))
        elif key.startswith("Seq_Frame") and key.endswith("Transform"):
            T = np.array([float(x) for x in value.split()]).reshape(4, 4)
            poses.append(LPS_TO_RAS @ T @ LPS_TO_RAS)
    return np.array(frames), np.array(poses)


def add_stl_header(path: Path) -> None:
    """Put ``SPACE=LPS`` into a binary STL file's 80-byte header."""
    with open(path, "r+b") as fh:
        fh.write(STL_HEADER.ljust(80, b" "))


def write_scene(
    path: Path,
    volume: str | None,
    models: dict[str, str],
    sequences: dict[str, str],
    frames: np.ndarray,
) -> Path:
    """``scene.mrml``: the volume (file name relative to the scene, or None), each bone's
    model under its proxy transform, and one browser playing every bone's sequence."""
    root = ET.Element("MRML", version=SLICER_VERSION, userTags="")
    if volume is not None:
        _node(root, "VolumeArchetypeStorage", "vtkMRMLVolumeArchetypeStorageNode1", fileName=volume)
        _node(
            root,
            "VolumeDisplay",
            "vtkMRMLScalarVolumeDisplayNode1",
            colorNodeID="vtkMRMLColorTableNodeGrey",
            autoWindowLevel="1",
        )
        _node(
            root,
            "Volume",
            "vtkMRMLScalarVolumeNode1",
            name="static scan",
            references="display:vtkMRMLScalarVolumeDisplayNode1;"
            "storage:vtkMRMLVolumeArchetypeStorageNode1;",
        )
    browser_refs = []
    for k, bone in enumerate(models):
        n = k + 1
        name = transform_name(bone)
        sequence = f"vtkMRMLSequenceNode{n}"
        proxy = f"vtkMRMLLinearTransformNode{n}"
        _node(
            root,
            "LinearTransformSequenceStorage",
            f"vtkMRMLLinearTransformSequenceStorageNode{n}",
            fileName=sequences[bone],
        )
        _node(
            root,
            "Sequence",
            sequence,
            name=f"{name} sequence",
            indexName="frame",
            indexUnit="",
            indexType="numeric",
            references=f"storage:vtkMRMLLinearTransformSequenceStorageNode{n};",
        )
        _node(
            root,
            "LinearTransform",
            proxy,
            name=name,
            matrixTransformToParent=IDENTITY,
        )
        _node(root, "ModelStorage", f"vtkMRMLModelStorageNode{n}", fileName=models[bone])
        root[-1].set("coordinateSystem", "LPS")
        _node(
            root,
            "ModelDisplay",
            f"vtkMRMLModelDisplayNode{n}",
            color=COLORS.get(KNOWN_ROLES.get(bone), "0.8 0.8 0.8"),
            visibility="true",
        )
        _node(
            root,
            "Model",
            f"vtkMRMLModelNode{n}",
            name=bone,
            references=f"display:vtkMRMLModelDisplayNode{n};storage:vtkMRMLModelStorageNode{n};"
            f"transform:{proxy};",
        )
        browser_refs.append(f"sequenceNodeRef{k}:{sequence};dataNodeRef{k}:{proxy};")
    _node(
        root,
        "SequenceBrowser",
        "vtkMRMLSequenceBrowserNode1",
        name=f"tracked motion ({len(frames)} frames)",
        selectedItemNumber="0",
        playbackRateFps="10",
        playbackLooped="true",
        virtualNodePostfixes=" ".join(str(k) for k in range(len(models))),
        references="".join(browser_refs),
    )
    ET.indent(root, space=" ")
    ET.ElementTree(root).write(path, encoding="UTF-8", xml_declaration=True)
    return path


def referenced_files(path: Path) -> list[Path]:
    """Every file a scene written here names, resolved against its folder."""
    root = ET.parse(path).getroot()
    names = [node.get("fileName") for node in root if node.get("fileName") is not None]
    return [path.parent / unquote(name) for name in names]


def _node(root: ET.Element, tag: str, node_id: str, **attributes: str) -> ET.Element:
    attributes.setdefault("name", tag)
    if "fileName" in attributes:
        attributes["fileName"] = quote(attributes["fileName"], safe="/")
    return ET.SubElement(root, tag, id=node_id, **attributes)
