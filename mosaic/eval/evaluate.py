"""Detector evaluation: the paper's pair metrics, the FIRE protocol, and video registration.

Pairs (`evaluate_pair`): each detector of the registry runs through the pipeline's own stages
(`prepare` → `FeatureExtractor` → `match_descriptors` → `estimate_homography`) and is scored
with the paper's criteria (`glampoints.metrics`): repeatability (3 px), M.score, NNDR matching
AUC, coverage fraction of true positives, and the registration class (failed / inaccurate /
acceptable) from the errors of ground-truth points (six fixed points for homography datasets,
the control points for FIRE) with MEE / RMSE per class. Every pair also gets the FIRE protocol
error (mean ground-truth point error at full resolution, inf when failed), from which the AUC
over thresholds 1..25 px, its 0..25 integral variant, per-category AUCs and mAUC follow.

Videos (`evaluate_video`): `runner.run_video` (the code path of `mosaic build`) runs the video
with `on_failure = "skip"`; frames are checked against the synthetic ground truth (`*.gt.json`)
when there is one: each frame's placement against the first frame (corner error, drift) and
against the frame it was registered to (step error); the report's motion models are counted per
video, and its per-frame quality score is compared with the corner error (rank correlation, bad
frames flagged, good frames flagged). Each run's full report is kept under `reports/`. With a
readable source photograph, the mosaic itself is scored against it (`mosaic.eval.fidelity`,
issue 16: fidelity and good area), next to the oracle (the plain mean of the frames placed by
the true transforms, computed once per video).

Outputs (`write_pair_outputs`, `write_video_outputs`): CSV and JSON tables, per-pair/per-video
rows and PNG plots. Pure metric definitions live in `glampoints.metrics`, not here.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import logging
import math
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from mosaic.config import Config, RegistrationConfig, for_photographs, with_overrides
from mosaic.errors import ConfigError, DetectorWeightsError, InputError
from mosaic.eval.datasets import (
    FIRE_CATEGORIES,
    Pair,
    PairDataset,
    fire_category,
    fire_truth,
    read_matrix,
)
from mosaic.eval.fidelity import (
    FidelityScores,
    SourceTruth,
    mosaic_fidelity,
    oracle_fidelity,
    prepare_source,
)
from mosaic.features import DETECTORS, FeatureExtractor
from mosaic.features import paper_metrics as gm
from mosaic.geometry import corner_error, relative_homographies
from mosaic.io import UNDECODABLE, atomic_path, make_folder, read_image, write_json, write_text
from mosaic.matching import distance_matrix, match_descriptors
from mosaic.pipeline import MosaicResult
from mosaic.pixel_refine import fit_pair
from mosaic.preprocess import field_of_view_mask, prepare, retina_disc, scale_matrix, to_gray
from mosaic.quality import spearman
from mosaic.registration import MODELS as MOTION_MODELS
from mosaic.registration import apply_homography, apply_quadratic, estimate_homography
from mosaic.report import FAILED, REGISTERED, SKIPPED
from mosaic.runner import VIDEO_SUFFIXES, Outputs, is_frame_folder, run_video
from mosaic.runner import reread_frames as _reread
from mosaic.synthetic.synth import gt_path_for, load_ground_truth

log = logging.getLogger(__name__)

EPS_PX = 3.0  # correctness radius of a keypoint / match (paper: 3 px)
FIRE_SCALE = 0.15  # the paper's FIRE protocol: 2912 px images downscaled to 15 % for detection
ACCURATE_CORNER_ERROR_PX = 10.0  # a video frame further than this from the truth is a failure
CLASSES = ("failed", "inaccurate", "acceptable")
# FIRE pairs: the final fit of `mosaic register` (`pixel_refine.fit_pair`) on the coarse
# inliers, per motion model and with or without the coarse-to-fine refinement: name -> (model,
# refined)
FIRE_VARIANTS = {
    "hom": ("homography", False),
    "hom+refine": ("homography", True),
    "quad": ("quadratic", False),
    "quad+refine": ("quadratic", True),
}


# --------------------------------------------------------------------------------------------
# Detectors
# --------------------------------------------------------------------------------------------


def parse_detectors(spec: str | None) -> list[str]:
    """Detector names from "a,b,c" (None or "all": every detector of the registry)."""
    if spec is None or spec.strip() in ("", "all"):
        return list(DETECTORS)
    names = [s.strip() for s in spec.split(",") if s.strip()]
    unknown = [n for n in names if n not in DETECTORS]
    if unknown:
        raise ConfigError(
            f"unknown detector {', '.join(unknown)} (choices: {', '.join(DETECTORS)})"
        )
    return list(dict.fromkeys(names))


def make_extractors(
    config: Config, names: Sequence[str], explicit: bool = True
) -> dict[str, tuple[Config, FeatureExtractor]]:
    """One (config, extractor) per detector; glampoints is skipped (warning) without weights.

    With `explicit` False (the default list of every detector), detectors that the configured
    descriptor does not support are skipped with a warning instead of raising.
    """
    built: dict[str, tuple[Config, FeatureExtractor]] = {}
    for name in names:
        cfg = with_overrides(config, features={"detector": name})
        try:
            built[name] = (cfg, FeatureExtractor(cfg.features))
        except DetectorWeightsError as exc:
            log.warning("skipping detector %s: %s", name, exc)
        except ConfigError as exc:
            if explicit:
                raise
            log.warning("skipping detector %s: %s", name, exc)
    if not built:
        raise ConfigError(f"none of the detectors {', '.join(names)} can run")
    return built


# --------------------------------------------------------------------------------------------
# Pairs
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PairResult:
    """Scores of one detector on one pair (one row of pairs.csv)."""

    detector: str
    pair: str
    category: str
    n_keypoints_1: int
    n_keypoints_2: int
    n_matches: int
    n_true_positives: int
    repeatability: float
    matching_score: float
    nndr_auc: float
    coverage: float
    n_inliers: int
    status: str  # failed | inaccurate | acceptable
    reason: str | None  # why it failed
    mee_px: float  # median / max / RMS error of the ground-truth points, at detection scale
    mae_px: float
    rmse_px: float
    error_px: float  # FIRE protocol: mean point error at full resolution; inf when failed
    time_ms: float  # detection + description of both images
    H_est_1_to_2: list[list[float]] | None = field(default=None, repr=False)  # full resolution
    coarse_s: float = math.nan  # pre-processing, detection, description, matching and RANSAC
    # FIRE pairs (control points): per FIRE_VARIANTS name, the FIRE error (inf when failed) and
    # the seconds of its final fit (to add to coarse_s)
    variant_error_px: dict[str, float] = field(default_factory=dict)
    variant_s: dict[str, float] = field(default_factory=dict)


def _resize(image: np.ndarray, scale: float) -> np.ndarray:
    if scale == 1.0:
        return image
    h, w = image.shape[:2]
    size = (max(round(w * scale), 8), max(round(h * scale), 8))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def fit_homography(xy_1: np.ndarray, xy_2: np.ndarray) -> np.ndarray | None:
    """Least-squares H_1_to_2 of control points (all of them, no RANSAC); None if < 4 points."""
    if len(xy_1) < gm.MIN_MATCHES:
        return None
    H, _ = cv2.findHomography(xy_1.astype(np.float64), xy_2.astype(np.float64), 0)
    return None if H is None else H / H[2, 2]


def _ground_truth_points(
    pair: Pair, S1: np.ndarray, S2: np.ndarray, shape1: tuple[int, ...]
) -> tuple[bool, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(points_in_2_to_1, src_full, dst_full, src_scaled, dst_scaled) for registration errors.

    Homography datasets: the six fixed points of image 1 and their true positions in image 2.
    FIRE: the control points of image 2 and their positions in image 1 (the error is measured
    in the reference image, as in the FIRE protocol).
    """
    if pair.control_points is not None:
        cp = pair.control_points
        src, dst = cp[:, 2:4], cp[:, 0:2]
        return True, src, dst, gm.warp_points(S2, src), gm.warp_points(S1, dst)
    assert pair.H_1_to_2 is not None
    h, w = pair.image1.shape[:2]
    src = gm.six_fixed_points(w, h)
    dst = gm.warp_points(pair.H_1_to_2, src)
    src_s = gm.six_fixed_points(shape1[1], shape1[0])
    H_s = S2 @ pair.H_1_to_2 @ np.linalg.inv(S1)
    return False, src, dst, src_s, gm.warp_points(H_s, src_s)


