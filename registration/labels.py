"""The label convention of knee volumes: the phantom's, the segmentation's and the report's."""

from __future__ import annotations

LABELS: dict[str, int] = {
    "air": 0,
    "soft_tissue": 1,
    "femur": 2,
    "tibia": 3,
    "fibula": 4,
    "patella": 5,
}
"""Label value per tissue (cortical and cancellous bone share a bone's label)."""

INSERT_LABEL = 6
"""Label of a TKA polyethylene insert (the knee report fits the TP plane to its top)."""

BONE_LABELS: dict[str, tuple[int, ...]] = {
    "femur": (LABELS["femur"],),
    "tibia": (LABELS["tibia"],),
    "fibula": (LABELS["fibula"],),
    "patella": (LABELS["patella"],),
    "tibia_fibula": (LABELS["tibia"], LABELS["fibula"]),
}
"""The label values each named bone (or rigid unit of bones) is made of."""

BONE_UNITS: dict[str, tuple[int, ...]] = {
    name: BONE_LABELS[name] for name in ("femur", "tibia_fibula", "patella")
}
"""The rigid units registration tracks."""
