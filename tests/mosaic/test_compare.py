"""`mosaic compare` against synthetic truth: follow-up visits of the shipped photograph with
planted changes (`mosaic.synthetic.followup`), as photographs with a known eye turn and as
videos built into mosaics; unrelated eyes and visits without overlap refused."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from mosaic.cli import app
from mosaic.compare import (
    CHANGE_SIGMAS,
    MIN_CORRELATION,
    NotComparableError,
    Visit,
    compare_visits,
    covered_area,
    run_compare,
)
from mosaic.config import Config
from mosaic.features import FeatureExtractor
from mosaic.pixel_refine import fixed_to_moving_map
from mosaic.registration import apply_homography
from mosaic.synthetic.followup import MIN_CHANGE_PX, Change, plant_changes, source_to_mosaic
from tests.conftest import SAMPLE_IMAGE, SHARED_DATA

runner = CliRunner()
HALF = np.diag([0.5, 0.5, 1.0])  # photographs compared at half the source's 1411 px
MAX_ERROR_PX = 2.0  # the criterion: mean over the overlap
MAX_FALSE_REGIONS = 1  # the criterion, per pair


@pytest.fixture(scope="module")
def source() -> np.ndarray:
    return cv2.imread(str(SAMPLE_IMAGE), cv2.IMREAD_COLOR)


@pytest.fixture(scope="module")
def extractor() -> FeatureExtractor:
    return FeatureExtractor(Config().features)


def _photo(name: str, image: np.ndarray) -> Visit:
    return Visit(name, Path(name), "photograph", image, covered_area(image))


def _eye_turn(rng: np.random.Generator, size: int) -> np.ndarray:
    """`H_source_to_followup`: the eye turned up to 10 degrees, shifted up to 60 px, scaled by
    0.9-1.1 about the centre, with a little perspective."""
    a, k = np.deg2rad(rng.uniform(-10, 10)), rng.uniform(0.9, 1.1)
    c = np.array([(size - 1) / 2] * 2)
    H = np.eye(3)
    H[:2, :2] = k * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    H[:2, 2] = c + rng.uniform(-60, 60, 2) - H[:2, :2] @ c
    H[2, :2] = rng.uniform(-2e-5, 2e-5, 2)
    return H


def followup_photograph(
    source: np.ndarray, seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[Change]]:
    """(baseline, follow-up, H_followup_to_baseline, changes in baseline px): the source at half
    size, and the changed source seen after an eye turn, at half size, another visit's
    light (gain 1.1, gamma 0.85), focus (blur sigma 0.8 source px) and noise (sigma 3)."""
    rng = np.random.default_rng(seed)
    changed, changes = plant_changes(source, None, rng)
    n = source.shape[1]
    H_source_to_followup = _eye_turn(rng, n)
    half = (round(n / 2), round(source.shape[0] / 2))
    base = cv2.resize(source, half, interpolation=cv2.INTER_AREA)
    turned = cv2.warpPerspective(changed, H_source_to_followup, (n, source.shape[0]))
    follow = cv2.GaussianBlur(turned.astype(np.float32), (0, 0), 0.8)
    follow = cv2.resize(follow, half, interpolation=cv2.INTER_AREA)
    follow = 255 * (np.clip(follow * 1.1, 0, 255) / 255) ** 0.85 + rng.normal(0, 3, follow.shape)
    follow = np.clip(follow + 0.5, 0, 255).astype(np.uint8)
    H_followup_to_baseline = HALF @ np.linalg.inv(H_source_to_followup) @ np.linalg.inv(HALF)
    in_base = [Change(c.kind, tuple(v / 2 for v in c.bbox)) for c in changes]
    return base, follow, H_followup_to_baseline, in_base


def alignment_error(comparison, H_followup_to_baseline: np.ndarray) -> float:
    """Mean distance (px) over the overlap between where the answer and the truth put each
    baseline pixel in the follow-up."""
    ys, xs = np.nonzero(comparison.overlap)
    map_x, map_y = fixed_to_moving_map(
        comparison.H_followup_to_baseline,
        comparison.Q_followup_to_baseline,
        comparison.overlap.shape,
    )
    answer = np.column_stack([map_x[ys, xs], map_y[ys, xs]])
    truth = apply_homography(
        np.linalg.inv(H_followup_to_baseline), np.column_stack([xs, ys]).astype(float)
    )
    return float(np.linalg.norm(answer - truth, axis=1).mean())


def _meets(a: tuple, b: tuple) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def found_and_false(regions, changes: list[Change]) -> tuple[list[str], int]:
    """The kinds of the changes some region overlaps, and the regions that overlap none."""
    found = [c.kind for c in changes if any(_meets(r.bbox, c.bbox) for r in regions)]
    false = sum(not any(_meets(r.bbox, c.bbox) for c in changes) for r in regions)
    return found, false


def test_planted_changes_are_where_the_truth_says(source):
    changed, changes = plant_changes(source, None, np.random.default_rng(3))
    assert [c.kind for c in changes] == ["haemorrhage", "narrowed_vessel", "laser_scars"]
    differs = np.abs(changed.astype(int) - source.astype(int)).max(axis=2) > 2
    inside = np.zeros_like(differs)
    for c in changes:
        x0, y0, x1, y1 = c.bbox
        assert x1 - x0 >= MIN_CHANGE_PX and y1 - y0 >= MIN_CHANGE_PX
        inside[int(y0) : int(np.ceil(y1)) + 1, int(x0) : int(np.ceil(x1)) + 1] = True
        assert differs[int(y0) : int(y1), int(x0) : int(x1)].sum() >= MIN_CHANGE_PX**2
    assert not (differs & ~inside).any()  # nothing changed outside the truth's boxes
    for a in changes:  # apart
        assert not any(_meets(a.bbox, b.bbox) for b in changes if b is not a)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_followup_photograph_aligned_and_changes_found(source, extractor, seed):
    base, follow, H_truth, changes = followup_photograph(source, seed)
    comparison = compare_visits(
        _photo("baseline", base), _photo("followup", follow), Config(), extractor
    )
    assert alignment_error(comparison, H_truth) < MAX_ERROR_PX
    found, false = found_and_false(comparison.regions, changes)
    assert found == [c.kind for c in changes]
    assert false <= MAX_FALSE_REGIONS
    assert comparison.correlation > MIN_CORRELATION
    assert all(r.mean_change > CHANGE_SIGMAS for r in comparison.regions)


def test_same_photograph_twice_has_no_change(source, extractor):
    base = cv2.resize(source, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    comparison = compare_visits(_photo("baseline", base), _photo("followup", base), Config(),
                                extractor)  # fmt: skip
    assert alignment_error(comparison, np.eye(3)) < 0.5
    assert comparison.regions == []


def _refused(baseline: np.ndarray, followup: np.ndarray, extractor) -> str:
    with pytest.raises(NotComparableError) as caught:
        compare_visits(_photo("baseline", baseline), _photo("followup", followup), Config(),
                       extractor)  # fmt: skip
    return str(caught.value)


def test_mirrored_eye_is_refused(source, extractor):
    """The other eye looks like this one mirrored: vessels that branch the other way."""
    base = cv2.resize(source, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    message = _refused(base, np.ascontiguousarray(base[:, ::-1]), extractor)
    assert "\n" not in message


def test_visits_without_overlap_are_refused(source, extractor):
    base = cv2.resize(source, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    w = base.shape[1]
    left, right = base.copy(), base.copy()
    left[:, w * 2 // 5 :] = 0  # each visit sees its own side of the retina
    right[:, : w * 3 // 5] = 0
    _refused(left, right, extractor)


def test_unrelated_eyes_from_shared_data_are_refused(extractor):
    folder = SHARED_DATA / "retina" / "train" / "lmc"
    if not folder.is_dir():
        pytest.skip("../shared/data/retina/train/lmc is not here")
    images = [folder / "100_a.jpg", folder / "101_a.jpg"]  # two eyes (some numbers are one)
    one, other = (cv2.resize(cv2.imread(str(p)), (640, 480)) for p in images)
    _refused(one, other, extractor)


@pytest.mark.slow
def test_followup_video_on_baseline_video(tmp_path):
    """Two synthetic videos of one eye (the follow-up with planted changes, `synth
    --followup-of`), each built into its mosaic by `compare`: the mosaic-to-mosaic transform
    within 2 px of the truth over the overlap, every change found, at most one false region;
    and the baseline's mosaic against the source photograph aligned as well."""
    base, follow = tmp_path / "base.mp4", tmp_path / "follow.mp4"
    for args in (["-o", str(base), "--seed", "0"],
                 ["-o", str(follow), "--seed", "1", "--followup-of", str(base)]):  # fmt: skip
        result = runner.invoke(app, ["synth", *args, "--frames", "30", "--size", "480x320"])
        assert result.exit_code == 0, result.output
    out = tmp_path / "cmp"
    comparison, written = run_compare(base, follow, out, Config())
    reports = [json.loads((out / f"{n}_mosaic.json").read_text()) for n in ("baseline", "followup")]
    truths = [json.loads(p.with_suffix(".gt.json").read_text()) for p in (base, follow)]
    S_base, S_follow = (source_to_mosaic(r, g) for r, g in zip(reports, truths, strict=True))
    H_truth = S_base @ np.linalg.inv(S_follow)
    assert alignment_error(comparison, H_truth) < MAX_ERROR_PX
    changes = [
        Change(c["kind"], tuple(_box(S_base, c["bbox_source"])))
        for c in truths[1]["followup"]["changes"]
    ]
    found, false = found_and_false(comparison.regions, changes)
    assert found == [c.kind for c in changes]
    assert false <= MAX_FALSE_REGIONS
    assert written["status"] == "registered"
    assert {p.name for p in out.iterdir()} >= {"compare.json", *written["pictures"]}

    # the baseline's mosaic as written (its report beside it) against the source photograph:
    # a mosaic and a photograph, met at one scale by `compare`; the truth is S_base itself
    mosaic = out / "baseline_mosaic.png"
    against_photo, _ = run_compare(mosaic, SAMPLE_IMAGE, tmp_path / "photo", Config())
    assert alignment_error(against_photo, S_base) < MAX_ERROR_PX
    assert json.loads((tmp_path / "photo" / "compare.json").read_text())["baseline"]["kind"] == (
        "mosaic"
    )