_FAILED_SCORES = ("failed", math.nan, math.nan, math.nan, math.inf, None)


def _registration_scores(
    pair: Pair,
    H_est_scaled: np.ndarray | None,
    S1: np.ndarray,
    S2: np.ndarray,
    shape1: tuple[int, ...],
) -> tuple[str, float, float, float, float, np.ndarray | None]:
    """(class, MEE, MAE, RMSE, FIRE error, H_est_1_to_2 at full resolution) of an estimate.

    Class, MEE, MAE and RMSE are measured at detection scale (as the paper did on FIRE, whose
    images it downscaled); the FIRE error at full resolution.
    """
    if H_est_scaled is None:
        return _FAILED_SCORES
    H_est = np.linalg.inv(S2) @ H_est_scaled @ S1
    H_est /= H_est[2, 2]
    to_1, src, dst, src_s, dst_s = _ground_truth_points(pair, S1, S2, shape1)
    est, est_s = (
        (np.linalg.inv(H_est), np.linalg.inv(H_est_scaled)) if to_1 else (H_est, H_est_scaled)
    )
    errors_s = gm.point_errors(est_s, src_s, dst_s)
    status, mee, mae = gm.classify_errors(errors_s)
    error_px = float(np.mean(gm.point_errors(est, src, dst)))
    return status, mee, mae, gm.rmse(errors_s), error_px, H_est


def evaluate_pair(
    pair: Pair, config: Config, extractor: FeatureExtractor, scale: float = 1.0
) -> PairResult:
    """Run one detector on one pair through the pipeline's stages and score it.

    Detection runs on both images resized by `scale`; the estimated homography is mapped back
    to full resolution for the FIRE error. Failure follows the paper: fewer than 4 matches, a
    reflection or a scale outside [0.1, 4] (`config.registration.min_inliers` is lowered to 4).
    """
    img1, img2 = _resize(pair.image1, scale), _resize(pair.image2, scale)
    S1 = scale_matrix(pair.image1.shape, img1.shape)
    S2 = scale_matrix(pair.image2.shape, img2.shape)
    start = time.perf_counter()
    prep1, prep2 = prepare(img1, config.preprocess), prepare(img2, config.preprocess)
    f1, f2 = extractor(prep1), extractor(prep2)
    time_ms = (time.perf_counter() - start) * 1e3
    shape1, shape2 = prep1.gray.shape, prep2.gray.shape

    matches = match_descriptors(f1.descriptors, f2.descriptors, config.matching)
    xy1_m, xy2_m = f1.xy[matches.idx_a], f2.xy[matches.idx_b]
    paper_rules = dataclasses.replace(config.registration, min_inliers=gm.MIN_MATCHES)
    reg = estimate_homography(xy1_m, xy2_m, paper_rules)
    coarse_s = time.perf_counter() - start

    H_gt_full = pair.H_1_to_2
    if H_gt_full is None and pair.control_points is not None:
        H_gt_full = fit_homography(pair.control_points[:, :2], pair.control_points[:, 2:])

    rep = ms = auc = cover = float("nan")
    n_tp = 0
    if H_gt_full is not None:
        H = S2 @ H_gt_full @ np.linalg.inv(S1)
        rep = gm.repeatability(f1.xy, f2.xy, H, shape1, shape2, EPS_PX)
        ms = gm.matching_score(f1.xy, f2.xy, xy1_m, xy2_m, H, shape1, shape2, EPS_PX)
        tp = gm.true_positive_mask(xy1_m, xy2_m, H, EPS_PX)
        n_tp = int(tp.sum())
        cover = gm.coverage_fraction(xy1_m[tp], shape1)
        in1, in2 = gm.common_region(f1.xy, f2.xy, H, shape1, shape2)
        if in1.any() and in2.any():
            nearest, ratio = gm.nearest_neighbour_ratios(
                distance_matrix(f1.descriptors[in1], f2.descriptors[in2])
            )
            correct = gm.true_positive_mask(f1.xy[in1], f2.xy[in2][nearest], H, EPS_PX)
            auc = gm.nndr_auc(ratio, correct)

    scores = _registration_scores(pair, reg.H_moving_to_fixed, S1, S2, shape1)
    status, mee, mae, rms, error_px, H_full = scores if reg.ok else _FAILED_SCORES
    variant_error_px: dict[str, float] = {}
    variant_s: dict[str, float] = {}
    if pair.control_points is not None:
        inliers = (
            (
                gm.warp_points(np.linalg.inv(S1), xy1_m[reg.inliers]).astype(np.float64),
                gm.warp_points(np.linalg.inv(S2), xy2_m[reg.inliers]).astype(np.float64),
            )
            if H_full is not None
            else None
        )
        variant_error_px, variant_s = fire_variants(
            pair, inliers, H_full, min(S1[0, 0], S2[0, 0]), paper_rules
        )
    return PairResult(
        detector=extractor.detector.name,
        pair=pair.name,
        category=pair.category,
        n_keypoints_1=len(f1),
        n_keypoints_2=len(f2),
        n_matches=len(matches),
        n_true_positives=n_tp,
        repeatability=rep,
        matching_score=ms,
        nndr_auc=auc,
        coverage=cover,
        n_inliers=reg.n_inliers,
        status=status,
        reason=reg.reason,
        mee_px=mee,
        mae_px=mae,
        rmse_px=rms,
        error_px=error_px,
        time_ms=time_ms,
        H_est_1_to_2=None if H_full is None else H_full.tolist(),
        coarse_s=coarse_s,
        variant_error_px=variant_error_px,
        variant_s=variant_s,
    )


def fire_variants(
    pair: Pair,
    inliers: tuple[np.ndarray, np.ndarray] | None,
    H_est_1_to_2: np.ndarray | None,
    start_scale: float,
    config: RegistrationConfig,
) -> tuple[dict[str, float], dict[str, float]]:
    """The FIRE error (px, inf when the coarse registration failed) and the seconds of each
    FIRE_VARIANTS fit, all from the same coarse inliers (`inliers`: image 1's and image 2's
    points, full resolution) and homography: image 2 (moving) is fitted into image 1 (fixed)
    as `mosaic register` does (`pixel_refine.fit_pair`, `config.refine_levels` levels when refined;
    none are run when it is 0), and the control points of image 2 are mapped into image 1."""
    assert pair.control_points is not None
    variants = {
        name: spec
        for name, spec in FIRE_VARIANTS.items()
        if not spec[1] or config.refine_levels > 0
    }
    if inliers is None or H_est_1_to_2 is None:
        return dict.fromkeys(variants, math.inf), dict.fromkeys(variants, 0.0)
    xy_fixed, xy_moving = inliers
    truth, points = pair.control_points[:, :2], pair.control_points[:, 2:4]
    H0 = np.linalg.inv(H_est_1_to_2)
    discs = retina_disc(pair.image1), retina_disc(pair.image2)  # once for the four fits
    errors, seconds = {}, {}
    for name, (model, refined) in variants.items():
        levels = config.refine_levels if refined else 0
        start = time.perf_counter()
        fit, _ = fit_pair(
            pair.image1,
            pair.image2,
            xy_moving,
            xy_fixed,
            H0 / H0[2, 2],
            start_scale,
            dataclasses.replace(config, refine_levels=levels),
            model,
            discs,
        )
        seconds[name] = time.perf_counter() - start
        mapped = (
            apply_quadratic(fit.Q, points)
            if fit.model == "quadratic"
            else apply_homography(fit.H, points)
        )
        error = float(np.mean(np.linalg.norm(mapped - truth, axis=1)))
        errors[name] = error if math.isfinite(error) else math.inf
    return errors, seconds


def evaluate_pairs(
    dataset: PairDataset,
    extractors: dict[str, tuple[Config, FeatureExtractor]],
    scale: float = 1.0,
    max_pairs: int = 0,
    progress: bool = False,
) -> list[PairResult]:
    """Every detector on every pair (each pair is read once); rows ordered pair by pair."""
    n = len(dataset) if max_pairs <= 0 else min(max_pairs, len(dataset))
    results = []
    pairs = (p for _, p in zip(range(n), dataset, strict=False))
    for pair in tqdm(pairs, total=n, unit="pair", desc="evaluate", disable=not progress):
        for config, extractor in extractors.values():
            results.append(evaluate_pair(pair, config, extractor, scale))
    return results


