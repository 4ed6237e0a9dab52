"""Registration of one image pair (`mosaic register`, `mosaic compare`): each image at its
working size, matched, the motion estimated, then refined up to the full resolution.
`match_pair` is the first half (working sizes, features, matches), which
`viz.pair_matches_picture` draws.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np

from mosaic.config import Config
from mosaic.features import FeatureExtractor, Features
from mosaic.matching import Matches, match_descriptors
from mosaic.pixel_refine import fit_pair
from mosaic.preprocess import (
    Disc,
    inverted_as,
    pair_polarities,
    pair_working_scales,
    prepare,
    resize_by,
    retina_disc,
)
from mosaic.registration import Registration, estimate_motion

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PairMatches:
    """Two images' features at their working sizes and the matches between them."""

    fixed: Features
    moving: Features
    matches: Matches  # idx_a: into `fixed`, idx_b: into `moving`
    S_fixed: np.ndarray | None  # H_image_to_work of each (None: the working size is the image's)
    S_moving: np.ndarray | None
    moving_work_shape: tuple[int, int]  # (h, w) of the moving image at its working size


def match_pair(
    fixed: np.ndarray,
    moving: np.ndarray,
    config: Config,
    extractor: FeatureExtractor,
    discs: tuple[Disc | None, Disc | None] | None = None,
) -> PairMatches:
    """Each image at its working size (`pair_working_scales`; `discs`: their `retina_disc`s,
    when the caller has them), described by `extractor`, and the descriptors matched."""
    pre = config.preprocess
    scale_fixed, scale_moving = pair_working_scales(
        fixed, moving, pre.max_side_px, pre.fov_diameter_px, discs
    )
    fixed_work, S_fixed = resize_by(fixed, scale_fixed)
    moving_work, S_moving = resize_by(moving, scale_moving)
    features_fixed = extractor(prepare(fixed_work, pre))
    features_moving = extractor(prepare(moving_work, pre))
    matches = match_descriptors(
        features_fixed.descriptors, features_moving.descriptors, config.matching
    )
    return PairMatches(
        features_fixed, features_moving, matches, S_fixed, S_moving, moving_work.shape[:2]
    )


def register_pair(
    fixed: np.ndarray,
    moving: np.ndarray,
    config: Config,
    extractor: FeatureExtractor,
    model: str | None = None,
) -> Registration:
    """Register one image pair: the result's `H_moving_to_fixed` maps `moving` into `fixed` (full
    size pixels); `model` (default `[registration] model`) as in `estimate_motion`, or
    "quadratic" (`Q_moving_to_fixed`, 2x6; "auto" also chooses it where it beats the homography).

    Each image is registered at its working size (its retina's diameter at `[preprocess]
    fov_diameter_px` when it shows a whole one, else `max_side_px`; `working_scales`), then
    refined through `[registration] refine_levels` levels up to the full resolution
    (`pixel_refine.refine_pair`); a refinement that loses the matches keeps the coarse answer. A
    pair of opposite vessel polarities (an angiogram and a colour photograph, `[preprocess]
    vessel_polarity`) is also registered with the bright-vessel one inverted, and the
    registration with more inliers answers (`Registration.inverted` says which). With
    "auto", photographs of a whole retina are always refined (homography or quadratic, which
    the working size cannot tell apart); other views keep a simpler coarse model."""
    model = model or config.registration.model
    invert = pair_polarities(fixed, moving) if config.preprocess.vessel_polarity else (False,) * 2
    as_is = _register_pair(fixed, moving, config, extractor, model)
    if not any(invert):
        return as_is
    log.info(
        "vessels of opposite polarity: registered again, the %s image inverted",
        "fixed" if invert[0] else "moving",
    )
    inverted = dataclasses.replace(
        _register_pair(*inverted_as(fixed, moving, invert), config, extractor, model),
        inverted=invert[::-1],
    )
    registered = [reg for reg in (inverted, as_is) if reg.ok]
    return max(registered, key=lambda reg: reg.n_inliers) if registered else inverted


def _register_pair(
    fixed: np.ndarray,
    moving: np.ndarray,
    config: Config,
    extractor: FeatureExtractor,
    model: str,
) -> Registration:
    """`register_pair` of the two images as they are."""
    discs = retina_disc(fixed), retina_disc(moving)  # working sizes, model, overlap
    paired = match_pair(fixed, moving, config, extractor, discs)
    features_fixed, features_moving, matches = paired.fixed, paired.moving, paired.matches
    xy_moving = features_moving.xy[matches.idx_b]
    reg = estimate_motion(
        xy_moving,
        features_fixed.xy[matches.idx_a],
        config.registration,
        paired.moving_work_shape,
        model,
    )
    S_fixed, S_moving = (np.eye(3) if S is None else S for S in (paired.S_fixed, paired.S_moving))
    scales = (float(S_moving[0, 0]), float(S_fixed[0, 0]))
    reg = dataclasses.replace(reg, working_scales=scales)
    blank = [name for name, f in (("fixed", features_fixed), ("moving", features_moving)) if not f]
    if blank:  # say why: a blank, black or out-of-focus image has nothing to match
        images = " and ".join(blank) + (" images" if len(blank) > 1 else " image")
        reason = f"no textured keypoints in the {images}"
        return dataclasses.replace(reg, H_moving_to_fixed=None, reason=reason)
    if reg.H_moving_to_fixed is None:
        return reg
    H = np.linalg.inv(S_fixed) @ reg.H_moving_to_fixed @ S_moving
    error_px = reg.reproj_error_px / scales[1]  # measured in the fixed working image
    reg = dataclasses.replace(reg, H_moving_to_fixed=H / H[2, 2], reproj_error_px=error_px)
    if model not in ("homography", "quadratic", "auto"):
        return reg  # a simpler model was asked for: nothing to refine it towards
    if model == "auto" and reg.model != "homography" and discs[1] is None:
        return reg  # a simpler model fits these views (magnified, nearly flat): it stands
    xy_full = (xy_moving[reg.inliers] + 0.5) / S_moving[0, 0] - 0.5
    xy_target = (features_fixed.xy[matches.idx_a][reg.inliers] + 0.5) / S_fixed[0, 0] - 0.5
    fit, levels_done = fit_pair(
        fixed,
        moving,
        xy_full,
        xy_target,
        reg.H_moving_to_fixed,
        min(scales),
        config.registration,
        model,
        discs,
    )
    return dataclasses.replace(
        reg,
        H_moving_to_fixed=fit.H,
        Q_moving_to_fixed=fit.Q if fit.model == "quadratic" else None,
        model=fit.model,
        refined_levels=levels_done,
        reproj_error_px=fit.error_px,
    )
