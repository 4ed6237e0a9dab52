"""GlamPoints detector: BN folding, fast inference equals the network, mask, weights files."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn
from typer.testing import CliRunner

from glampoints.cli import app
from glampoints.detector import (
    DEFAULT_WEIGHTS,
    GlamPoints,
    Keypoints,
    WeightsError,
    fold_batchnorm,
    load_weights,
    save_weights,
)
from glampoints.unet import UNet
from tests.glampoints.conftest import randomise_batchnorm, vessel_image


@pytest.fixture
def detector() -> GlamPoints:
    torch.manual_seed(0)
    det = GlamPoints()
    randomise_batchnorm(det.net)
    det.invalidate()
    return det


def _reference(net: nn.Module, image: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        x = torch.from_numpy(image).float().div(255)[None, None]
        return net.eval()(x)[0, 0].numpy()


def test_batchnorm_folding_gives_the_same_scores():
    torch.manual_seed(1)
    net = randomise_batchnorm(UNet())
    fused = fold_batchnorm(net)
    assert not any(isinstance(m, nn.BatchNorm2d) for m in fused.modules())
    x = torch.rand(2, 1, 48, 64)
    with torch.no_grad():
        diff = (fused(x) - net(x)).abs().max().item()
    assert diff < 1e-4
    assert any(isinstance(m, nn.BatchNorm2d) for m in net.modules())  # original untouched


def test_score_map_equals_the_unfused_network(detector, texture):
    s = detector.score_map(texture)
    assert s.shape == texture.shape and s.dtype == np.float32
    assert np.abs(s - _reference(detector.net, texture)).max() < 1e-4
    # the traced graph is reused for another size
    other = texture[:70, :91].copy()
    assert np.abs(detector.score_map(other) - _reference(detector.net, other)).max() < 1e-4


def test_bfloat16_precision_is_close(detector, texture):
    fast = GlamPoints(precision="bfloat16")
    fast.load_state_dict(detector.net.state_dict())
    assert np.abs(fast.score_map(texture) - detector.score_map(texture)).max() < 0.02


def test_detect_matches_nms_of_the_score_map_and_respects_mask(detector, texture):
    kps = detector.detect(texture)
    assert isinstance(kps, Keypoints) and len(kps) > 20
    assert kps.xy.dtype == np.float32 and kps.scores.dtype == np.float32
    assert np.all(np.diff(kps.scores) <= 0)
    s = detector.score_map(texture)
    # keypoints are sub-pixel refinements (at most 0.5 px) of the NMS maxima of the score map
    pix = np.rint(kps.xy).astype(int)
    assert np.abs(kps.xy - pix).max() <= 0.5
    np.testing.assert_allclose(kps.scores, s[pix[:, 1], pix[:, 0]])

    mask = np.zeros_like(texture)
    mask[:, :100] = 255
    masked = detector.detect(texture, mask)
    assert len(masked) > 0 and np.all(masked.xy[:, 0] < 100)
    # points well inside the mask are unaffected by masking
    far = kps.xy[:, 0] < 90
    inner = masked.xy[masked.xy[:, 0] < 90]
    assert {tuple(p) for p in kps.xy[far]} == {tuple(p) for p in inner}

    capped = GlamPoints(max_keypoints=5)
    capped.load_state_dict(detector.net.state_dict())
    top = capped.detect(texture, mask)
    np.testing.assert_array_equal(top.xy, masked.xy[:5])


def test_detect_rejects_bad_input(detector):
    with pytest.raises(ValueError, match="uint8"):
        detector.detect(np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(ValueError, match="mask"):
        detector.detect(np.zeros((32, 32), np.uint8), np.ones((16, 16), np.uint8))


def test_weights_round_trip(tmp_path, detector, texture):
    path = tmp_path / "w.pt"
    save_weights(detector.net.state_dict(), path, {"epochs": 3})
    assert path.stat().st_size < 5_000_000
    loaded = GlamPoints.from_pretrained(path)
    assert loaded.meta == {"epochs": 3}
    np.testing.assert_array_equal(loaded.score_map(texture), detector.score_map(texture))
    state, _ = load_weights(path)
    assert set(state) == set(detector.net.state_dict())


def test_bad_weights_raise_weights_error(tmp_path):
    missing = tmp_path / "nope.pt"
    with pytest.raises(WeightsError, match="not found") as e:
        GlamPoints.from_pretrained(missing)
    assert str(missing) in str(e.value) and "\n" not in str(e.value)

    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"\x00garbage" * 100)
    with pytest.raises(WeightsError, match="cannot read") as e:
        GlamPoints.from_pretrained(corrupt)
    assert str(corrupt) in str(e.value) and "\n" not in str(e.value)

    wrong = tmp_path / "wrong.pt"
    state = UNet().state_dict()
    state.pop("head.weight")
    save_weights(state, wrong)
    with pytest.raises(WeightsError, match="do not fit") as e:
        GlamPoints.from_pretrained(wrong)
    assert "\n" not in str(e.value)

    other = tmp_path / "other.pt"
    torch.save({"foo": 1}, other)
    with pytest.raises(WeightsError, match="not a GLAMpoints weights file"):
        GlamPoints.from_pretrained(other)
    assert issubclass(WeightsError, ValueError)


@pytest.mark.skipif(not DEFAULT_WEIGHTS.exists(), reason="no shipped weights yet")
def test_shipped_weights_detect_vessel_keypoints():
    det = GlamPoints.from_pretrained(max_keypoints=300)
    img = vessel_image((240, 320), seed=9)
    kps = det.detect(img)
    assert 50 <= len(kps) <= 300


def test_cli_detect(tmp_path, detector):
    import cv2

    weights = tmp_path / "w.pt"
    save_weights(detector.net.state_dict(), weights)
    img_path = tmp_path / "img.png"
    cv2.imwrite(str(img_path), vessel_image((96, 128), seed=4))
    runner = CliRunner()
    out_png = tmp_path / "kp.png"
    res = runner.invoke(
        app,
        [
            "detect",
            str(img_path),
            "-o",
            str(out_png),
            "--weights",
            str(weights),
            "--json",
            "--max-keypoints",
            "7",
        ],
    )
    assert res.exit_code == 0, res.output
    import json

    data = json.loads(res.stdout)
    assert len(data["xy"]) == 7 and len(data["scores"]) == 7
    assert cv2.imread(str(out_png)).shape == (96, 128, 3)

    res = runner.invoke(app, ["detect", str(tmp_path / "missing.png")])
    assert res.exit_code == 2 and "cannot read image" in res.stderr
    assert res.stderr.strip().count("\n") == 0
    bad = tmp_path / "bad.pt"
    bad.write_text("not torch")
    res = runner.invoke(app, ["detect", str(img_path), "--weights", str(bad)])
    assert res.exit_code == 2 and str(bad) in res.stderr and "Traceback" not in res.output