def _nanmean(values: Iterable[float]) -> float:
    arr = np.asarray(list(values), dtype=np.float64)
    arr = arr[np.isfinite(arr)]
    return float(arr.mean()) if arr.size else math.nan


def _category_key(category: str) -> tuple[int, str]:
    """FIRE's order S, P, A first, then any other category alphabetically."""
    order = {c: i for i, c in enumerate(FIRE_CATEGORIES)}
    return order.get(category, len(order)), category


def summarize_pairs(results: Sequence[PairResult]) -> list[dict[str, Any]]:
    """One row per detector (in order of appearance): the paper's tables side by side."""
    rows = []
    for detector in dict.fromkeys(r.detector for r in results):
        rs = [r for r in results if r.detector == detector]
        classes = np.array([r.status for r in rs])
        errors = np.array([r.error_px for r in rs])
        row: dict[str, Any] = {
            "detector": detector,
            "pairs": len(rs),
            "keypoints": _nanmean((r.n_keypoints_1 + r.n_keypoints_2) / 2 for r in rs),
            "matches": _nanmean(r.n_matches for r in rs),
            "true_positives": _nanmean(r.n_true_positives for r in rs),
            "repeatability": _nanmean(r.repeatability for r in rs),
            "m_score": _nanmean(r.matching_score for r in rs),
            "nndr_auc": _nanmean(r.nndr_auc for r in rs),
            "coverage": _nanmean(r.coverage for r in rs),
        }
        for cls in CLASSES:
            row[f"{cls}_pct"] = 100.0 * float(np.mean(classes == cls))
        stats = gm.class_error_stats(classes, [r.mee_px for r in rs], [r.rmse_px for r in rs])
        for group, values in stats.items():
            for key in ("mee_mean", "mee_std", "rmse_mean", "rmse_std"):
                row[f"{group}_{key}"] = values[key]
        row.update(_fire_scores(errors, [r.category for r in rs]))
        row["time_ms"] = _nanmean(r.time_ms for r in rs)
        rows.append(row)
    return rows


def _fire_scores(errors: np.ndarray, categories: Sequence[str]) -> dict[str, float]:
    """The FIRE protocol's scores of per-pair errors: AUC 1-25, AUC 0-25, AUC per category,
    mAUC and the mean error of the pairs that did not fail."""
    scores = {"auc": gm.fire_auc(errors), "auc_0_25": gm.fire_auc_integral(errors)}
    cats = np.asarray(categories)
    by_category = {c: errors[cats == c] for c in dict.fromkeys(categories) if c}
    for c, errs in sorted(by_category.items(), key=lambda kv: _category_key(kv[0])):
        scores[f"auc_{c}"] = gm.fire_auc(errs)
    scores["mauc"] = gm.mean_auc(by_category)
    scores["mean_error_px"] = _nanmean(errors)
    return scores


def summarize_models(results: Sequence[PairResult]) -> list[dict[str, Any]]:
    """FIRE pairs: one row per detector and FIRE_VARIANTS fit (the same coarse matches): its
    FIRE scores, failed pairs and seconds per pair (coarse stage and fit); [] without them."""
    rows = []
    for detector in dict.fromkeys(r.detector for r in results):
        rs = [r for r in results if r.detector == detector and r.variant_error_px]
        for name in FIRE_VARIANTS:
            if not rs or name not in rs[0].variant_error_px:
                continue
            errors = np.array([r.variant_error_px[name] for r in rs])
            row: dict[str, Any] = {"detector": detector, "model": name, "pairs": len(rs)}
            row["failed"] = int(np.sum(~np.isfinite(errors)))
            row.update(_fire_scores(errors, [r.category for r in rs]))
            row["s_per_pair"] = _nanmean(r.coarse_s + r.variant_s[name] for r in rs)
            rows.append(row)
    return rows


def read_answers(path: Path) -> list[dict[str, Any]]:
    """The JSON lines `mosaic register --pairs` printed (one object per pair)."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read answers file {path}: {exc}") from exc
    answers = []
    for i, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            answer = json.loads(line)
        except json.JSONDecodeError as exc:
            raise InputError(f"{path} line {i} is not JSON: {exc}") from exc
        if not isinstance(answer, dict) or "moving" not in answer or "fixed" not in answer:
            raise InputError(f"{path} line {i} is not a `mosaic register --pairs` answer")
        answers.append(answer)
    return answers


def _answer_error(answer: dict[str, Any] | None, points: np.ndarray) -> tuple[float, float]:
    """Mean control-point errors (px, in the fixed image) of an answer and of its
    `H_moving_to_fixed`; inf for a failed or missing answer."""
    if answer is None or answer.get("status") != "registered" or not answer["H_moving_to_fixed"]:
        return math.inf, math.inf
    xy_fixed, xy_moving = points[:, 0:2], points[:, 2:4]

    def error(mapped: np.ndarray) -> float:
        return float(np.mean(np.linalg.norm(mapped - xy_fixed, axis=1)))

    h_error = error(apply_homography(np.array(answer["H_moving_to_fixed"]), xy_moving))
    if answer.get("model") != "quadratic" or not answer.get("Q_moving_to_fixed"):
        return h_error, h_error
    return error(apply_quadratic(np.array(answer["Q_moving_to_fixed"]), xy_moving)), h_error


def score_answers(
    root: Path, answers: Sequence[dict[str, Any]]
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The FIRE protocol applied to `mosaic register --pairs` answers on a FIRE folder:
    (per pair, summary). Each pair XNN is looked up by its images (fixed XNN_1, moving XNN_2,
    FIRE's order); its answer (the quadratic where it answered one, else the homography) and
    its `H_moving_to_fixed` map the control points of the moving image into the fixed one. A
    failed pair, or one without an answer, counts as a miss at every threshold."""
    by_images = {(Path(a["fixed"]).stem, Path(a["moving"]).stem): a for a in answers}
    rows = []
    for name, gt in fire_truth(root):
        answer = by_images.get((f"{name}_1", f"{name}_2"))
        answer_px, h_px = _answer_error(answer, read_matrix(gt, (-1, 4)))
        rows.append(
            {
                "pair": name,
                "category": fire_category(name),
                "status": "no answer" if answer is None else answer.get("status"),
                "model": None if answer is None else answer.get("model"),
                "answer_error_px": answer_px,
                "H_error_px": h_px,
            }
        )
    categories = [r["category"] for r in rows]
    summary = []
    for label, key in (("answer", "answer_error_px"), ("H_moving_to_fixed", "H_error_px")):
        errors = np.array([r[key] for r in rows])
        row: dict[str, Any] = {"transform": label, "pairs": len(rows)}
        row["failed"] = int(np.sum(~np.isfinite(errors)))
        row.update(_fire_scores(errors, categories))
        summary.append(row)
    return rows, summary


# --------------------------------------------------------------------------------------------
# Tables
# --------------------------------------------------------------------------------------------


def _fmt(value: Any, spec: str) -> str:
    if isinstance(value, float) and not math.isfinite(value):
        return "-" if math.isnan(value) else "inf"
    if value is None:
        return "-"
    return format(value, spec) if spec else str(value)


def format_table(rows: Sequence[dict[str, Any]], columns: Sequence[tuple[str, str, str]]) -> str:
    """Plain-text table: `columns` are (key, header, format spec); missing keys print "-"."""
    cells = [[header for _, header, _ in columns]]
    cells += [[_fmt(row.get(key), spec) for key, _, spec in columns] for row in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(columns))]
    lines = [
        "  ".join(
            c.ljust(w) if i == 0 else c.rjust(w)
            for i, (c, w) in enumerate(zip(r, widths, strict=True))
        )
        for r in cells
    ]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


MATCHING_COLUMNS = (
    ("detector", "detector", ""),
    ("pairs", "pairs", "d"),
    ("keypoints", "keypoints", ".1f"),
    ("matches", "matches", ".1f"),
    ("true_positives", "TPs", ".1f"),
    ("repeatability", "repeat.", ".3f"),
    ("m_score", "M.score", ".3f"),
    ("nndr_auc", "NNDR AUC", ".3f"),
    ("coverage", "coverage", ".3f"),
    ("time_ms", "ms/pair", ".0f"),
)
REGISTRATION_COLUMNS = (
    ("detector", "detector", ""),
    ("failed_pct", "failed %", ".1f"),
    ("inaccurate_pct", "inacc. %", ".1f"),
    ("acceptable_pct", "accept. %", ".1f"),
    ("acceptable_mee_mean", "MEE acc", ".2f"),
    ("acceptable_rmse_mean", "RMSE acc", ".2f"),
    ("non_failed_mee_mean", "MEE all", ".2f"),
    ("non_failed_rmse_mean", "RMSE all", ".2f"),
    ("auc", "AUC 1-25", ".3f"),
    ("auc_0_25", "AUC 0-25", ".3f"),
    ("mauc", "mAUC", ".3f"),
    ("mean_error_px", "error px", ".2f"),
)


