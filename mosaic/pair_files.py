"""`mosaic register` on image files: one pair's answer (the images read and registered by
`pairs.register_pair`, the warp check and the matches picture written), and the answers of a
pairs CSV, one per row, a row that fails being its own answer while the rest go on.

An answer is the JSON object `register --json` prints (`pair_answer`).
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from mosaic.config import Config
from mosaic.errors import MosaicError
from mosaic.features import FeatureExtractor
from mosaic.io import read_csv_rows, read_image, write_image
from mosaic.pairs import register_pair
from mosaic.pixel_refine import warp_check
from mosaic.runner import one_line

log = logging.getLogger(__name__)


def pair_answer(
    fixed: Path,
    moving: Path,
    config: Config,
    extractor: FeatureExtractor,
    model: str,
    warp: Path | None = None,
    matches: Path | None = None,
) -> dict[str, Any]:
    """MOVING registered onto FIXED (`model`: auto or a motion model), as a JSON object;
    `warp`: the warp check written there, `matches`: the keypoints and inlier matches drawn."""
    images = read_image(fixed), read_image(moving)
    registration = register_pair(*images, config, extractor, model)
    H, Q = registration.H_moving_to_fixed, registration.Q_moving_to_fixed
    if warp is not None and H is not None:
        write_image(warp, warp_check(*images, H, Q))
    scales = registration.working_scales
    inverted = next(
        (n for n, i in zip(("moving", "fixed"), registration.inverted, strict=True) if i), None
    )
    answer = {
        **pair_names(fixed, moving),
        "status": "registered" if registration.ok else "failed",
        "reason": registration.reason,
        "H_moving_to_fixed": None if H is None else np.asarray(H).tolist(),
        "Q_moving_to_fixed": None if Q is None else np.asarray(Q).tolist(),
        "model": registration.model if registration.ok else None,
        "working_scale": None if scales is None else {"moving": scales[0], "fixed": scales[1]},
        "refined_levels": registration.refined_levels,
        "inverted": inverted,
        "n_matches": registration.n_matches,
        "n_inliers": registration.n_inliers,
        "residual_px": (
            round(float(registration.reproj_error_px), 3)
            if registration.ok and np.isfinite(registration.reproj_error_px)
            else None
        ),
    }
    if matches is not None:
        _write_matches_picture(matches, fixed, moving, answer, config, extractor)
    return answer


def _write_matches_picture(
    path: Path,
    fixed: Path,
    moving: Path,
    answer: dict[str, Any],
    config: Config,
    extractor: FeatureExtractor,
) -> None:
    """Both images side by side, keypoints and inlier matches drawn (`viz.pair_matches_picture`)."""
    from mosaic.viz import pair_matches_picture

    H, Q = answer["H_moving_to_fixed"], answer["Q_moving_to_fixed"]
    picture = pair_matches_picture(
        read_image(fixed),
        read_image(moving),
        config,
        extractor,
        None if H is None else np.array(H),
        None if Q is None else np.array(Q),
        (answer["inverted"] == "fixed", answer["inverted"] == "moving"),
    )
    write_image(path, picture)


def pair_names(fixed: Path, moving: Path) -> dict[str, str]:
    """The answer's first keys: the two images' paths."""
    return {"fixed": str(fixed), "moving": str(moving)}


def read_pairs(path: Path) -> list[tuple[Path, Path] | str]:
    """The pairs of a CSV (paths relative to it); a row without both paths is its error."""
    rows = read_csv_rows(path, "pairs file", ("fixed", "moving"))
    base = path.parent
    return [
        (base / r["fixed"].strip(), base / r["moving"].strip())
        if (r.get("fixed") or "").strip() and (r.get("moving") or "").strip()
        else f"row {i + 2}: fixed and moving must both be given"
        for i, r in enumerate(rows)
    ]


def pairs_file_answers(
    path: Path, config: Config, extractor: FeatureExtractor, model: str
) -> Iterator[dict[str, Any]]:
    """The answer of each row of the pairs CSV `path`, in order, with a progress bar on stderr;
    a malformed row, a missing image or a bug is that row's failed answer."""
    for pair in tqdm(read_pairs(path), unit="pair", desc="register", file=sys.stderr):
        if isinstance(pair, str):  # a malformed row: one failed line, go on
            yield {"status": "failed", "reason": pair}
            continue
        try:
            answer = pair_answer(*pair, config, extractor, model)
        except MosaicError as exc:  # a missing or unreadable image
            answer = {**pair_names(*pair), "status": "failed", "reason": str(exc)}
        except Exception as exc:  # one pair's failure is its line; the rest go on
            log.info("pair %s, %s failed", *pair, exc_info=True)
            reason = f"internal error: {one_line(exc)}"
            answer = {**pair_names(*pair), "status": "failed", "reason": reason}
        yield answer
