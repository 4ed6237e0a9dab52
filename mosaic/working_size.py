"""The video's working size: the one scale its frames are registered at (and composed at, with
`[compose] resolution = "working"`), and the maps between the frames' decoded pixels and those.

The tracker works at the working size; the records, the report and the viewer in the pixels of
the frames as decoded; the canvas in those of `[compose] resolution` (`composed_px`).
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from mosaic.config import Config
from mosaic.features import Features, to_frame_pixels
from mosaic.lens_rim import Circle
from mosaic.preprocess import resize_by, retina_disc, working_scale

log = logging.getLogger(__name__)


class WorkingSize:
    """One video's working size, set by its first readable frame."""

    def __init__(self, config: Config):
        self._pre = config.preprocess
        self._compose_there = config.compose.resolution == "working"
        self.S: np.ndarray | None = None  # H_frame_to_work of the video's frames (one size)
        # diameter (px) of the whole retina the video's first readable frame shows (None: it
        # shows none, or [preprocess] fov_diameter_px = 0): it sets every frame's working size
        self.retina_diameter_px: float | None = None
        self._retina_decided = False

    def resize(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The frame at the video's working size and H_frame_to_work (None: unchanged): its
        longer side at most `[preprocess] max_side_px`, and, when the video's first readable
        frame shows a whole retina (`preprocess.retina_disc`: fundus video), that retina's
        diameter at most `fov_diameter_px` (the detector's scale, as `mosaic register`), the
        same factor for every frame. Slit-lamp, AO and magnified fundus video show no whole
        retina: max_side_px alone, as before. Never upscales; max_side_px = 0 turns both off."""
        pre = self._pre
        if not self._retina_decided:
            self._retina_decided = True
            rule_on = pre.fov_diameter_px > 0 and pre.max_side_px > 0
            disc = retina_disc(image) if rule_on else None
            self.retina_diameter_px = None if disc is None else 2.0 * disc[2]
        scale = working_scale(image, pre.max_side_px)
        if self.retina_diameter_px is not None:
            scale = min(scale, pre.fov_diameter_px / self.retina_diameter_px)
        return resize_by(image, scale)

    def settle(
        self, S: np.ndarray | None, frame_shape: tuple[int, ...], work_shape: tuple[int, ...]
    ) -> None:
        """The H_frame_to_work a registered frame was extracted at (said once, when scaled)."""
        if self.S is None and S is not None:
            rule = f"max_side_px = {self._pre.max_side_px}"
            if self.retina_diameter_px is not None:
                rule += (
                    f", fov_diameter_px = {self._pre.fov_diameter_px} with the "
                    f"retina {self.retina_diameter_px:.0f} px across"
                )
            log.info(
                "frames of %dx%d are registered at %dx%d ([preprocess] %s)",
                frame_shape[1], frame_shape[0], work_shape[1], work_shape[0], rule,
            )  # fmt: skip
        self.S = S

    @property
    def composed_px(self) -> np.ndarray | None:
        """H_frame_to_mosaic_px: decoded pixels into those the mosaic is composed in (None:
        the same), the working size's with `[compose] resolution = "working"`."""
        return self.S if self._compose_there else None

    def in_mosaic_px(
        self, image: np.ndarray, work: np.ndarray | None, H_frame_to_ref: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """A decoded frame (and the same at the working size, if at hand) and its pose, in the
        pixels the mosaic is composed in (`composed_px`)."""
        C = self.composed_px
        if C is None:
            return image, H_frame_to_ref
        if work is None:
            work, _ = self.resize(image)
        return work, conjugated(H_frame_to_ref, C)

    def to_frame(self, H_work_to_ref_work: np.ndarray) -> np.ndarray:
        """H_frame_to_ref (decoded pixels) of a homography between working-size frames."""
        if self.S is None:
            return H_work_to_ref_work
        H = np.linalg.inv(self.S) @ H_work_to_ref_work @ self.S
        return H / H[2, 2]

    def in_frame(self, features: Features) -> Features:
        """Features with their points in the pixels of the decoded frame."""
        if self.S is None:
            return features
        factor = np.array([1.0 / self.S[0, 0], 1.0 / self.S[1, 1]], np.float32)
        return dataclasses.replace(features, xy=to_frame_pixels(features.xy, factor))


def conjugated(H_frame_to_ref: np.ndarray, C: np.ndarray) -> np.ndarray:
    """The same transform between frames resized by `C` (a scale matrix)."""
    H = C @ H_frame_to_ref @ np.linalg.inv(C)
    return H / H[2, 2]


def circle_in_frame(circle: Circle, H_frame_to_work: np.ndarray | None) -> Circle:
    """A circle (cx, cy, r) at the working size in the pixels of the frame as decoded."""
    if H_frame_to_work is None:
        return circle
    s, tx, ty = H_frame_to_work[0, 0], H_frame_to_work[0, 2], H_frame_to_work[1, 2]
    return (circle[0] - tx) / s, (circle[1] - ty) / s, circle[2] / s
