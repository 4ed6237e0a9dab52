"""GLAMpoints keypoint detector: UNet score map + non-maximum suppression, fast CPU inference.

CPU inference (float32, the default) runs the network as a chain of fused oneDNN primitives
(`_OneDnnUNet`): every BatchNorm folded into its convolution (`fold_batchnorm`), ReLU / sigmoid
fused into the convolution before it, channels-last tensors, weights pre-packed once per input
shape, and the decoder's skip concatenation replaced by two convolutions whose sum (and ReLU)
is a oneDNN post-op, so no concatenated tensor is ever written. The full-resolution level
(8 channels) runs in "pair space": a channels-last (H, W, 8) map is the same memory as an
(H, W/2, 16) map of pixel pairs, and its 3x3 convolutions become 3x2 convolutions with 16
channels, which oneDNN's AVX-512 kernels vectorise fully (8-channel outputs fill half a vector).
The scores equal the plain eval-mode network to ~1e-6. Where the oneDNN ops are missing (other
builds, GPUs) or fail, the BN-folded channels-last eager module is used instead.

Measured on the 2-core development machine (AMD EPYC Zen 4, 2 threads, 660x350 image, medians
of three runs; the machine was shared with other jobs, so the single-thread CPU time follows in
brackets): plain eval-mode UNet 87 ms (136 ms); BN-folded channels-last eager 50 ms (82); this
path 38 ms, best 33 ms (70); TorchScript freeze 43 ms (77); torch.compile ~40 ms after a 5-25 s
first call; NMS 0.4 ms, sub-pixel refinement 0.1 ms. The network costs 2.7 GMAC per padded
672x352 frame and float32 convolutions peak at ~106 GMAC/s on these two cores, so float32
cannot go below ~26 ms here. `precision="bfloat16"` (AVX512-BF16) takes ~20 ms.
Its scores differ by ~1e-2, which changes which of two near-equal maxima NMS keeps; with the
epoch-10 weights and a 10 px descriptor that looked harmful (failures 20% -> 25% on 144 pairs),
but with the shipped weights and the app's 6 px descriptor it is at parity (380 training-image
pairs: 51.8% vs 51.6% acceptable; 6 hard synthetic videos: 0.948 vs 0.967 of frames within
10 px). This class defaults to float32; the app's `[features] precision = "auto"` takes
bfloat16 where the CPU has it in hardware (`cpu_has_native_bfloat16`).

Threads: numpy's OpenBLAS workers spin for a while after each BLAS call; in a process that
calls numpy matmul between frames they compete with these two torch threads and halve the
speed (detect 96 -> 48 ms in `mosaic bench` with OPENBLAS_NUM_THREADS=1). `benchmark` and
`glampoints bench` repeat the measurement.
"""

from __future__ import annotations

import copy
import itertools
import logging
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch import nn

from glampoints.nms import nms_numpy, refine_subpixel
from glampoints.unet import MULTIPLE, UNet, pad_to_multiple

log = logging.getLogger(__name__)

DEFAULT_WEIGHTS = Path(__file__).resolve().parent / "weights" / "glampoints_retina.pt"
WEIGHTS_FORMAT = "glampoints-unet"
WEIGHTS_VERSION = 1
PRECISIONS = {"float32": torch.float32, "bfloat16": torch.bfloat16}
BACKENDS = ("auto", "onednn", "eager")
_CL = torch.channels_last
_MAX_PACKED_SHAPES = 8  # pre-packed weight layouts kept per convolution (one per input shape)
_ONEDNN_OPS = (
    "_convolution_pointwise",
    "_convolution_pointwise_",
    "_convolution_transpose_pointwise",
    "_reorder_convolution_weight",
    "_reorder_convolution_transpose_weight",
)


class WeightsError(ValueError):
    """A GLAMpoints weights file is missing, unreadable or does not fit the network."""


@dataclass(frozen=True)
class Keypoints:
    """Detected keypoints, strongest first: xy (N,2) float32 (x, y) pixels, scores (N,) float32."""

    xy: np.ndarray
    scores: np.ndarray

    def __len__(self) -> int:
        return len(self.xy)


