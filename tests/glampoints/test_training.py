"""Training: reward/mask construction, loss, smoke run, exact resume, export, CLI errors."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from glampoints.detector import GlamPoints
from glampoints.nms import nms
from glampoints.synthetic import fixed_pairs, frame_preprocess
from glampoints.training import (
    TrainConfig,
    TrainingError,
    config_from_dict,
    evaluate_glampoints,
    evaluate_pairs,
    evaluate_sift,
    export_weights,
    glampoints_loss,
    list_images,
    load_base_image,
    load_checkpoint,
    reward_and_mask,
    train,
    validation_pairs,
)
from glampoints.unet import UNet
from mosaic.glampoints_cli import app
from tests.glampoints.conftest import vessel_image


def _peaks_map(shape: tuple[int, int], xy: np.ndarray) -> torch.Tensor:
    s = torch.zeros((1, 1, *shape))  # background at the threshold: never a keypoint
    s[0, 0, xy[:, 1], xy[:, 0]] = torch.linspace(0.9, 0.5, len(xy))
    return s


def test_reward_and_mask_on_identical_images():
    img = vessel_image((96, 96), seed=11)
    rng = np.random.default_rng(0)
    xy = np.stack(np.meshgrid(np.arange(12, 90, 12), np.arange(12, 90, 12)), -1).reshape(-1, 2)
    s = _peaks_map(img.shape, xy)
    scores = torch.cat([s, s])  # images1 then images2
    cfg = TrainConfig("", "", "", nms_window_px=10)
    R, M, stats = reward_and_mask([img], [img], [np.eye(3)], scores, cfg, rng)
    assert stats["n_kp"] == len(xy)
    # identical images, identity H: every cross-checked match is a true positive
    assert stats["n_tp"] == stats["n_match"] > 0.8 * len(xy)
    for k in (0, 1):
        assert R[k].sum() == stats["n_tp"]
        kp = np.zeros(img.shape, bool)
        kp[xy[:, 1], xy[:, 0]] = True
        assert np.all(kp[R[k, 0] > 0])  # rewards only at keypoints
        assert np.all(M[k][R[k] > 0] == 1)
        # more TPs than others: the mask is every keypoint
        assert M[k].sum() == len(xy)
        assert set(zip(*np.nonzero(M[k, 0]), strict=True)) == {(y, x) for x, y in xy.tolist()}


def test_mask_samples_as_many_negatives_as_true_positives():
    img = vessel_image((96, 96), seed=12)
    xy = np.stack(np.meshgrid(np.arange(12, 90, 12), np.arange(12, 90, 12)), -1).reshape(-1, 2)
    # image 2 (same image, identity H) keeps only 10 of the 49 keypoints: 10 TPs
    cfg = TrainConfig("", "", "")
    R, M, stats = reward_and_mask(
        [img],
        [img],
        [np.eye(3)],
        torch.cat([_peaks_map(img.shape, xy), _peaks_map(img.shape, xy[::5])]),
        cfg,
        np.random.default_rng(1),
    )
    assert stats["n_tp"] == 10
    assert R[0].sum() == 10 and R[1].sum() == 10
    # image 1: 10 TPs + 10 of its 39 other keypoints; image 2: its 10 TPs and nothing else
    assert M[0].sum() == 20 and M[1].sum() == 10
    assert np.all(M[0][R[0] > 0] == 1)
    kp1 = np.zeros(img.shape, bool)
    kp1[xy[:, 1], xy[:, 0]] = True
    assert np.all(kp1[M[0, 0] > 0])  # the mined negatives are keypoints


def test_loss_formula_and_gradient():
    torch.manual_seed(0)
    net = UNet()
    img = vessel_image((64, 64), seed=5)
    cfg = TrainConfig("", "", "", nms_window_px=6)
    out = glampoints_loss(net, [img], [img], [np.eye(3)], cfg, np.random.default_rng(0))
    assert set(out) >= {"total", "n_tp", "n_kp", "mined"}
    total = out["total"]
    assert torch.isfinite(total) and 0 < float(total.detach()) < 1
    # recompute with the same reward and mask
    x = torch.from_numpy(np.stack([img, img])).float().div(255)[:, None]
    S = net(x)
    R, M, _ = reward_and_mask([img], [img], [np.eye(3)], S, cfg, np.random.default_rng(0))
    expect = ((S - torch.from_numpy(R)) ** 2 * torch.from_numpy(M)).sum() / M.sum()
    assert float(total.detach()) == pytest.approx(float(expect.detach()), rel=1e-5)
    total.backward()
    assert float(net.head.weight.grad.abs().sum()) > 0


def test_evaluate_pairs_perfect_detector():
    img = vessel_image((128, 128), seed=6)
    H = np.array([[1, 0, 9], [0, 1, -6], [0, 0, 1]], dtype=np.float64)
    img2 = cv2.warpPerspective(img, H, (128, 128))

    def points(images):
        s = torch.stack(
            [torch.from_numpy(cv2.GaussianBlur(i, (0, 0), 2).astype(np.float32)) for i in images]
        )[:, None]
        return [xy.numpy() for xy, _ in nms(s, 8, 0.0)]

    res = evaluate_pairs(points, [(img, img2, H)])
    assert res["repeatability"] > 0.8
    assert res["acceptable"] == 1.0 and res["failed"] == 0.0
    assert res["n_tp"] > 10


def _write_images(folder: Path, n: int, seed: int, shape=(120, 140)) -> None:
    folder.mkdir(parents=True)
    for i in range(n):
        img = vessel_image(shape, seed=seed + i)
        cv2.imwrite(str(folder / f"{i}_a.png"), np.dstack([img // 2, img, img // 3]))


@pytest.fixture
def data(tmp_path) -> tuple[Path, Path]:
    _write_images(tmp_path / "train", 4, 100)
    _write_images(tmp_path / "val", 1, 200)
    return tmp_path / "train", tmp_path / "val"


def _cfg(data, out: Path, **kw) -> TrainConfig:
    base = dict(
        data_dir=str(data[0]),
        val_dir=str(data[1]),
        out_dir=str(out),
        epochs=3,
        batch_size=2,
        crop=64,
        pairs_per_image=1,
        val_pairs_per_image=2,
        val_crop=64,
        num_threads=1,
        checkpoint_every=1,
        nms_window_px=6,
    )
    base.update(kw)
    return TrainConfig(**base)


def test_smoke_run_checkpoint_resume_and_export(tmp_path, data):
    out = tmp_path / "run"
    # 4 images x 1 pair / batch 2 = 2 steps per epoch; 3 steps cross one epoch end
    summary = train(_cfg(data, out, max_steps=3))
    assert summary["step"] == 3 and summary["epoch"] == 1
    last = load_checkpoint(out / "last.pt")
    assert last["step"] == 3 and last["epoch"] == 1 and last["step_in_epoch"] == 1
    assert last["files"] == ["0_a.png", "1_a.png", "2_a.png", "3_a.png"]
    assert isinstance(last["git"], str) and last["git"]
    assert (out / "best.pt").exists()
    lines = (out / "metrics.jsonl").read_text().splitlines()
    assert len(lines) == 1
    rec = json.loads(lines[0])
    assert rec["epoch"] == 1 and np.isfinite(rec["train_loss"]) and rec["train_loss"] > 0
    # the logged validation, recomputed independently: best.pt holds the epoch-1 network
    cfg = _cfg(data, out, max_steps=3)
    pairs = validation_pairs(cfg)
    net = UNet().to(memory_format=torch.channels_last)
    net.load_state_dict(load_checkpoint(out / "best.pt")["model"])
    assert rec["val"] == pytest.approx(evaluate_glampoints(net, pairs, cfg), nan_ok=True)
    assert rec["val_sift"] == pytest.approx(evaluate_sift(pairs, cfg), nan_ok=True)
    assert rec["val"]["pairs"] == len(pairs) == 2  # 1 validation image x 2 pairs
    shares = [rec["val"][k] * len(pairs) for k in ("acceptable", "inaccurate", "failed")]
    assert shares == [round(v) for v in shares] and sum(shares) == len(pairs)

    with pytest.raises(TrainingError, match="--resume"):
        train(_cfg(data, out, max_steps=5))
    summary = train(_cfg(data, out, max_steps=5), resume=True)
    assert summary["step"] == 5
    last = load_checkpoint(out / "last.pt")
    assert last["step"] == 5 and last["epoch"] == 2 and last["step_in_epoch"] == 1
    assert [json.loads(x)["epoch"] for x in (out / "metrics.jsonl").read_text().splitlines()] == [
        1,
        2,
    ]

    dest = tmp_path / "exported.pt"
    export_weights(out / "best.pt", dest)
    assert dest.stat().st_size < 5_000_000
    det = GlamPoints.from_pretrained(dest)
    assert det.meta["trained_epochs"] >= 1
    assert len(det.detect(vessel_image((64, 64), seed=1))) > 0


def test_resume_continues_exactly(tmp_path, data):
    straight = tmp_path / "a"
    train(_cfg(data, straight, max_steps=3, epochs=2))
    split = tmp_path / "b"
    train(_cfg(data, split, max_steps=1, epochs=2))
    train(_cfg(data, split, max_steps=3, epochs=2), resume=True)
    a = load_checkpoint(straight / "last.pt")["model"]
    b = load_checkpoint(split / "last.pt")["model"]
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=1e-6)


def test_training_errors(tmp_path, data):
    with pytest.raises(TrainingError, match="not found"):
        train(_cfg((tmp_path / "nope", data[1]), tmp_path / "o"))
    with pytest.raises(TrainingError, match="checkpoint not found"):
        train(_cfg(data, tmp_path / "o2"), resume=True)
    runner = CliRunner()
    res = runner.invoke(
        app,
        [
            "train",
            "--data",
            str(tmp_path / "nope"),
            "--val",
            str(data[1]),
            "--out",
            str(tmp_path / "o3"),
        ],
    )
    assert res.exit_code == 2 and "image folder not found" in res.stderr
    res = runner.invoke(app, ["export", str(tmp_path / "missing.pt"), "-o", str(tmp_path / "x")])
    assert res.exit_code == 2 and "checkpoint not found" in res.stderr
    assert "Traceback" not in res.output


def test_init_starts_a_new_run_from_given_weights(tmp_path, data):
    first = tmp_path / "first"
    train(_cfg(data, first, max_steps=2))
    start = load_checkpoint(first / "last.pt")["model"]
    # lr 0: the fine-tuning run's weights stay exactly those it was initialised from (only the
    # BatchNorm running statistics move in a training-mode forward)
    tuned = tmp_path / "tuned"
    train(_cfg(data, tuned, max_steps=1, lr=0.0, init=str(first / "last.pt")))
    ckpt = load_checkpoint(tuned / "last.pt")
    for k, _ in UNet().named_parameters():
        torch.testing.assert_close(ckpt["model"][k], start[k], rtol=0, atol=0)
    assert ckpt["config"]["init"] == str(first / "last.pt") and ckpt["step"] == 1
    # a file that is not weights: one clear TrainingError, not a traceback
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(TrainingError, match="--init"):
        train(_cfg(data, tmp_path / "x", max_steps=1, init=str(bad)))


def test_crops_get_the_apps_preprocessing(data):
    cfg = _cfg(data, Path("unused"), preprocess_crops=True)
    pairs = validation_pairs(cfg)
    legacy = validation_pairs(dataclasses.replace(cfg, preprocess_crops=False))
    raw = fixed_pairs(
        [load_base_image(p, True, cfg.max_base_side, clahe=False) for p in list_images(data[1])],
        cfg.seed + 1000,
        cfg.val_pairs_per_image,
        cfg.val_crop,
    )
    for (a, b, H), (ra, rb, rH) in zip(pairs, raw, strict=True):
        np.testing.assert_array_equal(H, rH)
        np.testing.assert_array_equal(a, frame_preprocess(ra))
        np.testing.assert_array_equal(b, frame_preprocess(rb))
    # the default mode equalises the base image instead: different crops
    firsts = zip([p[0] for p in pairs], [p[0] for p in legacy], strict=True)
    assert any(not np.array_equal(a, la) for a, la in firsts)


def test_checkpoints_from_before_crop_preprocessing_keep_their_mode():
    old = config_from_dict({"data_dir": "a", "val_dir": "b", "out_dir": "c", "betas": [0.9, 0.99]})
    assert old.preprocess_crops is False and old.init == "" and old.betas == (0.9, 0.99)