FIRE_COLUMNS = (  # `_fire_scores` (a column per category goes in before mAUC)
    ("auc", "AUC 1-25", ".3f"),
    ("auc_0_25", "AUC 0-25", ".3f"),
    ("mauc", "mAUC", ".3f"),
    ("mean_error_px", "error px", ".2f"),
)
MODEL_COLUMNS = (
    ("detector", "detector", ""),
    ("model", "model", ""),
    ("failed", "failed", "d"),
    *FIRE_COLUMNS,
    ("s_per_pair", "s/pair", ".2f"),
)
ANSWER_COLUMNS = (
    ("transform", "transform", ""),
    ("pairs", "pairs", "d"),
    ("failed", "failed", "d"),
    *FIRE_COLUMNS,
)


def format_answer_table(summary: Sequence[dict[str, Any]]) -> str:
    """`score_answers`' summary: the FIRE protocol for the answer and for the homography."""
    return (
        "FIRE protocol of the `mosaic register --pairs` answers (error px: mean control-point "
        "distance in the fixed image, full resolution; failed pairs count as misses)\n"
        + format_table(summary, _with_categories(ANSWER_COLUMNS, summary))
    )


def _with_categories(
    columns: Sequence[tuple[str, str, str]], rows: Sequence[dict[str, Any]]
) -> list[tuple[str, str, str]]:
    """`columns` with an "AUC <category>" column per category in `rows`, before mAUC."""
    categories = sorted(
        {k[4:] for row in rows for k in row if k.startswith("auc_") and k != "auc_0_25"},
        key=_category_key,
    )
    at = [key for key, _, _ in columns].index("mauc")
    cols = list(columns)
    cols[at:at] = [(f"auc_{c}", f"AUC {c}", ".3f") for c in categories]
    return cols


def format_pair_tables(
    summary: Sequence[dict[str, Any]], models: Sequence[dict[str, Any]] = ()
) -> str:
    """The matching table and the registration table, one row per detector; for FIRE pairs
    (`models`: `summarize_models`) the FIRE protocol per motion model and refinement."""
    text = (
        "Matching (means per pair)\n"
        + format_table(summary, MATCHING_COLUMNS)
        + "\n\nRegistration (MEE/RMSE at detection scale; AUC and error px at full resolution)\n"
        + format_table(summary, _with_categories(REGISTRATION_COLUMNS, summary))
    )
    if models:
        text += (
            "\n\nFIRE protocol per model, fitted to the same matches as `mosaic register` fits "
            "them (error px at full resolution; s/pair: detection, matching and the fit)\n"
            + format_table(models, _with_categories(MODEL_COLUMNS, models))
        )
    return text


# --------------------------------------------------------------------------------------------
# Output files
# --------------------------------------------------------------------------------------------


def write_answer_tables(
    rows: Sequence[dict[str, Any]], summary: Sequence[dict[str, Any]], out_dir: str | Path
) -> Path:
    """`score_answers`' tables as `answers_pairs.csv` and `answers.csv` in `out_dir`."""
    out = make_folder(out_dir)
    write_csv(out / "answers_pairs.csv", rows)
    write_csv(out / "answers.csv", summary)
    return out


def write_csv(path: Path, rows: Sequence[dict[str, Any]]) -> Path:
    """Rows of dicts as CSV (columns: union of keys in first-seen order; nested values as JSON)."""
    columns = list(dict.fromkeys(k for row in rows for k in row))
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, fieldnames=columns, restval="")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: _csv_value(v) for k, v in row.items()})
    return write_text(path, text.getvalue())  # atomic: readers never see half a table


def _csv_value(value: Any) -> Any:
    if isinstance(value, float):
        return "" if math.isnan(value) else (f"{value:.6g}" if math.isfinite(value) else "inf")
    return value


def _json_safe(value: Any) -> Any:
    """nan -> None and inf -> "inf", recursively (JSON has neither)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


def _pyplot() -> Any:
    """matplotlib's pyplot on the Agg backend (imported lazily: only plotting needs it)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_pairs(
    results: Sequence[PairResult], summary: Sequence[dict[str, Any]], out: Path
) -> list[Path]:
    """cumulative_error.png (fraction of pairs under t, per detector) and success_rates.png."""
    plt = _pyplot()
    t = np.linspace(0.0, gm.FIRE_MAX_THRESHOLD_PX, 251)
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for row in summary:
        errors = np.array([r.error_px for r in results if r.detector == row["detector"]])
        ax.plot(t, gm.success_curve(errors, t), label=f"{row['detector']} (AUC {row['auc']:.3f})")
    ax.set_xlabel("error threshold t [px, full resolution]")
    ax.set_ylabel("fraction of pairs with error < t")
    ax.set_xlim(0, gm.FIRE_MAX_THRESHOLD_PX)
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    curve = out / "cumulative_error.png"
    with atomic_path(curve) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6.4, 0.5 * len(summary) + 1.4))
    names = [row["detector"] for row in summary]
    left = np.zeros(len(summary))
    colours = {"failed": "#d62728", "inaccurate": "#ff7f0e", "acceptable": "#2ca02c"}
    for cls in CLASSES:
        values = np.array([row[f"{cls}_pct"] for row in summary])
        ax.barh(names, values, left=left, color=colours[cls], label=cls)
        left += values
    ax.set_xlabel("pairs [%]")
    ax.set_xlim(0, 100)
    ax.invert_yaxis()
    ax.legend(fontsize=8, ncol=3, loc="lower center", bbox_to_anchor=(0.5, 1.0))
    fig.tight_layout()
    bars = out / "success_rates.png"
    with atomic_path(bars) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)
    return [curve, bars]


def plot_models(results: Sequence[PairResult], models: Sequence[dict[str, Any]], out: Path) -> Path:
    """cumulative_error_models.png: the FIRE success curve of each FIRE_VARIANTS fit, one
    panel per detector."""
    plt = _pyplot()
    detectors = list(dict.fromkeys(row["detector"] for row in models))
    t = np.linspace(0.0, gm.FIRE_MAX_THRESHOLD_PX, 251)
    fig, axes = plt.subplots(1, len(detectors), figsize=(4.6 * len(detectors), 3.8), squeeze=False)
    for ax, detector in zip(axes[0], detectors, strict=True):
        rs = [r for r in results if r.detector == detector and r.variant_error_px]
        for row in (m for m in models if m["detector"] == detector):
            errors = np.array([r.variant_error_px[row["model"]] for r in rs])
            label = f"{row['model']} (AUC {row['auc']:.3f})"
            ax.plot(t, gm.success_curve(errors, t), label=label)
        ax.set_title(detector, fontsize=10)
        ax.set_xlabel("error threshold t [px, full resolution]")
        ax.set_xlim(0, gm.FIRE_MAX_THRESHOLD_PX)
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="lower right")
    axes[0][0].set_ylabel("fraction of pairs with error < t")
    fig.tight_layout()
    path = out / "cumulative_error_models.png"
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)
    return path


def _pair_rows(results: Sequence[PairResult]) -> list[dict[str, Any]]:
    """pairs.csv's rows: a PairResult's fields, the variants' as `error_px_<variant>` and
    `s_<variant>` columns, without the homography."""
    rows = []
    for r in results:
        row = {k: v for k, v in dataclasses.asdict(r).items() if k not in _NESTED_PAIR_FIELDS}
        for name, error in r.variant_error_px.items():
            row[f"error_px_{name}"] = error
            row[f"s_{name}"] = r.variant_s[name]
        rows.append(row)
    return rows


_NESTED_PAIR_FIELDS = ("H_est_1_to_2", "variant_error_px", "variant_s")


