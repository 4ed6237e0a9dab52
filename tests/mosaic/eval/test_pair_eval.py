"""Pair evaluation (`glampoints evaluate`) end to end, against fixtures whose ground truth
is known: the paper's metrics, the FIRE protocol and the scoring of `mosaic register` answers."""

from __future__ import annotations

import csv
import json
import math

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from glampoints.metrics import point_errors
from mosaic.cli import app as mosaic_app
from mosaic.config import Config
from mosaic.errors import InputError
from mosaic.eval.common import make_extractors
from mosaic.eval.datasets import Pair
from mosaic.eval.pair_eval import FIRE_VARIANTS, evaluate_pair, read_answers, score_answers
from mosaic.glampoints_cli import app as glampoints_app
from mosaic.io import sample_image_path
from mosaic.preprocess import scale_matrix
from mosaic.synthetic.curved import write_fire_folder
from tests.mosaic.eval.test_datasets import make_fire_fixture

runner = CliRunner()


def test_scale_matrix_maps_pixel_centres():
    S = scale_matrix((100, 200), (50, 100))  # half size: pixel centres 0, 1 -> -0.25, 0.25
    np.testing.assert_allclose(S @ [0, 0, 1], [-0.25, -0.25, 1])
    np.testing.assert_allclose(S @ [199, 99, 1], [99.25, 49.25, 1])


def test_identity_pair_scores_perfectly(fundus):
    image = fundus[500:700, 500:740]
    pair = Pair("same", "", image, image.copy(), np.eye(3))
    config, extractor = make_extractors(Config(), ["sift"])["sift"]
    result = evaluate_pair(pair, config, extractor)
    assert result.repeatability == 1.0
    assert result.n_true_positives == result.n_matches > 100
    assert result.matching_score >= 0.95
    assert result.status == "acceptable"
    assert result.mee_px < 1e-3 and result.error_px < 1e-3
    assert result.coverage > 0.9