def fold_batchnorm(net: nn.Module) -> nn.Module:
    """Eval-mode copy of `net` with each Conv2d -> BatchNorm2d pair fused into one Conv2d.

    conv(x) = W x + b followed by BN gives (W * k) x + (b - mean) * k + beta with
    k = gamma / sqrt(var + eps) per output channel; the BN is replaced by Identity.
    """
    fused = copy.deepcopy(net).eval()
    for module in fused.modules():
        if not isinstance(module, nn.Sequential):
            continue
        names = list(module._modules)
        for a, b in itertools.pairwise(names):
            conv, bn = module._modules[a], module._modules[b]
            if not (isinstance(conv, nn.Conv2d) and isinstance(bn, nn.BatchNorm2d)):
                continue
            with torch.no_grad():
                k = bn.weight / torch.sqrt(bn.running_var + bn.eps)
                bias = conv.bias if conv.bias is not None else torch.zeros_like(bn.running_mean)
                new = nn.Conv2d(
                    conv.in_channels,
                    conv.out_channels,
                    conv.kernel_size,
                    stride=conv.stride,
                    padding=conv.padding,
                    dilation=conv.dilation,
                    groups=conv.groups,
                    bias=True,
                    padding_mode=conv.padding_mode,
                ).to(conv.weight.device)
                new.weight.copy_(conv.weight * k.view(-1, 1, 1, 1))
                new.bias.copy_((bias - bn.running_mean) * k + bn.bias)
            module._modules[a] = new
            module._modules[b] = nn.Identity()
    return fused


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0][:200] if text else type(exc).__name__


class _Padded(nn.Module):
    """UNet on padded input (no shape-dependent Python, so it traces for any size).

    The body runs in the dtype of its weights; the 1x1 head and sigmoid always run in float32,
    so a bfloat16 body does not quantise the scores into plateaus (NMS ties).
    """

    def __init__(self, net: UNet) -> None:
        super().__init__()
        self.net = net
        self.head = copy.deepcopy(net.head).float()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.head(self.net.features_padded(x).float()))


def cpu_has_native_bfloat16() -> bool:
    """Whether this CPU does bfloat16 dot products in hardware (AVX512-BF16 or AMX; read from
    /proc/cpuinfo, so Linux only): elsewhere bfloat16 is emulated and slower than float32."""
    try:
        info = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    return bool(re.search(r"\b(avx512_bf16|amx_bf16)\b", info))


def onednn_fusion_available() -> bool:
    """Whether this PyTorch build has the fused oneDNN convolution ops (those torch.compile uses
    on CPU) that the fast inference path calls directly."""
    try:
        ops = torch.ops.mkldnn
        return torch.backends.mkldnn.is_available() and all(hasattr(ops, n) for n in _ONEDNN_OPS)
    except (AttributeError, RuntimeError):
        return False