def write_pair_outputs(
    results: Sequence[PairResult],
    summary: Sequence[dict[str, Any]],
    out_dir: str | Path,
    meta: dict[str, Any] | None = None,
) -> list[Path]:
    """summary.csv / summary.json (per detector), pairs.csv (per pair), the two plots and, for
    FIRE pairs, models.csv (per detector and FIRE_VARIANTS fit; also `models` in the JSON) and
    cumulative_error_models.png."""
    out = make_folder(out_dir)
    models = summarize_models(results)
    written = [
        write_csv(out / "summary.csv", summary),
        write_csv(out / "pairs.csv", _pair_rows(results)),
    ]
    if models:
        written.append(write_csv(out / "models.csv", models))
    document = {
        "meta": meta or {},
        "summary": list(summary),
        "models": models,
        "pairs": [dataclasses.asdict(r) for r in results],
    }
    written.append(write_json(out / "summary.json", _json_safe(document)))
    written += plot_pairs(results, summary, out)
    if models:
        written.append(plot_models(results, models, out))
    return written


def run_pair_evaluation(
    dataset: PairDataset,
    config: Config,
    detectors: Sequence[str],
    out_dir: str | Path,
    scale: float | None = None,
    max_pairs: int = 0,
    explicit: bool = True,
    progress: bool = False,
) -> tuple[list[PairResult], list[dict[str, Any]]]:
    """Evaluate every detector on a dataset and write the tables and plots into `out_dir`.

    `scale` None: 0.15 for FIRE (the paper's protocol), 1 otherwise.
    """
    if scale is None:
        scale = FIRE_SCALE if dataset.format == "fire" else 1.0
    config = for_photographs(config)
    if not 0.0 < scale <= 4.0:
        raise InputError(f"scale must be in (0, 4], got {scale}")
    make_folder(out_dir)
    extractors = make_extractors(config, detectors, explicit)
    results = evaluate_pairs(dataset, extractors, scale, max_pairs, progress)
    summary = summarize_pairs(results)
    meta = {
        "dataset": str(dataset.root),
        "format": dataset.format,
        "scale": scale,
        "detectors": list(extractors),
        "config": dataclasses.asdict(config),
    }
    write_pair_outputs(results, summary, out_dir, meta)
    return results, summary


# --------------------------------------------------------------------------------------------
# Videos
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class VideoResult:
    """One detector on one video (one row of videos.csv)."""

    detector: str  # "name/strategy", e.g. "sift/keyframes"
    video: str
    has_ground_truth: bool
    frames: int  # frames read (including skipped ones)
    registered: int
    failed: int
    skipped: int
    registered_fraction: float  # registered / decoded frames
    frames_until_failure: int  # registered (and, with ground truth, accurate) from the start
    frames_until_failure_pipeline: int  # the pipeline's own count (registration failures only)
    accurate_fraction: float  # registered within 10 px of the truth / decoded frames
    mean_error_px: float  # corner error of registered frames (frame -> first frame)
    median_error_px: float
    max_error_px: float
    drift_px_per_frame: float  # slope of the corner error against the frame index
    mean_inliers: float
    fps: float
    step_median_px: float = math.nan  # corner error of each frame relative to its reference
    step_p90_px: float = math.nan
    quality_rho: float = math.nan  # Spearman of quality and corner error (negative: it works)
    bad_frames: float = math.nan  # frames more than 10 px off the truth (nan: no truth)
    bad_caught: float = math.nan  # fraction of them flagged by the quality score
    good_flagged: float = math.nan  # fraction of the frames within 10 px flagged
    fidelity: float = math.nan  # mean local NCC of the main mosaic and the source (issue 16)
    good_area: float = math.nan  # share of the scanned retina with local NCC > 0.5
    oracle_fidelity: float = math.nan  # the same for the mean of frames placed by the truth
    oracle_good_area: float = math.nan
    model_counts: dict[str, int] = field(default_factory=dict)  # registered frames per model
    # mosaic segments (several: the camera left the mapped area; `registered` counts them all,
    # `accurate` and the errors are of the first placed frame's segment)
    segments: int = 1
    precision: str | None = None  # GLAMpoints' network as it ran (None: no network, older run)
    errors: list[tuple[int, float]] = field(default_factory=list, repr=False)  # (index, px)
    step_errors: list[tuple[int, float]] = field(default_factory=list, repr=False)


def find_videos(paths: Sequence[str | Path]) -> list[Path]:
    """Videos named on the command line: files, frame folders, or folders holding videos.

    A folder with image files is one video (its frames); otherwise its video files and its
    sub-folders that have a `<name>.gt.json` beside them are the videos.
    """
    found: list[Path] = []
    for raw in paths:
        p = Path(raw).expanduser()
        if not p.exists():
            raise InputError(f"input not found: {p}")
        if p.is_file():
            found.append(p)
            continue
        if is_frame_folder(p):
            found.append(p)
            continue
        inner = sorted(
            f
            for f in p.iterdir()
            if (f.is_file() and f.suffix.lower() in VIDEO_SUFFIXES)
            or (f.is_dir() and gt_path_for(f).is_file())
        )
        if not inner:
            raise InputError(f"no videos or frames in {p}")
        found += inner
    return found


def _video_errors(
    frames: list[dict[str, Any]], gt: list[np.ndarray], size: tuple[int, int]
) -> dict[int, float]:
    """Corner error (px) of each registered frame of the first frame's segment, vs the truth."""
    placed = [f for f in frames if f["status"] == REGISTERED and f["H_to_canvas"] is not None]
    if not placed:
        return {}
    ref = placed[0]
    H_ref_to_canvas = np.asarray(ref["H_to_canvas"], np.float64)
    if ref["index"] >= len(gt):
        return {}
    rel = relative_homographies(gt, ref=ref["index"])
    errors = {}
    for f in placed:
        if f["segment"] != ref["segment"]:
            continue
        if f["index"] >= len(gt):
            log.warning("frame %d has no ground truth (%d frames in it)", f["index"], len(gt))
            continue
        H_i_to_ref = np.linalg.solve(H_ref_to_canvas, np.asarray(f["H_to_canvas"], np.float64))
        errors[f["index"]] = corner_error(H_i_to_ref, rel[f["index"]], size)
    return errors


def _frame_references(frames: list[dict[str, Any]]) -> dict[int, int]:
    """{frame index: index of the frame it was registered against} for registered frames.

    The report's `"reference"` is used when it names a placed frame of the same segment. When it
    is missing or None (reports written before it existed) for a frame that is not its
    segment's first, the previous registered frame of that segment stands in: exact for the
    chain strategy, an approximation for keyframes. A segment's first frame has no reference.
    """
    placed = [f for f in frames if f["status"] == REGISTERED and f["H_to_canvas"] is not None]
    segment_of = {f["index"]: f["segment"] for f in placed}
    previous: dict[Any, int] = {}  # segment -> last registered frame index
    references = {}
    for f in placed:
        ref = f.get("reference")
        if ref is None:
            ref = previous.get(f["segment"])
        elif segment_of.get(ref, object()) != f["segment"] or ref == f["index"]:
            log.warning("frame %d: reference %s is not a registered frame", f["index"], ref)
            ref = None
        if ref is not None:
            references[f["index"]] = int(ref)
        previous[f["segment"]] = f["index"]
    return references


def _step_errors(
    frames: list[dict[str, Any]], gt: list[np.ndarray], size: tuple[int, int]
) -> dict[int, float]:
    """Corner error (px) of each registered frame's placement relative to its reference.

    Estimate inv(P_ref) @ P_i (P = the report's H_to_canvas), truth inv(G_ref) @ G_i (G =
    H_frame_to_source), both in full-size frame pixels; references from `_frame_references`.
    """
    poses = {
        f["index"]: np.asarray(f["H_to_canvas"], np.float64)
        for f in frames
        if f["status"] == REGISTERED and f["H_to_canvas"] is not None
    }
    errors = {}
    for index, ref in _frame_references(frames).items():
        if max(index, ref) >= len(gt):
            log.warning("frame %d or %d has no ground truth (%d frames)", index, ref, len(gt))
            continue
        H_est = np.linalg.solve(poses[ref], poses[index])
        H_gt = np.linalg.solve(gt[ref], gt[index])
        errors[index] = corner_error(H_est, H_gt, size)
    return errors


def _model_counts(frames: list[dict[str, Any]]) -> dict[str, int]:
    """Registered frames per motion model (every model of MOTION_MODELS, 0 when unused).

    Frames without a `"model"` (a segment's first frame, older reports) are not counted; a
    model name outside MOTION_MODELS gets its own entry after them.
    """
    counts = dict.fromkeys(MOTION_MODELS, 0)
    for f in frames:
        model = f.get("model")
        if f["status"] == REGISTERED and model is not None:
            counts[model] = counts.get(model, 0) + 1
    return counts


