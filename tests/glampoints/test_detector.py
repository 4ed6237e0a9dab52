"""GlamPoints detector: BN folding, fast inference equals the network, NMS fast path, mask,
sub-pixel refinement, weights files, benchmark."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn
from typer.testing import CliRunner

from glampoints import detector as detector_module
from glampoints.detector import (
    DEFAULT_WEIGHTS,
    GlamPoints,
    Keypoints,
    WeightsError,
    benchmark,
    fold_batchnorm,
    load_weights,
    onednn_fusion_available,
    save_weights,
)
from glampoints.nms import nms, nms_numpy, refine_subpixel
from glampoints.unet import UNet
from mosaic.glampoints_cli import app
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


BACKENDS = ["eager"] + (["onednn"] if onednn_fusion_available() else [])
needs_onednn = pytest.mark.skipif(not onednn_fusion_available(), reason="no oneDNN fused ops")


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("shape", [(77, 123), (123, 77), (16, 16), (5, 37), (48, 64)])
def test_inference_paths_equal_the_plain_network_on_any_size(detector, backend, shape):
    detector.backend = backend
    detector.invalidate()
    rng = np.random.default_rng(shape[0] * 1000 + shape[1])
    image = (rng.random(shape) * 255).astype(np.uint8)
    s = detector.score_map(image)
    assert detector.inference_path == backend
    assert s.shape == shape and s.dtype == np.float32
    assert np.abs(s - _reference(detector.net, image)).max() < 1e-4


def test_default_cpu_path_is_the_fused_one_when_available(detector, texture):
    detector.score_map(texture)
    assert detector.inference_path == ("onednn" if onednn_fusion_available() else "eager")
    detector.backend = "bogus"
    detector.invalidate()
    with pytest.raises(ValueError, match="backend"):
        detector.score_map(texture)


@needs_onednn
def test_pair_space_convolutions_equal_3x3_convolutions_with_zero_padding():
    # even -> odd -> even pair-space chain == two 3x3 convs (+ReLU); non-zero biases make the
    # zeroed outside pixels matter
    torch.manual_seed(3)
    a, b = nn.Conv2d(3, 8, 3, padding=1), nn.Conv2d(8, 8, 3, padding=1)
    x = torch.rand(1, 3, 9, 14).contiguous(memory_format=torch.channels_last)
    with torch.inference_mode():
        ref = torch.relu(b(torch.relu(a(x))))
        pa = detector_module._PairConv(a.weight, a.bias, to_odd=True)
        pb = detector_module._PairConv(b.weight, b.bias, to_odd=False)
        odd = pa(detector_module._pairs(x))
        assert odd.shape == (1, 16, 9, 8)  # pixels -1 .. 14
        out = detector_module._unpairs(pb(odd))
    assert out.shape == ref.shape
    assert (out - ref).abs().max().item() < 1e-5


@needs_onednn
@pytest.mark.parametrize("fails_at", ["build", "call"])
def test_fused_path_falls_back_to_eager_when_onednn_fails(
    detector, texture, monkeypatch, caplog, fails_at
):
    working = detector_module._OneDnnUNet.__call__

    def broken(self, x):
        if fails_at == "build" or x.shape[-1] > 48:  # the build check runs a 32x48 input
            raise RuntimeError("could not create a primitive descriptor")
        return working(self, x)

    monkeypatch.setattr(detector_module._OneDnnUNet, "__call__", broken)
    with caplog.at_level("WARNING", logger="glampoints.detector"):
        s = detector.score_map(texture)
    assert detector.inference_path == "eager"
    assert "using eager" in caplog.text
    assert np.abs(s - _reference(detector.net, texture)).max() < 1e-4
    detector.invalidate()  # a failed path is not retried under "auto"
    detector.score_map(texture)
    assert detector.inference_path == "eager"
    detector.backend = "onednn"  # forced: the failure is raised, not hidden
    detector.invalidate()
    with pytest.raises(RuntimeError, match="primitive"):
        detector.score_map(texture)


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


def test_fast_numpy_nms_equals_the_torch_reference():
    rng = np.random.default_rng(7)
    total = 0
    for trial in range(120):
        h, w = (int(v) for v in rng.integers(4, 70, 2))
        s = rng.random((h + 2, w + 3)).astype(np.float32)[1 : 1 + h, 2 : 2 + w]  # a strided view
        if trial % 3 == 1:
            s = np.round(s, 1)  # plateaus and ties
        if trial % 3 == 2:
            s = np.where(rng.random((h, w)) < 0.4, np.float32(-np.inf), s)  # masked pixels
        window, threshold = int(rng.integers(1, 14)), float(rng.choice([0.0, 0.25]))
        top_k = [None, 3, 0][trial % 3]
        ref_xy, ref_s = nms(
            torch.from_numpy(np.ascontiguousarray(s))[None, None], window, threshold, top_k
        )[0]
        xy, sc = nms_numpy(s, window, threshold, top_k)
        np.testing.assert_array_equal(xy, ref_xy.numpy())
        np.testing.assert_array_equal(sc, ref_s.numpy())
        assert xy.dtype == np.float32 and sc.dtype == np.float32 and xy.shape == (len(sc), 2)
        total += len(xy)
    assert total > 500


def test_subpixel_refinement_recovers_the_vertex_of_a_paraboloid():
    h, w = 40, 60
    peaks = np.array([[10.3, 12.8], [30.0, 20.45], [47.6, 30.2]])
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    s = np.full((h, w), -1.0)
    for px, py in peaks:  # separate paraboloids, each the max near its own peak
        s = np.maximum(s, 1.0 - ((xx - px) ** 2 + (yy - py) ** 2) / 50.0)
    s = s.astype(np.float32)
    integer = np.rint(peaks).astype(np.float32)
    refined = refine_subpixel(s, integer)
    assert refined.dtype == np.float32
    np.testing.assert_allclose(refined, peaks, atol=1e-3)
    # border points stay where they are; non-finite neighbours count as 0
    s2 = s.copy()
    s2[12, 9] = np.nan
    edge = np.array([[0, 5], [w - 1, 7]], np.float32)
    np.testing.assert_array_equal(refine_subpixel(s2, edge), edge)
    assert np.all(np.abs(refine_subpixel(s2, integer[:1]) - integer[:1]) <= 0.5)
    assert refine_subpixel(s, np.zeros((0, 2), np.float32)).shape == (0, 2)


def test_benchmark_reports_the_stages(detector):
    res = benchmark(detector, shape=(64, 96), repeats=3)
    assert res["path"] == detector.inference_path and res["precision"] == "float32"
    assert (res["height"], res["width"], res["repeats"]) == (64.0, 96.0, 3.0)
    for key in ("score_map_ms", "nms_ms", "refine_ms", "detect_ms", "first_call_ms"):
        assert 0.0 < res[key] < 10_000.0, key
    assert res["score_map_min_ms"] <= res["score_map_ms"] <= res["score_map_p90_ms"]
    assert res["keypoints"] > 0 and res["threads"] >= 1


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
    assert res.exit_code == 2 and "image not found" in res.stderr
    assert res.stderr.strip().count("\n") == 0
    bad = tmp_path / "bad.pt"
    bad.write_text("not torch")
    res = runner.invoke(app, ["detect", str(img_path), "--weights", str(bad)])
    assert res.exit_code == 2 and str(bad) in res.stderr and "Traceback" not in res.output


@pytest.mark.parametrize("precision", ["float32", "bfloat16"])
@pytest.mark.parametrize("shape", [(350, 660), (352, 672), (16, 16), (5, 7), (40, 9), (37, 768)])
def test_cpu_input_is_torchs_own_conversion_and_padding(precision, shape):
    """The CPU input (padded by OpenCV, mapped through a per-grey-level table) is bit for bit
    what torch's `uint8 -> dtype, / 255` and `pad_to_multiple` give, with every grey level."""
    from glampoints.detector import PRECISIONS
    from glampoints.unet import pad_to_multiple

    rng = np.random.default_rng(sum(shape))
    image = rng.integers(0, 256, shape).astype(np.uint8)
    image.flat[:256] = np.arange(256)[: image.size]
    det = GlamPoints(precision=precision)
    x = torch.from_numpy(image).to(PRECISIONS[precision]).div_(255.0)[None, None]
    expected = pad_to_multiple(x).contiguous(memory_format=torch.channels_last)
    got = det._prepare(image)
    assert got.dtype == expected.dtype and got.shape == expected.shape
    assert torch.equal(got, expected)


