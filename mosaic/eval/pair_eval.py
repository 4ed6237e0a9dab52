"""Pair evaluation (`glampoints evaluate`): the paper's pair metrics and the FIRE protocol.

Each detector of the registry runs through the pipeline's own stages (`prepare` →
`FeatureExtractor` → `match_descriptors` → `estimate_homography`) and is scored with the
paper's criteria (`glampoints.metrics`): repeatability (3 px), M.score, NNDR matching AUC,
coverage fraction of true positives, and the registration class (failed / inaccurate /
acceptable) from the errors of ground-truth points (six fixed points for homography datasets,
the control points for FIRE) with MEE / RMSE per class. Every pair also gets the FIRE protocol
error (mean ground-truth point error at full resolution, inf when failed), from which the AUC
over thresholds 1..25 px, its 0..25 integral variant, per-category AUCs and mAUC follow.
`score_answers` applies the FIRE protocol to `mosaic register --pairs` answers instead.

Outputs (`write_pair_outputs`): CSV and JSON tables, per-pair rows and PNG plots. Pure metric
definitions live in `glampoints.metrics`, not here.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from mosaic.config import Config, RegistrationConfig, for_photographs
from mosaic.errors import InputError
from mosaic.eval.common import format_table, json_safe, make_extractors, nanmean, pyplot, write_csv
from mosaic.eval.datasets import (
    FIRE_CATEGORIES,
    Pair,
    PairDataset,
    fire_category,
    fire_truth,
    read_matrix,
)
from mosaic.features import FeatureExtractor, Features
from mosaic.features import paper_metrics as gm
from mosaic.io import atomic_path, make_folder, write_json
from mosaic.matching import distance_matrix, match_descriptors
from mosaic.pixel_refine import fit_pair
from mosaic.preprocess import prepare, retina_disc, scale_matrix
from mosaic.registration import apply_homography, apply_quadratic, estimate_homography

log = logging.getLogger(__name__)

EPS_PX = 3.0  # correctness radius of a keypoint / match (paper: 3 px)
FIRE_SCALE = 0.15  # the paper's FIRE protocol: 2912 px images downscaled to 15 % for detection
CLASSES = ("failed", "inaccurate", "acceptable")
# FIRE pairs: the final fit of `mosaic register` (`pixel_refine.fit_pair`) on the coarse
# inliers, per motion model and with or without the coarse-to-fine refinement:
# name -> (model, refined)
FIRE_VARIANTS = {
    "hom": ("homography", False),
    "hom+refine": ("homography", True),
    "quad": ("quadratic", False),
    "quad+refine": ("quadratic", True),
}


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


def least_squares_homography(xy_1: np.ndarray, xy_2: np.ndarray) -> np.ndarray | None:
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


def _detection_scores(
    f1: Features,
    f2: Features,
    xy1_m: np.ndarray,
    xy2_m: np.ndarray,
    H: np.ndarray,
    shape1: tuple[int, int],
    shape2: tuple[int, int],
) -> tuple[float, float, int, float, float]:
    """The paper's scores of the keypoints and matches against the true `H` (image 1 into
    image 2, detection pixels): repeatability, matching score, true matches, their coverage,
    and the nearest-neighbour ratio AUC in the common region."""
    rep = gm.repeatability(f1.xy, f2.xy, H, shape1, shape2, EPS_PX)
    ms = gm.matching_score(f1.xy, f2.xy, xy1_m, xy2_m, H, shape1, shape2, EPS_PX)
    tp = gm.true_positive_mask(xy1_m, xy2_m, H, EPS_PX)
    cover = gm.coverage_fraction(xy1_m[tp], shape1)
    auc = float("nan")
    in1, in2 = gm.common_region(f1.xy, f2.xy, H, shape1, shape2)
    if in1.any() and in2.any():
        nearest, ratio = gm.nearest_neighbour_ratios(
            distance_matrix(f1.descriptors[in1], f2.descriptors[in2])
        )
        correct = gm.true_positive_mask(f1.xy[in1], f2.xy[in2][nearest], H, EPS_PX)
        auc = gm.nndr_auc(ratio, correct)
    return rep, ms, int(tp.sum()), cover, auc


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
        H_gt_full = least_squares_homography(pair.control_points[:, :2], pair.control_points[:, 2:])

    rep = ms = auc = cover = float("nan")
    n_tp = 0
    if H_gt_full is not None:
        H = S2 @ H_gt_full @ np.linalg.inv(S1)
        rep, ms, n_tp, cover, auc = _detection_scores(f1, f2, xy1_m, xy2_m, H, shape1, shape2)

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
    as `mosaic register` does (`pixel_refine.fit_pair`, `config.refine_levels` levels when
    refined; none are run when it is 0), and the control points of image 2 are mapped into
    image 1."""
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
            "keypoints": nanmean((r.n_keypoints_1 + r.n_keypoints_2) / 2 for r in rs),
            "matches": nanmean(r.n_matches for r in rs),
            "true_positives": nanmean(r.n_true_positives for r in rs),
            "repeatability": nanmean(r.repeatability for r in rs),
            "m_score": nanmean(r.matching_score for r in rs),
            "nndr_auc": nanmean(r.nndr_auc for r in rs),
            "coverage": nanmean(r.coverage for r in rs),
        }
        for cls in CLASSES:
            row[f"{cls}_pct"] = 100.0 * float(np.mean(classes == cls))
        stats = gm.class_error_stats(classes, [r.mee_px for r in rs], [r.rmse_px for r in rs])
        for group, values in stats.items():
            for key in ("mee_mean", "mee_std", "rmse_mean", "rmse_std"):
                row[f"{group}_{key}"] = values[key]
        row.update(_fire_scores(errors, [r.category for r in rs]))
        row["time_ms"] = nanmean(r.time_ms for r in rs)
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
    scores["mean_error_px"] = nanmean(errors)
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
            row["s_per_pair"] = nanmean(r.coarse_s + r.variant_s[name] for r in rs)
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


def plot_pairs(
    results: Sequence[PairResult], summary: Sequence[dict[str, Any]], out: Path
) -> list[Path]:
    """cumulative_error.png (fraction of pairs under t, per detector) and success_rates.png."""
    plt = pyplot()
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
    plt = pyplot()
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
    written.append(write_json(out / "summary.json", json_safe(document)))
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