def _quality_vs_error(
    frames: list[dict[str, Any]], errors: dict[int, float] | None
) -> dict[str, float]:
    """How the report's per-frame `quality` and `flagged` predict the corner error (`errors`).

    Over the frames with an error but the reference frame (error 0 by construction, never
    scored): `quality_rho`, the Spearman correlation of score and error over the scored ones
    (negative: lower score, larger error); `bad_frames`, those more than
    ACCURATE_CORNER_ERROR_PX off; `bad_caught`, the fraction of them flagged (a frame without a
    score is never flagged: a miss); `good_flagged`, the fraction of the others flagged. NaN
    without errors, or (but `bad_frames`) when no frame has a score (older reports).
    """
    nan = math.nan
    if errors is None:
        return {"quality_rho": nan, "bad_frames": nan, "bad_caught": nan, "good_flagged": nan}
    entries = {f["index"]: f for f in frames}
    judged = sorted(errors)[1:]  # the first is the reference frame
    error = np.array([errors[i] for i in judged], np.float64)
    score = np.array([entries[i].get("quality") for i in judged], np.float64)  # None -> nan
    flagged = np.array([bool(entries[i].get("flagged")) for i in judged], bool)
    bad = error > ACCURATE_CORNER_ERROR_PX
    scored = bool(np.isfinite(score).any())

    def flagged_share(group: np.ndarray) -> float:
        return float(flagged[group].mean()) if scored and group.any() else nan

    return {
        "quality_rho": spearman(score, error),
        "bad_frames": float(bad.sum()),
        "bad_caught": flagged_share(bad),
        "good_flagged": flagged_share(~bad),
    }


def _leading_accurate(frames: list[dict[str, Any]], errors: dict[int, float] | None) -> int:
    """Registered (and accurate, when errors are given) frames from the start until a failure."""
    count = 0
    for f in frames:
        if f["status"] == SKIPPED:
            continue
        if f["status"] == FAILED:
            break
        if errors is not None and not errors.get(f["index"], math.inf) <= ACCURATE_CORNER_ERROR_PX:
            break
        count += 1
    return count


def _unique_stems(videos: Sequence[Path]) -> list[str]:
    """Each video's file stem (a frame folder's name), made unique with "-2", "-3", ..."""
    stems: list[str] = []
    for video in videos:
        stem = base = video.name if video.is_dir() else video.stem
        k = 1
        while stem in stems:
            k += 1
            stem = f"{base}-{k}"
        stems.append(stem)
    return stems


@dataclass(frozen=True)
class FidelityReference:
    """A video's truth for the mosaic-fidelity scores, shared by all its runs."""

    truth: list[np.ndarray]  # H_frame_to_source per frame index
    source: SourceTruth
    oracle: FidelityScores  # the mean of the frames placed by the truth


def source_path(gt_file: Path) -> Path | None:
    """The source photograph a ground-truth file names (None if it names none).

    `~` is expanded; a relative path is looked up beside the ground truth (where its video
    is), then from the current folder (where `mosaic synth` was run); the first that exists,
    else the former.
    """
    try:
        source = json.loads(gt_file.read_text(encoding="utf-8")).get("source")
    except (OSError, ValueError, AttributeError) as exc:
        raise InputError(f"malformed ground truth {gt_file}: {exc}") from exc
    if not isinstance(source, str) or not source:
        return None
    p = Path(source).expanduser()
    if p.is_absolute():
        return p
    beside = gt_file.parent / p
    return beside if beside.is_file() or not p.is_file() else p


def _fov_masker(config: Config) -> Callable[[np.ndarray], np.ndarray | None]:
    """The frames' field-of-view mask as the pipeline composes them (None: no mask)."""
    pre = config.preprocess

    def mask_of(image: np.ndarray) -> np.ndarray | None:
        if not pre.fov_mask:
            return None
        return field_of_view_mask(
            to_gray(image, pre.green_channel), pre.fov_threshold, pre.fov_erode_px
        )

    return mask_of


def fidelity_reference(path: Path, config: Config) -> FidelityReference | None:
    """Truth, source and oracle scores of a video, or None without ground truth or a readable
    source photograph (then one warning). The oracle reads the video once more, frame by frame.
    """
    gt_file = gt_path_for(path)
    if not gt_file.is_file():
        return None
    source_file = source_path(gt_file)
    try:
        if source_file is None:
            raise InputError(f"{gt_file} names no source image")
        image = read_image(source_file)
    except InputError as exc:
        log.warning("no fidelity scores for %s: %s", path, exc)
        return None
    start = time.perf_counter()
    truth = load_ground_truth(gt_file)
    source = prepare_source(image)
    frames = _reread(path, config.pipeline.step, config.pipeline.max_frames)()
    oracle = oracle_fidelity(
        frames, truth, source, _fov_masker(config), config.compose.max_canvas_px
    )
    log.info(
        "oracle of %s: fidelity %.3f, good area %.3f (%.1f s)",
        path.name,
        oracle.fidelity,
        oracle.good_area,
        time.perf_counter() - start,
    )
    return FidelityReference(truth, source, oracle)


def _fidelity_scores(
    result: MosaicResult, reference: FidelityReference, size: tuple[int, int]
) -> dict[str, float]:
    """The main mosaic's fidelity and good area (its frames' reported poses map into its
    image), and the video's oracle, as VideoResult fields."""
    start = time.perf_counter()
    frames = result.report["frames"]
    main = result.main
    scores = FidelityScores()
    if main is not None:
        poses = {
            f["index"]: np.asarray(f["H_to_canvas"], np.float64)
            for f in frames
            if f["status"] == REGISTERED
            and f["segment"] == main.index
            and f["H_to_canvas"] is not None
        }
        image = main.image
        content = image.any(axis=2) if image.ndim == 3 else image > 0
        scanned = [f["index"] for f in frames]
        scores = mosaic_fidelity(
            image, content, poses, reference.truth, reference.source, size, scanned
        )
    log.info(
        "fidelity %.3f, good area %.3f (oracle %.3f, %.3f; %.1f s)",
        scores.fidelity,
        scores.good_area,
        reference.oracle.fidelity,
        reference.oracle.good_area,
        time.perf_counter() - start,
    )
    return {
        "fidelity": scores.fidelity,
        "good_area": scores.good_area,
        "oracle_fidelity": reference.oracle.fidelity,
        "oracle_good_area": reference.oracle.good_area,
    }