@pytest.mark.both_precisions
def test_subpixel_keypoints_recover_a_known_subpixel_shift():
    """The shipped model on the sample fundus image and on copies moved by known fractions of
    a pixel: the shift read from the keypoints (median displacement of the points matched to
    their nearest neighbour) lies within 0.2 px of the truth with the quadratic peak refinement,
    and integer NMS positions cannot (their displacements are whole pixels: off by the shift's
    own fraction, up to 0.5 px)."""
    import cv2

    from tests.conftest import SAMPLE_IMAGE

    green = cv2.imread(str(SAMPLE_IMAGE))[..., 1]
    # the app's "auto" (the marker sets what it resolves to)
    precision = "bfloat16" if detector_module.cpu_has_native_bfloat16() else "float32"
    shifts = ((0.4, -0.3), (-0.25, 0.45), (0.5, 0.5), (0.15, -0.35))
    worst = {}
    for subpixel in (True, False):
        det = GlamPoints.from_pretrained(precision=precision, subpixel=subpixel)
        errors = []
        for dx, dy in shifts:
            moved = cv2.warpAffine(
                green,
                np.float32([[1, 0, dx], [0, 1, dy]]),
                green.shape[::-1],
                flags=cv2.INTER_CUBIC,
            )
            a = det.detect(green[400:700, 400:800]).xy
            b = det.detect(moved[400:700, 400:800]).xy
            distance = np.linalg.norm(b[None] - a[:, None], axis=2)
            nearest = distance.argmin(axis=1)
            kept = distance[np.arange(len(a)), nearest] < 1.5
            assert kept.sum() > 100, kept.sum()
            shift = np.median(b[nearest[kept]] - a[kept], axis=0)
            errors.append(float(np.abs(shift - [dx, dy]).max()))
        worst[subpixel] = max(errors)
    assert worst[True] < 0.2, worst  # measured 0.02-0.05 px (Intel AMX, both precisions)
    assert worst[False] >= 0.2, worst  # the broken variant: integer positions