def _box(H: np.ndarray, bbox: list[float]) -> list[float]:
    x0, y0, x1, y1 = bbox
    q = apply_homography(H, np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], float))
    return [q[:, 0].min(), q[:, 1].min(), q[:, 0].max(), q[:, 1].max()]


def _compare(folder: Path, baseline: str, followup: str, out: str):
    args = [str(folder / baseline), str(folder / followup), "-o", str(folder / out)]
    return runner.invoke(app, ["compare", *args])


@pytest.mark.slow
def test_cli_compare_writes_pictures_and_refuses_in_one_line(tmp_path, source):
    base = cv2.resize(source, None, fx=0.4, fy=0.4, interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(tmp_path / "base.png"), base)
    cv2.imwrite(str(tmp_path / "same.png"), base)
    cv2.imwrite(str(tmp_path / "mirror.png"), np.ascontiguousarray(base[:, ::-1]))
    result = _compare(tmp_path, "base.png", "same.png", "ok")
    assert result.exit_code == 0, result.output
    written = json.loads((tmp_path / "ok" / "compare.json").read_text())
    assert np.allclose(written["H_followup_to_baseline"], np.eye(3), atol=1e-2)
    assert written["regions"] == [] and written["baseline"]["kind"] == "photograph"
    for name in written["pictures"]:
        assert cv2.imread(str(tmp_path / "ok" / name)).shape[:2] == base.shape[:2]
    result = _compare(tmp_path, "base.png", "mirror.png", "no")
    assert result.exit_code == 1
    assert "Traceback" not in result.output and len(result.output.strip().splitlines()) == 1
    assert json.loads((tmp_path / "no" / "compare.json").read_text())["status"] == "refused"
    result = _compare(tmp_path, "nothing.png", "same.png", "x")
    assert result.exit_code == 2 and "not found" in result.output