def evaluate_video(
    path: Path,
    config: Config,
    extractor: FeatureExtractor,
    progress: bool = False,
    report_path: Path | None = None,
    fidelity: bool = True,
    reference: FidelityReference | None = None,
) -> VideoResult:
    """Run the pipeline over a video (failed frames skipped) and score it against its truth.

    The frames' poses are the ones `mosaic build` reports: after the strategy's refinement
    (keyframes: pose graph) and re-rendering, so the video is read twice. With `report_path`,
    that report (with the input, as `mosaic build` writes it) is saved there as JSON.

    With `fidelity`, the main mosaic is scored against the source photograph (nan without
    one); `reference` is the video's `fidelity_reference`, computed here when None (pass it
    to score several runs of one video with one oracle).
    """
    config = with_overrides(config, pipeline={"on_failure": "skip"})
    run = run_video(  # refined poses, as `mosaic build` reports
        path,
        config,
        Outputs(report=report_path),
        extractor=extractor,
        progress=f"{extractor.detector.name} {path.name}" if progress else None,
        salvage=False,
    )
    result, info = run.result, run.info
    size = (info.width, info.height)
    frames, summary = result.report["frames"], result.report["summary"]
    gt_file = gt_path_for(path)
    errors: dict[int, float] | None = None
    steps: dict[int, float] = {}
    if gt_file.is_file() and size is not None:
        gt = load_ground_truth(gt_file)
        errors = _video_errors(frames, gt, size)
        steps = _step_errors(frames, gt, size)
    step_values = np.array(list(steps.values()))
    # every frame the video holds counts, those the gate skipped too (a frame skipped as
    # blurred is not placed: counting it out flattered gating); only undecodable ones do not
    undecodable = sum(f.get("reason") == UNDECODABLE for f in frames)
    decoded = max(summary["frames_read"] - undecodable, 1)
    values = np.array(list(errors.values())) if errors else np.zeros(0)
    drift = math.nan
    if len(values) >= 2:
        idx = np.array(list(errors), dtype=np.float64)  # type: ignore[arg-type]
        drift = float(np.polyfit(idx, values, 1)[0])
    accurate = int((values <= ACCURATE_CORNER_ERROR_PX).sum()) if errors is not None else 0
    if fidelity and reference is None:
        reference = fidelity_reference(path, config)
    scores = _fidelity_scores(result, reference, size) if fidelity and reference else {}
    return VideoResult(
        detector=f"{extractor.detector.name}/{config.pipeline.strategy}",
        video=str(path),
        has_ground_truth=errors is not None,
        frames=summary["frames_read"],
        registered=summary["registered"],
        failed=summary["failed"],
        skipped=summary["skipped"],
        registered_fraction=summary["registered"] / decoded,
        frames_until_failure=_leading_accurate(frames, errors),
        frames_until_failure_pipeline=summary["frames_until_failure"],
        accurate_fraction=accurate / decoded if errors is not None else math.nan,
        mean_error_px=float(values.mean()) if values.size else math.nan,
        median_error_px=float(np.median(values)) if values.size else math.nan,
        max_error_px=float(values.max()) if values.size else math.nan,
        drift_px_per_frame=drift,
        mean_inliers=float(summary["mean_inliers"]),
        fps=float(summary["fps"]),
        step_median_px=float(np.median(step_values)) if step_values.size else math.nan,
        step_p90_px=float(np.percentile(step_values, 90)) if step_values.size else math.nan,
        **_quality_vs_error(frames, errors),
        **scores,
        model_counts=_model_counts(frames),
        segments=summary["segments"],
        precision=summary.get("precision"),
        errors=sorted(errors.items()) if errors else [],
        step_errors=sorted(steps.items()),
    )


VIDEO_MEAN_KEYS = (
    "frames",
    "registered_fraction",
    "frames_until_failure",
    "frames_until_failure_pipeline",
    "accurate_fraction",
    "mean_error_px",
    "max_error_px",
    "drift_px_per_frame",
    "step_median_px",
    "step_p90_px",
    "quality_rho",
    "bad_frames",
    "bad_caught",
    "good_flagged",
    "fidelity",
    "good_area",
    "oracle_fidelity",
    "oracle_good_area",
    "mean_inliers",
    "fps",
    "segments",
)
VIDEO_COLUMNS = (
    ("detector", "detector", ""),
    ("videos", "videos", "d"),
    ("frames", "frames", ".1f"),
    ("registered_fraction", "registered", ".3f"),
    ("frames_until_failure", "until fail", ".2f"),
    ("frames_until_failure_pipeline", "until fail (pipe)", ".2f"),
    ("accurate_fraction", "accurate", ".3f"),
    ("mean_error_px", "error px", ".2f"),
    ("max_error_px", "max px", ".2f"),
    ("drift_px_per_frame", "drift px/fr", ".3f"),
    ("step_median_px", "step med px", ".2f"),
    ("step_p90_px", "step p90 px", ".2f"),
    ("quality_rho", "quality rho", ".2f"),
    ("bad_frames", "bad >10px", ".1f"),
    ("bad_caught", "bad caught", ".2f"),
    ("good_flagged", "good flagged", ".2f"),
    ("fidelity", "fidelity", ".3f"),
    ("good_area", "good area", ".3f"),
    ("oracle_fidelity", "oracle fid", ".3f"),
    ("oracle_good_area", "oracle good", ".3f"),
    ("models", "models", ""),
    ("fps", "fps", ".1f"),
)


# paired differences between methods (`compare_methods`): (key, header, format spec)
DIFFERENCE_KEYS = (
    ("accurate_fraction", "accurate", ".3f"),
    ("registered_fraction", "registered", ".3f"),
    ("until_failure_share", "until failure", ".3f"),  # frames_until_failure / frames
    ("mean_error_px", "error px", ".2f"),
)
BOOTSTRAP_SAMPLES = 2000


def _video_value(result: VideoResult, key: str) -> float:
    if key == "until_failure_share":
        return result.frames_until_failure / result.frames if result.frames else math.nan
    return float(getattr(result, key))


def _paired(
    pairs: Sequence[tuple[VideoResult, VideoResult]],
    method: str,
    against: str,
    rng: np.random.Generator,
    samples: int,
) -> dict[str, Any]:
    """The mean difference (first of each pair minus second) per measure, and its 95 %
    bootstrap interval over the pairs (videos resampled)."""
    row: dict[str, Any] = {"method": method, "against": against, "videos": len(pairs)}
    for key, _, _ in DIFFERENCE_KEYS:
        d = np.array([_video_value(a, key) - _video_value(b, key) for a, b in pairs])
        d = d[np.isfinite(d)]
        # rounded below float noise: equal runs print +0.000, not -0.000
        row[key] = round(float(d.mean()), 12) + 0.0 if len(d) else math.nan
        low = high = math.nan
        if len(d) >= 2:
            means = d[rng.integers(0, len(d), (samples, len(d)))].mean(axis=1)
            low, high = (float(x) for x in np.percentile(means, [2.5, 97.5]))
        row[f"{key}_low"], row[f"{key}_high"] = low, high
    return row


def compare_methods(
    results: Sequence[VideoResult],
    previous: Sequence[VideoResult] = (),
    samples: int = BOOTSTRAP_SAMPLES,
    seed: int = 0,
) -> list[dict[str, Any]]:
    """Each method (detector/strategy) against the run's first, and against itself in a
    `previous` run (`load_video_results`), paired over the videos both ran: the mean
    difference and its 95 % bootstrap interval (videos resampled). Single drifting videos
    swing by tenths with small changes, so on a few videos a difference whose interval holds
    0 is no difference; pairing removes what the videos themselves vary by."""
    rng = np.random.default_rng(seed)
    methods = list(dict.fromkeys(r.detector for r in results))
    by_run = {(r.detector, r.video): r for r in results}
    rows = []
    base = methods[0] if methods else ""
    for method in methods[1:]:
        videos = [v for m, v in by_run if m == method and (base, v) in by_run]
        pairs = [(by_run[method, v], by_run[base, v]) for v in videos]
        rows.append(_paired(pairs, method, base, rng, samples))
    key_before, key_now = _video_keys(previous), _video_keys(results)
    before = {(r.detector, key_before[r.video]): r for r in previous}
    for method in methods if previous else []:
        runs = [r for r in results if r.detector == method]
        keys = [(method, key_now[r.video]) for r in runs]
        pairs = [(r, before[k]) for r, k in zip(runs, keys, strict=True) if k in before]
        rows.append(_paired(pairs, method, f"{method} (previous run)", rng, samples))
    return rows


def warn_of_precisions(results: Sequence[VideoResult], previous: Sequence[VideoResult]) -> None:
    """Say where a method's GLAMpoints ran in another precision in the earlier run: single
    videos swing by tenths between float32 and bfloat16, so the differences include that."""
    before = {r.detector: r.precision for r in previous}
    mixed = {
        (r.detector, r.precision, before[r.detector])
        for r in results
        if r.detector in before and r.precision != before[r.detector]
    }
    for method, now, then in sorted(mixed, key=str):
        log.warning(
            "%s ran in %s here and in %s in the earlier run: the differences include the "
            "precision's (single videos swing by tenths between the two)",
            method, now or "an unrecorded precision", then or "an unrecorded precision",
        )  # fmt: skip


def _video_keys(run: Sequence[VideoResult]) -> dict[str, str]:
    """How each video of a run is matched across runs: by its file name where the run holds
    no other video of that name (runs started from other folders name the same video by other
    paths), else by its path."""
    videos = {r.video for r in run}
    names = Counter(Path(v).name for v in videos)
    return {v: Path(v).name if names[Path(v).name] == 1 else v for v in videos}


def load_video_results(path: Path) -> list[VideoResult]:
    """The per-video results of an earlier `mosaic evaluate` (its `--out` folder or its
    video_evaluation.json), for `compare_methods`."""
    file = path / "video_evaluation.json" if path.is_dir() else path
    try:
        videos = json.loads(file.read_text())["videos"]
        fields = {f.name for f in dataclasses.fields(VideoResult)}
        # JSON wrote nan as null (precision's null is None)
        entries = [
            {k: math.nan if v is None and k != "precision" else v for k, v in e.items()}
            for e in videos
        ]
        return [VideoResult(**{k: v for k, v in e.items() if k in fields}) for e in entries]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"not the output of `mosaic evaluate` on videos: {path} ({exc})") from exc