def test_fire_layout_end_to_end(tmp_path, fundus):
    """`glampoints evaluate` on a FIRE-layout fixture: two good pairs, one that must fail."""
    truth = make_fire_fixture(tmp_path / "FIRE", fundus)
    out = tmp_path / "out"
    args = ["evaluate", str(tmp_path / "FIRE"), "--format", "fire", "--detector", "sift,orb"]
    result = runner.invoke(glampoints_app, [*args, "--scale", "0.5", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "AUC S" in result.output and "sift" in result.output
    for name in ("summary.csv", "pairs.csv", "summary.json", "cumulative_error.png"):
        assert (out / name).stat().st_size > 0
    assert (out / "success_rates.png").read_bytes()[:4] == b"\x89PNG"

    document = json.loads((out / "summary.json").read_text())
    assert document["meta"]["scale"] == 0.5
    summary = {row["detector"]: row for row in document["summary"]}
    sift = summary["sift"]
    assert sift["failed_pct"] == pytest.approx(100 / 3)  # A01: featureless second image
    assert sift["acceptable_pct"] == pytest.approx(200 / 3)
    assert sift["auc_A"] == 0.0
    assert sift["auc_S"] >= 0.9 and sift["auc_P"] >= 0.9
    assert sift["mauc"] == pytest.approx((sift["auc_S"] + sift["auc_P"]) / 3)
    # repeatability measured 0.498 (0.5+ before the 12 px border margin dropped more points)
    assert sift["repeatability"] > 0.45 and sift["coverage"] > 0.3

    # each pair's FIRE error is the control points' error of its homography, at full resolution
    for row in document["pairs"]:
        points = truth[row["pair"]]
        if row["status"] == "failed":
            assert row["error_px"] == "inf" and row["H_est_1_to_2"] is None
            continue
        H_2_to_1 = np.linalg.inv(np.array(row["H_est_1_to_2"]))
        errors = point_errors(H_2_to_1, points[:, 2:], points[:, :2])
        assert row["error_px"] == pytest.approx(errors.mean(), abs=1e-3)  # files: 4 decimals
        if row["detector"] == "sift":
            assert row["error_px"] < 2.0  # px at full resolution (320 px images)
    with (out / "pairs.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 6 and {r["detector"] for r in rows} == {"sift", "orb"}


def test_fire_table_on_curved_pairs_ranks_the_models_against_the_truth(tmp_path):
    """`glampoints evaluate --format fire` on two curved pairs (exact control points) at the
    paper's scale: one row per detector and model, the same matches fitted four ways."""
    write_fire_folder([sample_image_path()], tmp_path / "curved", 2, seed=0, size=1024)
    out = tmp_path / "out"
    args = ["evaluate", str(tmp_path / "curved"), "--format", "fire", "--detector", "sift"]
    result = runner.invoke(glampoints_app, [*args, "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "FIRE protocol per model" in result.output and "quad+refine" in result.output

    document = json.loads((out / "summary.json").read_text())
    assert document["meta"]["scale"] == 0.15
    models = {row["model"]: row for row in document["models"]}
    assert list(models) == list(FIRE_VARIANTS)
    hom, quad, best = models["hom"], models["quad"], models["quad+refine"]
    assert all(row["failed"] == 0 and row["pairs"] == 2 for row in models.values())
    # the curvature limits the homography to ~2 px at 1024 px; the quadratic removes it and
    # the refinement lowers its error again
    assert best["auc"] > hom["auc"] and best["auc_0_25"] > hom["auc_0_25"]
    assert hom["mean_error_px"] > 1.5 and best["mean_error_px"] < hom["mean_error_px"] / 5
    assert best["mean_error_px"] < quad["mean_error_px"] / 2 and best["mean_error_px"] < 0.4
    assert all(row["s_per_pair"] > 0 for row in models.values())
    with (out / "models.csv").open() as fh:
        assert [r["model"] for r in csv.DictReader(fh)] == list(FIRE_VARIANTS)
    assert (out / "cumulative_error_models.png").read_bytes()[:4] == b"\x89PNG"
    with (out / "pairs.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    errors = [float(r["error_px_quad+refine"]) for r in rows]
    assert np.mean(errors) == pytest.approx(best["mean_error_px"], rel=1e-3)


def test_hpatches_style_pair_uses_six_fixed_points(fundus):
    image = fundus[450:650, 450:690]
    H = np.array([[1.0, 0.02, 5.0], [-0.02, 1.0, -3.0], [0.0, 0.0, 1.0]])
    warped = cv2.warpPerspective(image, H, (image.shape[1], image.shape[0]))
    config, extractor = make_extractors(Config(), ["sift"])["sift"]
    result = evaluate_pair(Pair("h", "v", image, warped, H), config, extractor)
    assert result.status == "acceptable"
    assert result.mee_px < 1.0 and result.rmse_px < 1.0
    # full and detection resolution are the same at scale 1
    assert result.error_px == pytest.approx(result.rmse_px, abs=0.5)


def _answer(name: str, model: str, H: np.ndarray, Q: np.ndarray | None = None) -> dict:
    return {
        "fixed": f"Images/{name}_1.jpg",
        "moving": f"Images/{name}_2.jpg",
        "status": "registered",
        "model": model,
        "H_moving_to_fixed": H.tolist(),
        "Q_moving_to_fixed": None if Q is None else Q.tolist(),
    }


def test_score_answers_applies_the_fire_protocol_to_register_answers(tmp_path):
    """Known answers on a FIRE folder whose truth is a shift of (10, -5): the exact answer
    scores 0 px, an answer 3-4-5 off scores 5 px, a pair without an answer is a miss."""
    root = tmp_path / "FIRE"
    (root / "Images").mkdir(parents=True)
    (root / "Ground Truth").mkdir()
    xy2 = np.random.default_rng(0).uniform(0, 300, (10, 2))
    for name in ("S01", "P01", "A01"):
        points = np.hstack([xy2 + np.array([10.0, -5.0]), xy2])
        np.savetxt(root / "Ground Truth" / f"control_points_{name}_1_2.txt", points)
    shift = np.array([[1.0, 0, 10], [0, 1, -5], [0, 0, 1]])
    Q_off = np.array([[0, 0, 0, 1.0, 0, 13], [0, 0, 0, 0, 1.0, -1]])  # (3, 4) off
    H_off = shift + np.array([[0, 0, 6], [0, 0, 8], [0, 0, 0]])  # (6, 8) off
    answers = [_answer("S01", "homography", shift), _answer("P01", "quadratic", H_off, Q_off)]
    path = tmp_path / "answers.jsonl"
    path.write_text("".join(json.dumps(a) + "\n" for a in answers))
    rows, summary = score_answers(root, read_answers(path))
    assert [(r["pair"], r["category"], r["status"]) for r in rows] == [
        ("A01", "A", "no answer"),
        ("P01", "P", "registered"),
        ("S01", "S", "registered"),
    ]
    np.testing.assert_allclose([r["answer_error_px"] for r in rows], [math.inf, 5, 0], atol=1e-9)
    np.testing.assert_allclose([r["H_error_px"] for r in rows], [math.inf, 10, 0], atol=1e-9)
    answer, homography = summary
    assert answer["failed"] == homography["failed"] == 1
    # AUC 1-25: 0 px is under all 25 thresholds, 5 px under 20 (t = 6..25), 10 px under 15
    assert answer["auc"] == pytest.approx((25 + 20) / 75)
    assert homography["auc"] == pytest.approx((25 + 15) / 75)
    assert (answer["auc_S"], answer["auc_P"], answer["auc_A"]) == (1.0, 0.8, 0.0)
    assert answer["mauc"] == pytest.approx(0.6)
    assert answer["mean_error_px"] == pytest.approx(2.5)  # of the pairs answered
    path.write_text("not json\n")
    with pytest.raises(InputError, match="line 1 is not JSON"):
        read_answers(path)


def test_register_answers_scored_by_glampoints_evaluate(tmp_path, fundus):
    """`mosaic register --pairs` on a FIRE folder, then `glampoints evaluate --answers`: the
    pairs with retina score within 2 px of the truth, the featureless one is a miss."""
    root = tmp_path / "FIRE"
    make_fire_fixture(root, fundus)
    names = ("S01", "P01", "A01")
    (root / "pairs.csv").write_text(
        "fixed,moving\n" + "".join(f"Images/{n}_1.jpg,Images/{n}_2.jpg\n" for n in names)
    )
    result = runner.invoke(
        mosaic_app, ["register", "--pairs", str(root / "pairs.csv"), "--detector", "sift"]
    )
    assert result.exit_code == 1  # A01 fails
    (tmp_path / "answers.jsonl").write_text(result.stdout)
    out = tmp_path / "scored"
    args = ["evaluate", str(root), "--answers", str(tmp_path / "answers.jsonl"), "--out", str(out)]
    result = runner.invoke(glampoints_app, args)
    assert result.exit_code == 0, result.output
    assert "H_moving_to_fixed" in result.stdout
    with (out / "answers_pairs.csv").open() as fh:
        rows = {r["pair"]: r for r in csv.DictReader(fh)}
    for name in ("S01", "P01"):
        assert rows[name]["status"] == "registered"
        assert float(rows[name]["answer_error_px"]) < 2.0
    assert rows["A01"]["status"] == "failed" and rows["A01"]["answer_error_px"] == "inf"
    with (out / "answers.csv").open() as fh:
        answer = next(csv.DictReader(fh))
    assert answer["failed"] == "1" and float(answer["auc"]) > 0.6
    # an answers file that is not one: one clear line, no traceback
    (tmp_path / "bad.jsonl").write_text('{"a": 1}\n')
    result = runner.invoke(
        glampoints_app, ["evaluate", str(root), "--answers", str(tmp_path / "bad.jsonl")]
    )
    assert result.exit_code == 2 and "not a `mosaic register --pairs` answer" in result.output
    assert "Traceback" not in result.output
