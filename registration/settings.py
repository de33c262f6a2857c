"""Registration settings, and the bodies a knee's tracker knows: what ``configs/registration.yaml``
sets and a researcher tunes."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, NonNegativeFloat, PositiveFloat, PositiveInt


class Settings(BaseModel):
    """Registration settings (mm and degrees); YAML files load with recon.config.load_config
    (``configs/registration.yaml`` holds the defaults)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    pyramid_mm: tuple[PositiveFloat, ...] = Field(
        (2.4, 1.2),
        min_length=1,
        description="pixel sizes of the resolution pyramid at the panel, coarse to fine, mm; "
        "each level bins the panel by the nearest whole factor (at least 1)",
    )
    highpass_mm: PositiveFloat = Field(3.0, description="high-pass Gaussian sigma, mm")
    frame_blur_mm: tuple[NonNegativeFloat, NonNegativeFloat] | None = Field(
        None,
        description="Gaussian sigmas (along the panel's u, v axes, mm) the frames are blurred "
        "by to match the DRRs' resolution (a CBCT is blurrier than a fluoroscopy panel, and "
        "blurrier across its axis than along it); None estimates them per bone on the first "
        "frame (the pair on registration.resolution.FRAME_BLUR_MM that maximises the bone's NCC)",
    )
    mask_dilation_mm: PositiveFloat = Field(4.0, description="2D mask dilation, mm")
    truncation_band_mm: NonNegativeFloat = Field(
        12.0,
        description="the mask leaves out pixels this close (panel mm) to where the static "
        "scan's box cuts the leg, projected at the current poses: the DRR ends there, the "
        "frame goes on (the edge and its high-pass reach, 3 sigma, plus a few mm of motion); "
        "0 keeps them",
    )
    de_translation_mm: PositiveFloat = Field(12.0, description="DE box half-width, mm")
    de_long_axis_deg: PositiveFloat = Field(15.0, description="DE box about the long axis, deg")
    de_other_axes_deg: PositiveFloat = Field(8.0, description="DE box about the others, deg")
    de_popsize: PositiveInt = 10
    de_maxiter: PositiveInt = 30
    powell_maxfev: PositiveInt = 400
    powell_xtol: PositiveFloat = Field(
        0.05,
        description="Powell's tolerance on the coarsest level, mm and deg (Nelder-Mead on the "
        "finer levels refines further)",
    )
    nelder_mead_maxfev: PositiveInt = 120
    refinement: Literal["least_squares", "powell_nelder_mead"] = Field(
        "least_squares",
        description="with the KPM, how a bone is refined once the KPM has placed it (every "
        "frame after the first): Levenberg-Marquardt on the residual whose half squared norm "
        "is 1 - NCC (Jacobian by central differences of ls_step), the coarse levels in a "
        "first pass over the bones and the finest in a second, whatever passes says; or "
        "powell_nelder_mead, the derivative-free passes of the first frame (where the DE's "
        "pose may be a few mm off, which Powell's box search recovers) and of the tracker "
        "without the KPM",
    )
    ls_step: tuple[PositiveFloat, PositiveFloat] = Field(
        (0.25, 0.25), description="least squares: central-difference steps, (mm, deg)"
    )
    ls_broyden: tuple[bool, bool] = Field(
        (True, False),
        description="least squares on the coarse levels and on the finest: the Jacobian by "
        "central differences at the start of the level only, then kept current by Broyden's "
        "rank-one update after each step (one render a step), and a last central-difference "
        "Jacobian and step at the end; false: by central differences at every step (scipy's "
        "MINPACK). Bones: the coarse level's start for the finest in a fifth less time a warm "
        "frame; the finest with it lost accuracy on fast motion",
    )
    ls_max_steps: tuple[PositiveInt, PositiveInt] = Field(
        (10, 5),
        description="least squares on the coarse levels and on the finest: trial steps with "
        "ls_broyden (one render each, after a Jacobian of 12 renders and before the last "
        "one's 13), otherwise residual evaluations as MINPACK counts them (each step also "
        "takes a Jacobian: 12 renders)",
    )
    ls_max_steps_views: tuple[PositiveInt, PositiveInt] = Field(
        (2, 2),
        description="the same on two or more views at once (registration.views): each "
        "render is every view's, and the depth that one view leaves loose the others fix, so "
        "fewer steps converge",
    )
    passes: PositiveInt = Field(
        2,
        description="passes over the bones per frame; later passes refine each against the "
        "others' newest estimates (first frame: Powell in a box of 0.4 x refine_range, then "
        "Nelder-Mead; warm frames: Nelder-Mead on the finest level); a first frame that "
        "estimates the frames' blur takes at least two",
    )
    kpm: bool = True
    global_init: bool = True
    powell: bool = True
    fail_ncc: float = Field(0.5, ge=-1.0, le=1.0, description="flag a bone below this NCC")
    drop_ncc: float = Field(
        0.02,
        ge=0.0,
        description="a warm frame whose NCC falls this far below the bone's previous frame "
        "widens the search (DE in half the first frame's box) and keeps the better pose",
    )
    refine_range: tuple[PositiveFloat, PositiveFloat] = Field(
        (5.0, 5.0), description="Powell's box about the start, (mm, deg)"
    )
    patellofemoral_sigma: tuple[PositiveFloat, PositiveFloat] | None = Field(
        (3.0, 5.0),
        description="patellofemoral prior: (mm, deg) of the patella's medial-lateral shift and "
        "out-of-plane tilt relative to the femur since the static scan; None turns it off",
    )
    depth_step_sigma_mm: dict[str, PositiveFloat] = Field(
        default_factory=dict,
        description="depth prior, by body: sigma of its move along the view's axis (its depth) "
        "from the frame before, mm; a body not named has none (a lateral view's knee moves "
        "across the beam, and its depth is the least seen of its six degrees of freedom)",
    )
    prior_weight: float = Field(
        0.005, ge=0.0, description="prior cost in NCC units per sigma squared"
    )
    kpm_depth: Literal["extrapolate", "hold"] = Field(
        "hold",
        description="what the KPM's prediction does with a bone's depth (its centroid's move "
        "along the view's ray): extrapolate it with the rest of the last motion, or hold it at "
        "the last frame's (one plane measures depth least well: an error in it, extrapolated, "
        "grows from frame to frame)",
    )
    seed: int = 0