def format_differences(rows: Sequence[dict[str, Any]]) -> str:
    """The table of `compare_methods`: 'mean [low, high]' per measure."""
    cells = []
    for row in rows:
        cell: dict[str, Any] = {k: row[k] for k in ("method", "against", "videos")}
        for key, _, spec in DIFFERENCE_KEYS:
            mean, low, high = (_fmt(row[k], f"+{spec}") for k in (key, f"{key}_low", f"{key}_high"))
            cell[key] = mean if math.isnan(row[f"{key}_low"]) else f"{mean} [{low}, {high}]"
        cells.append(cell)
    columns = [("method", "method", ""), ("against", "against", ""), ("videos", "videos", "d")]
    columns += [(key, header, "") for key, header, _ in DIFFERENCE_KEYS]
    return format_table(cells, columns)


def _model_columns(counts: dict[str, float]) -> dict[str, float]:
    """{"model_<name>": count} for the CSV, every model of MOTION_MODELS first (0 if absent)."""
    merged = {**dict.fromkeys(MOTION_MODELS, 0), **counts}
    return {f"model_{name}": n for name, n in merged.items()}


def format_models(counts: dict[str, float], spec: str = "d") -> str | None:
    """The models in use, abbreviated, e.g. "sim 80 / aff 10 / hom 9"; None when none was."""
    used = [f"{name[:3]} {format(n, spec)}" for name, n in counts.items() if n]
    return " / ".join(used) or None


def summarize_videos(results: Sequence[VideoResult]) -> list[dict[str, Any]]:
    """Mean over videos per detector (nan entries, e.g. no ground truth, are left out)."""
    rows = []
    for detector in dict.fromkeys(r.detector for r in results):
        rs = [r for r in results if r.detector == detector]
        row: dict[str, Any] = {"detector": detector, "videos": len(rs)}
        row.update({k: _nanmean(getattr(r, k) for r in rs) for k in VIDEO_MEAN_KEYS})
        columns = [_model_columns(r.model_counts) for r in rs]
        names = dict.fromkeys(n for c in columns for n in c)
        row.update({n: float(np.mean([c.get(n, 0) for c in columns])) for n in names})
        rows.append(row)
    return rows


def format_video_tables(
    results: Sequence[VideoResult],
    summary: Sequence[dict[str, Any]],
    previous: Sequence[VideoResult] = (),
) -> str:
    """Per-video tables (one per detector), the mean over videos, and the paired differences
    (`compare_methods`: against the first method, and against a `previous` run)."""
    per_video = [
        {
            **dataclasses.asdict(r),
            "videos": 1,
            "detector": f"{r.detector} {Path(r.video).name}",
            "models": format_models(r.model_counts),
        }
        for r in results
    ]
    means = [{**row, "models": format_models(_summary_models(row), ".1f")} for row in summary]
    text = (
        "Per video (models: registered frames per motion model)\n"
        + format_table(per_video, VIDEO_COLUMNS)
        + "\n\nMean over videos\n"
        + format_table(means, VIDEO_COLUMNS)
    )
    differences = compare_methods(results, previous)
    if differences:
        text += (
            "\n\nPaired over the same videos: mean difference [95 % bootstrap interval over "
            "videos]\n" + format_differences(differences)
        )
    return text


def _summary_models(row: dict[str, Any]) -> dict[str, float]:
    """{model: mean count} back from a summary row's "model_<name>" entries."""
    return {k[len("model_") :]: v for k, v in row.items() if k.startswith("model_")}


def plot_videos(
    results: Sequence[VideoResult], summary: Sequence[dict[str, Any]], out: Path
) -> list[Path]:
    """video_frames_until_failure.png (bars) and video_error.png (error against frame index)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 0.5 * len(summary) + 1.4))
    names = [row["detector"] for row in summary]
    ax.barh(names, [row["frames_until_failure"] for row in summary], color="#1f77b4")
    ax.set_xlabel("frames until failure (mean over videos)")
    ax.invert_yaxis()
    fig.tight_layout()
    bars = out / "video_frames_until_failure.png"
    with atomic_path(bars) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    colours = {name: f"C{i % 10}" for i, name in enumerate(names)}
    labelled: set[str] = set()
    for r in results:
        if not r.errors:
            continue
        idx, err = zip(*r.errors, strict=True)
        label = r.detector if r.detector not in labelled else None
        labelled.add(r.detector)
        ax.plot(idx, err, color=colours.get(r.detector), alpha=0.8, lw=1, label=label)
    ax.axhline(ACCURATE_CORNER_ERROR_PX, color="k", ls="--", lw=0.8)
    ax.set_xlabel("frame index")
    ax.set_ylabel("corner error vs ground truth [px]")
    ax.set_yscale("symlog", linthresh=1.0)
    ax.set_ylim(bottom=0.0)
    ax.grid(alpha=0.3)
    if labelled:
        ax.legend(fontsize=8)
    fig.tight_layout()
    curve = out / "video_error.png"
    with atomic_path(curve) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)
    return [bars, curve]


_VIDEO_ROW_EXCLUDED = ("errors", "step_errors", "model_counts")  # per-frame lists; a dict


def write_video_outputs(
    results: Sequence[VideoResult],
    summary: Sequence[dict[str, Any]],
    out_dir: str | Path,
    meta: dict[str, Any] | None = None,
    previous: Sequence[VideoResult] = (),
) -> list[Path]:
    """videos.csv (per video), video_summary.csv, video_differences.csv (`compare_methods`,
    with two methods or more) / video_evaluation.json and the plots."""
    out = make_folder(out_dir)
    rows = [
        {
            **{k: v for k, v in dataclasses.asdict(r).items() if k not in _VIDEO_ROW_EXCLUDED},
            **_model_columns(r.model_counts),
        }
        for r in results
    ]
    written = [write_csv(out / "videos.csv", rows), write_csv(out / "video_summary.csv", summary)]
    differences = compare_methods(results, previous)
    if differences:
        written.append(write_csv(out / "video_differences.csv", differences))
    document = {
        "meta": meta or {},
        "summary": list(summary),
        "differences": differences,
        "videos": [dataclasses.asdict(r) for r in results],
    }
    written.append(write_json(out / "video_evaluation.json", _json_safe(document)))
    written += plot_videos(results, summary, out)
    return written


def run_video_evaluation(
    paths: Sequence[str | Path],
    config: Config,
    detectors: Sequence[str],
    out_dir: str | Path,
    explicit: bool = True,
    progress: bool = False,
    strategies: Sequence[str] = ("keyframes", "chain"),
    fidelity: bool = True,
    previous: Sequence[VideoResult] = (),
) -> tuple[list[VideoResult], list[dict[str, Any]]]:
    """Evaluate every detector with every strategy on every video; write tables and plots
    (with `previous`, an earlier run's results, the differences against it too).

    Each run's report goes to `reports/<video stem>__<detector>__<strategy>.json` in `out_dir`
    (listed in the same order as the results under the JSON's `meta.reports`). With
    `fidelity`, each video's oracle is computed once and shared by its runs.
    """
    videos = find_videos(paths)
    report_dir = make_folder(Path(out_dir).expanduser() / "reports")
    extractors = make_extractors(config, detectors, explicit)
    results, reports = [], []
    for video, stem in zip(videos, _unique_stems(videos), strict=True):
        reference = fidelity_reference(video, config) if fidelity else None
        for name, (cfg, extractor) in extractors.items():
            for strategy in strategies:
                cfg_strategy = with_overrides(cfg, pipeline={"strategy": strategy})
                report = report_dir / f"{stem}__{name}__{strategy}.json"
                results.append(
                    evaluate_video(
                        video,
                        cfg_strategy,
                        extractor,
                        progress,
                        report,
                        fidelity=reference is not None,
                        reference=reference,
                    )
                )
                reports.append(str(report.relative_to(report_dir.parent)))
    summary = summarize_videos(results)
    meta = {
        "videos": [str(v) for v in videos],
        "detectors": list(extractors),
        "config": dataclasses.asdict(config),
        "reports": reports,
        "fidelity": fidelity,
    }
    write_video_outputs(results, summary, out_dir, meta, previous)
    warn_of_precisions(results, previous)
    return results, summary
