"""Benchmark: the knee replacement's CBCT with and without metal artefact reduction (NMAR).

The grand-challenge knee replacement (sim.tka_ct: CoCr femoral component and tibial tray,
polyethylene insert and patellar button, resected bones, the leg's soft tissue) is scanned on
the demo's protocol (a two-pass reverse spiral, 110 kV) with a polychromatic beam and the
photons' noise, and reconstructed with weighted FDK on the demo's recon box. Three volumes:

- ``metal_free``: the same knee with bone in place of the metal (the reference);
- ``uncorrected``: the knee replacement, reconstructed as it is;
- ``mar``: the knee replacement through ``recon.mar.nmar``.

For each: the bones segmented (registration.segment; with metal,
``segment_bones_with_metal``: the metal at a cortex's level) and
their Dice against the truth within 20 mm of the metal (all bone together, and per bone),
and the RMSE against the truth's attenuation in the leg outside the metal. Also: the metal
segmented against the truth's (Dice), and the seconds NMAR takes.

Prints one JSON object. Usage: ``python bench/mar.py [--views 180] [--panel 256]
[--voxel-mm 0.8]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from recon.config import load_protocol  # noqa: E402
from recon.fdk import fdk_reconstruct  # noqa: E402
from recon.mar import nmar  # noqa: E402
from recon.volume import Volume  # noqa: E402
from registration.segment import segment_bones, segment_bones_with_metal  # noqa: E402
from sim.phantoms.tka import DEFAULT_DATA, TkaPhantomSpec  # noqa: E402
from sim.scan import add_noise, photons_per_pixel  # noqa: E402
from sim.tka_ct import (  # noqa: E402
    METAL_LABEL,
    tka_scene,
    tka_subject,
    tka_truth,
)
from study.stages import recon_grid  # noqa: E402


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def scan(spec: TkaPhantomSpec, protocol, geometry, seed: int) -> np.ndarray:
    """The scene's noisy line integrals through every view."""
    subject = tka_subject(tka_scene(spec), protocol.exposure.tube_kv)
    clean = np.stack([subject(view) for view in geometry]).astype(np.float32)
    photons = photons_per_pixel(protocol.exposure, protocol.detector, protocol.orbit.sdd_mm)
    return add_noise(clean, photons, np.random.default_rng(seed))[1]


def bones(volume: Volume, metal: np.ndarray | None) -> np.ndarray | str:
    """The segmentation's labels (next to ``metal`` when given), or why it failed."""
    try:
        if metal is None:
            return segment_bones(volume, side="right").data
        return segment_bones_with_metal(volume, metal, METAL_LABEL, side="right").data
    except ValueError as err:
        return str(err)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=180)
    parser.add_argument("--panel", type=int, default=256, help="pixels per side")
    parser.add_argument("--voxel-mm", type=float, default=0.8)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if not DEFAULT_DATA.is_dir():
        print(json.dumps({"skipped": f"no data at {DEFAULT_DATA}"}))
        return
    base = load_protocol(ROOT / "configs" / "protocols" / "demo_knee.yaml")
    panel = base.detector.model_copy(
        update={
            "rows": args.panel,
            "cols": args.panel,
            "pixel_pitch_mm": base.detector.width_mm / args.panel,
        }
    )
    protocol = base.model_copy(
        update={"detector": panel, "orbit": base.orbit.model_copy(update={"views": args.views})}
    )
    geometry = protocol.orbit.geometry(protocol.detector)
    grid = recon_grid(protocol, args.voxel_mm)
    kv = protocol.exposure.tube_kv
    scene = tka_scene(TkaPhantomSpec())
    truth = tka_truth(scene, grid, kv)
    log(f"scanning {args.views} views of {args.panel}^2, metal and metal-free")
    started = time.perf_counter()
    metal = scan(TkaPhantomSpec(), protocol, geometry, args.seed)
    free = scan(TkaPhantomSpec(metal=False), protocol, geometry, args.seed)
    scan_s = time.perf_counter() - started
    started = time.perf_counter()
    result = nmar(metal, geometry, grid, say=log)
    mar_s = time.perf_counter() - started
    reference = fdk_reconstruct(free, geometry, grid).volume
    true_metal = truth.labels == METAL_LABEL
    volumes = {
        "metal_free": reference,
        "uncorrected": result.uncorrected,
        "mar": result.volume,
    }
    metal_given = {"metal_free": None, "uncorrected": result.metal, "mar": result.metal}
    entries = {}
    for name, volume in volumes.items():
        log(f"{name}: segmenting the bones")
        labels = bones(volume, metal_given[name])
        entry = {"rmse_outside_metal_per_mm": truth.rmse_outside_metal(volume.data)}
        if isinstance(labels, str):
            entry["segmentation_failed"] = labels
        else:
            entry["dice_near_metal"] = truth.near_metal_scores(labels)
        entries[name] = entry
    free_rmse = entries["metal_free"]["rmse_outside_metal_per_mm"]
    for name in ("uncorrected", "mar"):
        entries[name]["rmse_vs_metal_free"] = entries[name]["rmse_outside_metal_per_mm"] / free_rmse
    metal_dice = (
        2 * float((result.metal & true_metal).sum()) / float(result.metal.sum() + true_metal.sum())
    )
    print(
        json.dumps(
            {
                "views": args.views,
                "panel": args.panel,
                "voxel_mm": args.voxel_mm,
                "tube_kv": kv,
                "metal_cm3": result.metal_mm3 / 1000.0,
                "metal_dice": metal_dice,
                "trace_share_mean": float(result.trace_share.mean()),
                "scan_s": scan_s,
                "nmar_s": mar_s,
                **entries,
            }
        )
    )


if __name__ == "__main__":
    main()