@pytest.mark.slow
def test_manifest_compares_each_patients_visits_onto_the_first(tmp_path, source):
    """`compare --manifest`: per patient, later visits onto the earliest (visits ordered by
    their labels, not by the rows); a refused visit is its row's status, exit 1."""
    base, follow, _, changes = followup_photograph(source, 0)
    for name, image in (("base.png", base), ("follow.png", follow),
                        ("mirror.png", np.ascontiguousarray(base[:, ::-1]))):  # fmt: skip
        cv2.imwrite(str(tmp_path / name), image)
    (tmp_path / "visits.csv").write_text(
        "patient,visit,path\n"
        "anna OD,2025-06-01,follow.png\n"
        "anna OD,2024-11-20,base.png\n"
        "anna OD,2026-01-10,mirror.png\n"
        "ben OS,2025-01-01,base.png\n"
    )
    out = tmp_path / "out"
    result = runner.invoke(app, ["compare", "--manifest", str(tmp_path / "visits.csv"),
                                 "-o", str(out)])  # fmt: skip
    assert result.exit_code == 1, result.output
    summary = json.loads((out / "summary.json").read_text())
    anna = summary["patients"]["anna OD"]
    assert anna["baseline"] == "2024-11-20"
    assert [(r["visit"], r["status"]) for r in anna["visits"]] == [
        ("2025-06-01", "registered"), ("2026-01-10", "refused")]  # fmt: skip
    assert anna["visits"][0]["regions"] >= len(changes) - 1  # two may share one region
    assert summary["patients"]["ben OS"]["visits"] == []
    page = (out / "index.html").read_text()
    for src in re.findall(r"src='([^']+)'", page):
        assert (out / src).is_file(), src
    assert "refused" in page


@pytest.mark.slow
def test_mosaics_at_different_magnifications(source, extractor):
    """Two mosaics of one retina whose videos magnified it 2.3x apart (the central 60 % of the
    photograph, at 0.35 and 0.8 of its size): found by shrinking one against the other."""
    n = source.shape[0]
    crop = source[int(0.2 * n) : int(0.8 * n), int(0.2 * n) : int(0.8 * n)]
    views, S = [], []
    for k in (0.35, 0.8):
        views.append(cv2.resize(crop, None, fx=k, fy=k, interpolation=cv2.INTER_AREA))
        S.append(np.diag([k, k, 1.0]))
    visits = [Visit(name, Path(name), "mosaic", v, covered_area(v))
              for name, v in zip(("baseline", "followup"), views, strict=True)]  # fmt: skip
    comparison = compare_visits(*visits, Config(), extractor)
    H_truth = _pixel_scale_truth(0.35) @ np.linalg.inv(_pixel_scale_truth(0.8))
    assert alignment_error(comparison, H_truth) < MAX_ERROR_PX
    assert comparison.regions == []


def _pixel_scale_truth(k: float) -> np.ndarray:
    """The map of pixels into an image resized by k (`cv2.resize`: pixel centres)."""
    return np.array([[k, 0, 0.5 * k - 0.5], [0, k, 0.5 * k - 0.5], [0, 0, 1.0]])