class _FusedConv:
    """One (transposed) convolution as one oneDNN primitive, activation fused in ("relu",
    "sigmoid" or "none"). Input and output are channels-last; the weights are re-laid out
    once per input shape into the blocked format oneDNN picks for it (else every call would
    reorder them)."""

    def __init__(
        self,
        weight: torch.Tensor,
        bias: torch.Tensor | None,
        padding: tuple[int, int] | list[int],
        attr: str = "relu",
        stride: tuple[int, int] | list[int] = (1, 1),
        transposed: bool = False,
    ) -> None:
        self.weight = weight.detach().contiguous(memory_format=_CL)
        self.bias = None if bias is None else bias.detach().contiguous()
        self.padding, self.stride = list(padding), list(stride)
        self.attr, self.transposed = attr, transposed
        self._packed: dict[tuple[int, ...], torch.Tensor] = {}

    def packed_weight(self, x: torch.Tensor) -> torch.Tensor:
        key = tuple(x.shape)
        w = self._packed.get(key)
        if w is None:
            if len(self._packed) >= _MAX_PACKED_SHAPES:
                self._packed.clear()
            mk = torch.ops.mkldnn
            if self.transposed:
                w = mk._reorder_convolution_transpose_weight(
                    self.weight, self.padding, [0, 0], self.stride, [1, 1], 1, list(key)
                )
            else:
                w = mk._reorder_convolution_weight(
                    self.weight, self.padding, self.stride, [1, 1], 1, list(key)
                )
            self._packed[key] = w
        return w

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        w, mk = self.packed_weight(x), torch.ops.mkldnn
        if self.transposed:
            return mk._convolution_transpose_pointwise(
                x, w, self.bias, self.padding, [0, 0], self.stride, [1, 1], 1, self.attr, [], None
            )
        return mk._convolution_pointwise(
            x, w, self.bias, self.padding, self.stride, [1, 1], 1, self.attr, [], None
        )

    def add_relu_(self, other: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """other <- relu(other + conv(x)) in place: one primitive (oneDNN sum post-op)."""
        return torch.ops.mkldnn._convolution_pointwise_.binary(
            other, x, self.packed_weight(x), self.bias, self.padding, self.stride, [1, 1], 1,
            "add", 1.0, "relu", [], None,
        )  # fmt: skip


def _max_pool_2x2(x: torch.Tensor) -> torch.Tensor:
    """`F.max_pool2d(x, 2)` for even sizes as two strided maxima: the same values, 3-5x faster on
    channels-last CPU tensors (no indices are computed; ~1.7 ms a frame in bfloat16)."""
    rows = torch.maximum(x[:, :, 0::2], x[:, :, 1::2])
    return torch.maximum(rows[:, :, :, 0::2], rows[:, :, :, 1::2])


def _pairs(x: torch.Tensor) -> torch.Tensor:
    """(N,C,H,W) channels-last -> (N,2C,H,W/2) channels-last view of the same memory: pixel
    pairs (2j, 2j+1) side by side as channels."""
    n, c, h, w = x.shape
    return x.permute(0, 2, 3, 1).reshape(n, h, w // 2, 2 * c).permute(0, 3, 1, 2)


def _unpairs(x: torch.Tensor) -> torch.Tensor:
    """Inverse of `_pairs` (a view)."""
    n, c2, h, w2 = x.shape
    return x.permute(0, 2, 3, 1).reshape(n, h, 2 * w2, c2 // 2).permute(0, 3, 1, 2)


def _pair_weight(w: torch.Tensor) -> torch.Tensor:
    """(O,I,3,3) weight -> (2O,2I,3,2) weight of the same convolution in pair space.

    Input pair k holds pixels x' = 2k + b (or 2k - 1 + b, see `_PairConv`), output pair j
    pixels x = 2j - 1 + a (or 2j + a); with kernel column t the horizontal tap is
    dx = x' - x = 2t + b - a - 1 in both cases, and taps with |dx| > 1 are zero (6 of 8 blocks
    are used: 1.33x the MACs of the 3x3 convolution, at twice the vector width).
    """
    o, i = w.shape[:2]
    out = w.new_zeros(2 * o, 2 * i, 3, 2)
    for a, b, t in itertools.product((0, 1), repeat=3):
        dx = 2 * t + b - a - 1
        if abs(dx) <= 1:
            out[a * o : (a + 1) * o, b * i : (b + 1) * i, :, t] = w[:, :, :, dx + 1]
    return out


class _PairConv(_FusedConv):
    """A 3x3 stride-1 convolution of a full-resolution map, run in pair space.

    "even -> odd" (padding (1, 1)) reads pairs (2k, 2k+1) of a W-wide map and writes W/2 + 1
    pairs (2j-1, 2j), i.e. pixels -1 .. W; those two outside pixels are set to zero so the next
    "odd -> even" convolution (padding (1, 0)) sees the zero padding of the original network.
    """

    def __init__(
        self, weight: torch.Tensor, bias: torch.Tensor | None, to_odd: bool, attr: str = "relu"
    ) -> None:
        pair_bias = None if bias is None else torch.cat([bias, bias])
        super().__init__(_pair_weight(weight), pair_bias, (1, 1) if to_odd else (1, 0), attr)
        self.to_odd, self.channels = to_odd, weight.shape[0]

    def _zero_outside(self, y: torch.Tensor) -> torch.Tensor:
        if self.to_odd:
            y[:, : self.channels, :, 0] = 0  # pixel -1
            y[:, self.channels :, :, -1] = 0  # pixel W
        return y

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        return self._zero_outside(super().__call__(x))

    def add_relu_(self, other: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        return self._zero_outside(super().add_relu_(other, x))


def _convs(block: nn.Module) -> list[nn.Conv2d]:
    return [m for m in block.modules() if isinstance(m, nn.Conv2d)]


class _OneDnnUNet:
    """Inference-only UNet on fused oneDNN primitives (see the module docstring).

    Built from a BN-folded copy of the network (`fold_batchnorm`); maps a channels-last
    (N,1,H,W) image in the body's dtype (H, W multiples of 16) to float32 scores (N,1,H,W).
    The 1x1 head and its sigmoid always run in float32.
    """

    def __init__(self, folded: UNet, dtype: torch.dtype = torch.float32) -> None:
        def wb(m: nn.Module) -> tuple[torch.Tensor, torch.Tensor]:
            return m.weight.detach().to(dtype), m.bias.detach().to(dtype)

        def conv(m: nn.Conv2d, attr: str = "relu") -> _FusedConv:
            return _FusedConv(*wb(m), m.padding, attr)

        def split(m: nn.Conv2d, c_up: int, pair: bool = False) -> tuple[_FusedConv, _FusedConv]:
            """conv(cat([up, skip])) as conv_up(up) + conv_skip(skip), the sum a post-op."""
            w, b = wb(m)
            if pair:
                return (
                    _PairConv(w[:, :c_up], b, to_odd=True, attr="none"),
                    _PairConv(w[:, c_up:], None, to_odd=True),
                )
            return _FusedConv(w[:, :c_up], b, m.padding, "none"), _FusedConv(
                w[:, c_up:], None, m.padding
            )

        self.dtype = dtype
        (e1, e2), *deeper = [_convs(b) for b in folded.down]
        self.enc1 = (_PairConv(*wb(e1), to_odd=True), _PairConv(*wb(e2), to_odd=False))
        self.down = [(conv(a), conv(b)) for a, b in deeper]
        self.bottleneck = tuple(conv(m) for m in _convs(folded.bottleneck))
        self.up: list[tuple[_FusedConv, _FusedConv, _FusedConv, _FusedConv]] = []
        for up, dec in zip(folded.up[:-1], folded.dec[:-1], strict=True):
            a, b = _convs(dec)
            t = _FusedConv(*wb(up), (0, 0), "none", (2, 2), transposed=True)
            self.up.append((t, *split(a, up.out_channels), conv(b)))
        # Full-resolution decoder level in pair space. The 2x2 stride-2 transposed convolution
        # becomes a (2,1)-kernel, (2,1)-stride one whose 2C outputs are the pixel pair.
        last_up, (a, b) = folded.up[-1], _convs(folded.dec[-1])
        wt, bt = wb(last_up)  # (C_in, C, 2, 2)
        wt_pair = torch.cat([wt[:, :, :, :1], wt[:, :, :, 1:]], dim=1)  # (C_in, 2C, 2, 1)
        self.up1 = _FusedConv(wt_pair, torch.cat([bt, bt]), (0, 0), "none", (2, 1), True)
        self.dec1 = (
            *split(a, last_up.out_channels, pair=True),
            _PairConv(*wb(b), to_odd=False),
        )
        # 1x1 head C -> 1 with its sigmoid, float32: block-diagonal 2C -> 2 in pair space
        wh, bh = folded.head.weight.detach().float(), folded.head.bias.detach().float()
        c = wh.shape[1]
        w_pair = wh.new_zeros(2, 2 * c, 1, 1)
        w_pair[0, :c], w_pair[1, c:] = wh[0], wh[0]
        self.head = _FusedConv(w_pair, bh.repeat(2), (0, 0), "sigmoid")

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        e = self.enc1[1](self.enc1[0](_pairs(x)))  # full-res level 1 output, pair space
        skips = []
        y = _max_pool_2x2(_unpairs(e))
        for a, b in self.down:
            y = b(a(y))
            skips.append(y)
            y = _max_pool_2x2(y)
        y = self.bottleneck[1](self.bottleneck[0](y))
        for (up, c_up, c_skip, c2), skip in zip(self.up, reversed(skips), strict=True):
            y = c2(c_skip.add_relu_(c_up(up(y)), skip))
        c_up, c_skip, c2 = self.dec1
        d = c2(c_skip.add_relu_(c_up(self.up1(y)), e))
        if d.dtype != torch.float32:
            d = d.float()
        return _unpairs(self.head(d))


def save_weights(state_dict: dict[str, torch.Tensor], path: str | Path, meta: dict | None = None):
    """Write a shippable weights file: the UNet state dict plus a small metadata dict."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": WEIGHTS_FORMAT,
        "version": WEIGHTS_VERSION,
        "state_dict": {k: v.detach().cpu().contiguous().clone() for k, v in state_dict.items()},
        "meta": dict(meta or {}),
    }
    atomic_torch_save(payload, path)


def atomic_write(path: Path, write: Callable[[Path], object]) -> None:
    """`write` a temporary file beside `path`, then rename it: a kill never leaves half a file
    (weights, training checkpoints, the training log)."""
    tmp = path.with_name(f".{path.name}.tmp")
    write(tmp)
    tmp.replace(path)


def atomic_torch_save(obj: Any, path: Path) -> None:
    """`torch.save` of `obj` to `path`, atomically (`atomic_write`)."""
    atomic_write(path, lambda tmp: torch.save(obj, tmp))


def load_weights(path: str | Path) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """(state_dict, meta) of a weights file written by `save_weights` (or a training
    checkpoint, whose "model" entry is used); raises WeightsError naming the path."""
    path = Path(path)
    if not path.is_file():
        raise WeightsError(f"GLAMpoints weights file not found: {path}")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch's own text is long (pickling, weights_only): not for users
        raise WeightsError(
            f"cannot read GLAMpoints weights {path}: not a weights file (expected one written by "
            "`glampoints export`, or a training checkpoint)"
        ) from exc
    if isinstance(payload, dict) and isinstance(payload.get("state_dict"), dict):
        state, meta = payload["state_dict"], payload.get("meta") or {}
    elif isinstance(payload, dict) and isinstance(payload.get("model"), dict):
        state, meta = payload["model"], {"source": "training checkpoint"}
    else:
        raise WeightsError(f"{path} is not a GLAMpoints weights file (no state_dict)")
    if not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise WeightsError(f"{path} is not a GLAMpoints weights file (non-tensor entries)")
    return state, dict(meta)


_INPUT_TABLES: dict[str, tuple[np.ndarray, torch.dtype]] = {}


def _input_table(precision: str) -> tuple[np.ndarray, torch.dtype]:
    """(256,) table of the network's input for each grey level, as torch computes it
    (`uint8 -> dtype, / 255`), in a numpy dtype of the same width for `cv2.LUT` (bfloat16 as
    int16 bits), and the torch dtype to view the result as."""
    if precision not in _INPUT_TABLES:
        dtype = PRECISIONS[precision]
        levels = torch.arange(256, dtype=torch.uint8).to(dtype).div_(255.0)
        bits = torch.int16 if dtype == torch.bfloat16 else dtype
        _INPUT_TABLES[precision] = (levels.view(bits).numpy().copy(), dtype)
    return _INPUT_TABLES[precision]


class GlamPoints:
    """GLAMpoints detector: score map by the UNet, keypoints by NMS (window `nms_window_px`).

    Keypoints have score > `score_threshold`; at most `max_keypoints` (strongest) are kept.
    The device is chosen by the caller. Call `invalidate()` after changing `net`'s weights
    in place (`load_state_dict` here does it).
    """

    def __init__(
        self,
        nms_window_px: int = 10,
        score_threshold: float = 0.0,
        max_keypoints: int | None = None,
        device: torch.device | str = "cpu",
        precision: str = "float32",
        subpixel: bool = True,
    ) -> None:
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision}")
        if nms_window_px < 1:
            raise ValueError(f"nms_window_px must be >= 1, got {nms_window_px}")
        self.nms_window_px = int(nms_window_px)
        self.score_threshold = float(score_threshold)
        self.max_keypoints = max_keypoints
        self.device = torch.device(device)
        self.precision = precision
        self.subpixel = subpixel  # quadratic peak refinement of the NMS positions
        self.net = UNet().to(self.device).eval()
        self.meta: dict[str, Any] = {}
        # "auto": fused oneDNN path on CPU where available (and not failed before), else eager;
        # "onednn" | "eager" force one (benchmarks, tests). Call invalidate() after changing it.
        self.backend = "auto"
        self._infer: Callable[[torch.Tensor], torch.Tensor] | None = None
        self._onednn_failed = False

    @classmethod
    def from_pretrained(cls, path: str | Path | None = None, **kwargs: Any) -> GlamPoints:
        """Detector with weights from `path` (default: the shipped retina weights)."""
        det = cls(**kwargs)
        state, meta = load_weights(DEFAULT_WEIGHTS if path is None else path)
        det.load_state_dict(state, source=str(path or DEFAULT_WEIGHTS))
        det.meta = meta
        log.debug("loaded GLAMpoints weights %s (%s)", path or DEFAULT_WEIGHTS, meta)
        return det

    def load_state_dict(self, state: dict[str, torch.Tensor], source: str = "state dict") -> None:
        """Strictly load UNet weights; a mismatch raises WeightsError naming `source`."""
        try:
            self.net.load_state_dict(state, strict=True)
        except RuntimeError as exc:
            lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
            detail = lines[1] if len(lines) > 1 else lines[0] if lines else "mismatch"
            raise WeightsError(
                f"weights {source} do not fit the GLAMpoints UNet: {detail[:200]}"
            ) from exc
        self.net.eval()
        self.invalidate()

    def invalidate(self) -> None:
        """Forget the optimised inference copy (rebuilt on the next call)."""
        self._infer = None

    @property
    def inference_path(self) -> str:
        """The path the next score map takes: "onednn" (fused primitives) or "eager"."""
        if self._infer is None:
            return "onednn" if self._want_onednn() else "eager"
        return "onednn" if isinstance(self._infer, _OneDnnUNet) else "eager"

    def _want_onednn(self) -> bool:
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {', '.join(BACKENDS)}, got {self.backend}")
        usable = self.device.type == "cpu" and onednn_fusion_available()
        if self.backend == "onednn" and not usable:
            raise RuntimeError("the fused oneDNN path needs a CPU device and a oneDNN build")
        return self.backend == "onednn" or (
            self.backend == "auto" and usable and not self._onednn_failed
        )

    def _build(self) -> Callable[[torch.Tensor], torch.Tensor]:
        """The inference network: BN folded, channels-last, in the chosen precision.

        Fused oneDNN primitives where available (checked once against the eager module on a
        small input), else the eager module. TorchScript trace + freeze (+ optimize_for_inference),
        torch.compile and the to_mkldnn tensor path were measured slower (module docstring).
        """
        dtype = PRECISIONS[self.precision]
        folded = fold_batchnorm(self.net).to(self.device, dtype=dtype)
        eager = _Padded(folded).eval().to(memory_format=torch.channels_last)
        if not self._want_onednn():
            return eager
        try:
            fast = _OneDnnUNet(folded, dtype)
            x = torch.rand(1, 1, 32, 48, generator=torch.Generator().manual_seed(0))
            x = x.to(self.device, dtype).contiguous(memory_format=_CL)
            diff = (fast(x) - eager(x).float()).abs().max().item()
        except RuntimeError as exc:
            if self.backend == "onednn":
                raise
            log.warning("fused oneDNN inference unavailable (%s); using eager", _first_line(exc))
            self._onednn_failed = True
            return eager
        tolerance = 1e-4 if dtype == torch.float32 else 5e-2
        if not diff <= tolerance:
            if self.backend == "onednn":
                raise RuntimeError(f"fused oneDNN inference differs from the network by {diff}")
            log.warning("fused oneDNN inference differs by %.3g; using eager", diff)
            self._onednn_failed = True
            return eager
        return fast

    def _prepare(self, image: np.ndarray) -> torch.Tensor:
        if image.ndim != 2 or image.dtype != np.uint8:
            raise ValueError(
                f"GLAMpoints needs a uint8 HxW grey image, got {image.dtype} {image.shape}"
            )
        if self.device.type != "cpu":
            x = torch.from_numpy(np.ascontiguousarray(image)).to(self.device)
            x = x.to(PRECISIONS[self.precision]).div_(255.0)[None, None]
            return pad_to_multiple(x).contiguous(memory_format=torch.channels_last)
        # On the CPU the same values without torch's element-wise kernels, whose thread
        # hand-offs cost more than the work on a small frame (and far more on a loaded machine):
        # padded as `pad_to_multiple` pads (reflect = OpenCV's REFLECT_101, or zeros), then
        # mapped through a table of torch's own uint8 -> dtype -> / 255 for each grey level.
        h, w = image.shape
        ph, pw = (-h) % MULTIPLE, (-w) % MULTIPLE
        if ph or pw:
            border = cv2.BORDER_REFLECT_101 if ph < h and pw < w else cv2.BORDER_CONSTANT
            image = cv2.copyMakeBorder(image, 0, ph, 0, pw, border, value=0)
        table, dtype = _input_table(self.precision)
        x = torch.from_numpy(cv2.LUT(image, table)).view(dtype)[None, None]
        return x.contiguous(memory_format=torch.channels_last)

    def score_map(self, image: np.ndarray) -> np.ndarray:
        """HxW float32 keypoint probability map of a uint8 HxW grey image."""
        h, w = image.shape[:2]
        x = self._prepare(image)
        with torch.inference_mode():
            if self._infer is None:
                self._infer = self._build()
            try:
                out = self._infer(x)
            except RuntimeError as exc:  # e.g. a oneDNN primitive this shape cannot create
                if not isinstance(self._infer, _OneDnnUNet) or self.backend == "onednn":
                    raise
                log.warning("fused oneDNN inference failed (%s); using eager", _first_line(exc))
                self._onednn_failed = True
                self._infer = self._build()
                out = self._infer(x)
        # float32 CPU: no copy, a view of the padded map (the next call allocates a new one)
        return out[0, 0, :h, :w].float().cpu().numpy()

    def detect(self, image: np.ndarray, mask: np.ndarray | None = None) -> Keypoints:
        """Keypoints of a uint8 HxW grey image; `mask` (HxW, nonzero = allowed) drops points.

        Masked-out pixels are removed before NMS and top-k, so a strong response outside the
        mask (e.g. the field-of-view rim) does not suppress keypoints inside it.
        """
        s = self.score_map(image)
        if mask is not None:
            if mask.shape[:2] != s.shape:
                raise ValueError(f"mask shape {mask.shape} differs from image shape {s.shape}")
            if mask.dtype == np.uint8 and mask.ndim == 2:  # copied under the mask: one pass
                masked = cv2.copyTo(s, mask, np.full(s.shape, -np.inf, np.float32))
            else:
                masked = np.where(mask > 0, s, np.float32(-np.inf))
        else:
            masked = s
        xy, scores = nms_numpy(masked, self.nms_window_px, self.score_threshold, self.max_keypoints)
        if self.subpixel:
            xy = refine_subpixel(s, xy)
        return Keypoints(xy=xy, scores=scores)


def _ms_stats(seconds: list[float]) -> tuple[float, float, float]:
    t = 1000.0 * np.asarray(seconds)
    return float(np.median(t)), float(t.min()), float(np.percentile(t, 90))


def benchmark(
    detector: GlamPoints, shape: tuple[int, int] = (350, 660), repeats: int = 20, seed: int = 0
) -> dict[str, Any]:
    """Wall times (ms) of the detector's stages on a seeded, blurred-noise HxW image.

    After warm-up (network build, oneDNN primitive creation: `first_call_ms`), `repeats` runs
    of each: score map (median, min, p90: the min is robust to other load on the machine),
    NMS (`nms_numpy` with the detector's window, threshold and top-k), sub-pixel refinement,
    and `detect` end to end. Also the thread settings, the inference path and precision.
    """
    rng = np.random.default_rng(seed)
    noise = rng.random(shape).astype(np.float32)
    image = cv2.normalize(cv2.GaussianBlur(noise, (0, 0), 2.0), None, 0, 255, cv2.NORM_MINMAX)
    image = image.astype(np.uint8)
    detector.invalidate()
    t0 = time.perf_counter()
    s = detector.score_map(image)
    first_call = time.perf_counter() - t0
    for _ in range(2):  # warm-up
        detector.detect(image)
    args = (detector.nms_window_px, detector.score_threshold, detector.max_keypoints)
    t_score, t_nms, t_refine, t_detect = [], [], [], []
    n_points = 0
    for _ in range(repeats):
        t0 = time.perf_counter()
        s = detector.score_map(image)
        t1 = time.perf_counter()
        xy, _ = nms_numpy(s, *args)
        t2 = time.perf_counter()
        refine_subpixel(s, xy)
        t3 = time.perf_counter()
        n_points = len(detector.detect(image))
        t4 = time.perf_counter()
        t_score.append(t1 - t0)
        t_nms.append(t2 - t1)
        t_refine.append(t3 - t2)
        t_detect.append(t4 - t3)
    score_med, score_min, score_p90 = _ms_stats(t_score)
    return {
        "score_map_ms": score_med,
        "score_map_min_ms": score_min,
        "score_map_p90_ms": score_p90,
        "nms_ms": _ms_stats(t_nms)[0],
        "refine_ms": _ms_stats(t_refine)[0],
        "detect_ms": _ms_stats(t_detect)[0],
        "detect_min_ms": _ms_stats(t_detect)[1],
        "first_call_ms": 1000.0 * first_call,
        "keypoints": float(n_points),
        "threads": float(torch.get_num_threads()),
        "interop_threads": float(torch.get_num_interop_threads()),
        "path": detector.inference_path,
        "precision": detector.precision,
        "height": float(shape[0]),
        "width": float(shape[1]),
        "repeats": float(repeats),
    }
