"""GLAMpoints training (paper: "Training", "Baselines and implementation details").

Each step takes `batch_size` synthetic pairs (I, I', H) cut from the base images, runs the UNet
on all 2 * batch_size crops, and builds the paper's reward from non-differentiable steps on
the detached score maps: NMS keypoints (window 10), upright root-SIFT descriptors, brute-force
cross-checked matching, and a match is a true positive (TP) if ||H x - x'|| <= 3 px. The reward
map R is 1 at the TP keypoints of both images and 0 elsewhere; the mask M holds the n TPs of an
image and n other keypoints of that image sampled at random (all of them if there are fewer);
loss = sum((S - R)^2 * M) / sum(M) over the whole batch. Adam (lr 1e-3, betas 0.9/0.999),
batch 5, 256x256 crops, 35 epochs.

Epoch size: the paper made one pair per base image per epoch from 1336 images (about 267
steps of 5). We have 190 base images, so each contributes `pairs_per_image` = 7 pairs per
epoch (1330 pairs, 266 steps): the same number of steps per epoch and in total.

Pre-processing: with `preprocess=True` base images are reduced to their green channel and, by
default, contrast-equalised with CLAHE once, before the pairs are cut and the appearance changes
applied (the recipe of the shipped weights). `preprocess_crops=True` instead gives every
augmented crop the application's per-frame pre-processing (CLAHE, bilateral filter:
`synthetic.frame_preprocess`). Measured as a fine-tuning of the shipped run's epoch-18 state
(7 epochs): synthetic validation pairs through the app improved (53.3 % vs 48.3 % acceptable),
but the hard synthetic videos got much worse (45 % vs 80 % of frames within 10 px): CLAHE on a
256 px crop works on 32 px tiles, on a 660x350 frame on ~80 px tiles, so the crops train the
network on a stronger equalisation than frames get. Hence off by default.

Fine-tuning: `init` names weights (a weights file or a training checkpoint) that a new run
starts from instead of a random initialisation; the schedule and optimiser start afresh.

Reproducibility: every random draw comes from a generator seeded by (seed, epoch, index), so a
run resumed from a checkpoint replays the same pairs and mining; checkpoints are written
atomically every `checkpoint_every` steps and at each epoch end.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import random
import subprocess
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from tqdm import tqdm

from glampoints.descriptors import upright_rootsift
from glampoints.detector import (
    WeightsError,
    atomic_torch_save,
    atomic_write,
    load_weights,
    save_weights,
)
from glampoints.metrics import (
    matching_score,
    registration_class,
    repeatability,
    six_fixed_points,
    true_positive_mask,
)
from glampoints.nms import nms
from glampoints.synthetic import augment, fixed_pairs, frame_preprocess, green_clahe, make_pair
from glampoints.unet import UNet

log = logging.getLogger(__name__)

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")
Pair = tuple[np.ndarray, np.ndarray, np.ndarray]


class TrainingError(ValueError):
    """A training run cannot start, resume or go on (bad folder, no images, a checkpoint or
    metrics log that does not fit, a non-finite loss): its message is for the user."""


@dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run (stored in every checkpoint)."""

    data_dir: str
    val_dir: str
    out_dir: str
    epochs: int = 35
    batch_size: int = 5
    crop: int = 256
    lr: float = 1e-3
    betas: tuple[float, float] = (0.9, 0.999)
    nms_window_px: int = 10
    eps_px: float = 3.0
    pairs_per_image: int = 7  # 190 images x 7 = 1330 pairs/epoch, the paper's 1336 images x 1
    seed: int = 0
    num_threads: int = 2
    preprocess: bool = True  # green channel of the base images (else plain grey)
    preprocess_crops: bool = False  # the app's CLAHE + bilateral on every crop (see above)
    jpeg_p: float = 0.0  # probability of JPEG-compressing each augmented crop (not the paper's)
    init: str = ""  # weights a new run starts from ("" = random initialisation)
    max_steps: int | None = None  # stop after this many steps in all (smoke runs)
    val_pairs_per_image: int = 4
    val_crop: int = 256
    checkpoint_every: int = 50  # steps between checkpoints (plus one at each epoch end)
    descriptor_size_px: float = 10.0
    max_base_side: int = 800  # larger base images are downscaled to this longest side


# Fields a resumed run may change; everything else is taken from the checkpoint.
RESUME_OVERRIDES = ("data_dir", "val_dir", "out_dir", "epochs", "max_steps", "num_threads")


def git_hash() -> str:
    """Commit of the code doing the training ("-dirty" if glampoints/ has uncommitted
    changes), "unknown" outside a git checkout."""
    here = Path(__file__).resolve().parent

    def git(*args: str) -> str:
        done = subprocess.run(
            ["git", *args], cwd=here, capture_output=True, text=True, timeout=10, check=True
        )
        return done.stdout.strip()

    try:
        head = git("rev-parse", "HEAD")
        status = git("status", "--porcelain", "--", ".")
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    if not head:
        return "unknown"
    return head + ("-dirty" if status else "")


def list_images(folder: str | Path) -> list[Path]:
    """Image files of a folder, sorted by name; TrainingError if none."""
    folder = Path(folder)
    if not folder.is_dir():
        raise TrainingError(f"image folder not found: {folder}")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)
    if not files:
        raise TrainingError(f"no images ({', '.join(IMAGE_EXTENSIONS)}) in {folder}")
    return files


def load_base_image(path: Path, preprocess: bool, max_side: int, clahe: bool = True) -> np.ndarray:
    """Grey uint8 base image: green channel (+ CLAHE if `clahe`) or plain grey, longest side
    <= max_side."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise TrainingError(f"cannot read image {path}")
    if preprocess:
        grey = green_clahe(img) if clahe else np.ascontiguousarray(img[..., 1])
    else:
        grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    scale = max_side / max(grey.shape)
    if scale < 1.0:
        size = (round(grey.shape[1] * scale), round(grey.shape[0] * scale))
        grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
    return grey


# ---------------------------------------------------------------------------------------------
# Matching and reward


_MATCHER = cv2.BFMatcher(cv2.NORM_L2, crossCheck=True)


def match_descriptors(d1: np.ndarray, d2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours (brute force, L2): index arrays (i1, i2) of the matches."""
    if len(d1) == 0 or len(d2) == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty.copy()
    matches = _MATCHER.match(d1, d2)
    i1 = np.fromiter((m.queryIdx for m in matches), dtype=np.int64, count=len(matches))
    i2 = np.fromiter((m.trainIdx for m in matches), dtype=np.int64, count=len(matches))
    return i1, i2


def _mined(n_kp: int, tp_idx: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """TP indices plus as many randomly chosen other keypoints (all, if fewer)."""
    others = np.setdiff1d(np.arange(n_kp), tp_idx, assume_unique=False)
    if len(tp_idx) < len(others):
        others = rng.choice(others, size=len(tp_idx), replace=False)
    return np.concatenate([tp_idx, others]).astype(np.int64)


def reward_and_mask(
    images1: Sequence[np.ndarray],
    images2: Sequence[np.ndarray],
    Hs: Sequence[np.ndarray],
    scores: torch.Tensor,
    cfg: TrainConfig,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
    """Reward R and mining mask M (both (2B,1,h,w) float32) of a batch, plus diagnostics.

    `scores` holds the maps of images1 (first B) then images2 (last B).
    """
    B = len(Hs)
    R = np.zeros(tuple(scores.shape), dtype=np.float32)
    M = np.zeros_like(R)
    kps = nms(scores.detach(), cfg.nms_window_px, 0.0)
    n_tp = n_kp = n_match = 0
    for b in range(B):  # loop over the pairs of the batch; all per-keypoint work is vectorised
        xy1 = kps[b][0].cpu().numpy()
        xy2 = kps[B + b][0].cpu().numpy()
        d1 = upright_rootsift(images1[b], xy1, cfg.descriptor_size_px)
        d2 = upright_rootsift(images2[b], xy2, cfg.descriptor_size_px)
        i1, i2 = match_descriptors(d1, d2)
        tp = true_positive_mask(xy1[i1], xy2[i2], Hs[b], cfg.eps_px)
        for img_index, xy, tp_idx in ((b, xy1, i1[tp]), (B + b, xy2, i2[tp])):
            pts = xy.astype(np.int64)
            R[img_index, 0, pts[tp_idx, 1], pts[tp_idx, 0]] = 1.0
            sel = _mined(len(xy), tp_idx, rng)
            M[img_index, 0, pts[sel, 1], pts[sel, 0]] = 1.0
        n_tp += int(tp.sum())
        n_kp += len(xy1) + len(xy2)
        n_match += len(i1)
    stats = {"n_tp": n_tp / B, "n_kp": n_kp / (2 * B), "n_match": n_match / B}
    return R, M, stats


def glampoints_loss(
    net: UNet,
    images1: Sequence[np.ndarray],
    images2: Sequence[np.ndarray],
    Hs: Sequence[np.ndarray],
    cfg: TrainConfig,
    rng: np.random.Generator,
) -> dict[str, Any]:
    """Forward both images of every pair and return {"total": loss tensor, diagnostics...}.

    loss = sum((S - R)^2 * M) / sum(M); when no keypoint is mined (sum(M) = 0) the loss is a
    zero that still depends on the network, and "mined" is 0.
    """
    imgs = np.stack(list(images1) + list(images2))
    device = next(net.parameters()).device
    x = torch.from_numpy(imgs).to(device=device, dtype=torch.float32).div_(255.0)[:, None]
    S = net(x.contiguous(memory_format=torch.channels_last))
    R, M, stats = reward_and_mask(images1, images2, Hs, S, cfg, rng)
    Rt = torch.from_numpy(R).to(device)
    Mt = torch.from_numpy(M).to(device)
    mined = float(M.sum())
    total = ((S - Rt) ** 2 * Mt).sum() / max(mined, 1.0)
    return {"total": total, "mined": mined, **stats}


# ---------------------------------------------------------------------------------------------
# Validation


def _sift_points(image: np.ndarray) -> np.ndarray:
    """SIFT keypoint locations (duplicates from several orientations removed)."""
    kps = cv2.SIFT_create().detect(image, None)
    if not kps:
        return np.zeros((0, 2), dtype=np.float32)
    xy = np.array([k.pt for k in kps], dtype=np.float32)
    return np.unique(xy, axis=0)


def _glampoints_points(net: UNet, images: Sequence[np.ndarray], window: int) -> list[np.ndarray]:
    """NMS keypoints of the eval-mode network on each image (batched forward passes)."""
    out: list[np.ndarray] = []
    device = next(net.parameters()).device
    was_training = net.training
    net.eval()
    with torch.inference_mode():
        for start in range(0, len(images), 16):
            chunk = np.stack(images[start : start + 16])
            x = torch.from_numpy(chunk).to(device=device, dtype=torch.float32).div_(255.0)
            S = net(x[:, None].contiguous(memory_format=torch.channels_last)).float().cpu()
            out.extend(xy.numpy() for xy, _ in nms(S, window, 0.0))
    net.train(was_training)
    return out


def evaluate_pairs(
    points_fn: Callable[[Sequence[np.ndarray]], list[np.ndarray]],
    pairs: Sequence[Pair],
    eps_px: float = 3.0,
    descriptor_size_px: float = 10.0,
) -> dict[str, float]:
    """Mean repeatability, M.score, #TP matches and registration-class fractions over pairs.

    Registration: RANSAC homography (3 px) from the cross-checked matches, judged by
    `registration_class` on the six fixed points of the first image.
    """
    images = [p[0] for p in pairs] + [p[1] for p in pairs]
    pts = points_fn(images)
    n = len(pairs)
    rep, ms, tps, kp = [], [], [], []
    classes = {"acceptable": 0, "inaccurate": 0, "failed": 0}
    mee = []
    for k, (I1, I2, H) in enumerate(pairs):
        xy1, xy2 = pts[k], pts[n + k]
        d1 = upright_rootsift(I1, xy1, descriptor_size_px)
        d2 = upright_rootsift(I2, xy2, descriptor_size_px)
        i1, i2 = match_descriptors(d1, d2)
        m1, m2 = xy1[i1], xy2[i2]
        tp = true_positive_mask(m1, m2, H, eps_px)
        rep.append(repeatability(xy1, xy2, H, I1.shape, I2.shape, eps_px))
        ms.append(matching_score(xy1, xy2, m1, m2, H, I1.shape, I2.shape, eps_px))
        tps.append(int(tp.sum()))
        kp.append(0.5 * (len(xy1) + len(xy2)))
        H_est = None
        if len(i1) >= 4:
            H_est, _ = cv2.findHomography(m1, m2, cv2.RANSAC, 3.0)
        cls, err, _ = registration_class(
            H_est, H, six_fixed_points(I1.shape[1], I1.shape[0]), len(i1)
        )
        classes[cls] += 1
        if cls != "failed":
            mee.append(err)
    return {
        "repeatability": float(np.mean(rep)),
        "matching_score": float(np.mean(ms)),
        "n_tp": float(np.mean(tps)),
        "n_kp": float(np.mean(kp)),
        "acceptable": classes["acceptable"] / n,
        "inaccurate": classes["inaccurate"] / n,
        "failed": classes["failed"] / n,
        "median_mee": float(np.median(mee)) if mee else float("nan"),
        "pairs": float(n),
    }


def evaluate_sift(pairs: Sequence[Pair], cfg: TrainConfig) -> dict[str, float]:
    """The SIFT baseline: cv2.SIFT keypoints, same descriptor, matcher and criteria."""
    return evaluate_pairs(
        lambda imgs: [_sift_points(i) for i in imgs], pairs, cfg.eps_px, cfg.descriptor_size_px
    )


def evaluate_glampoints(net: UNet, pairs: Sequence[Pair], cfg: TrainConfig) -> dict[str, float]:
    """GLAMpoints (NMS window as in training, no top-k) on the validation pairs."""
    return evaluate_pairs(
        lambda imgs: _glampoints_points(net, imgs, cfg.nms_window_px),
        pairs,
        cfg.eps_px,
        cfg.descriptor_size_px,
    )


# ---------------------------------------------------------------------------------------------
# Checkpoints


def read_metrics(path: Path) -> list[dict[str, Any]]:
    """The records of a metrics.jsonl. A partial last line (a run killed while appending, with
    an older version that appended in place) is dropped with a warning; a bad line before the
    last is a corrupt log: TrainingError."""
    if not path.exists():
        return []
    try:
        lines = [ln for ln in path.read_text(encoding="utf-8").splitlines() if ln.strip()]
    except (OSError, UnicodeDecodeError) as exc:
        raise TrainingError(f"cannot read {path}: {exc}") from exc
    records = []
    for number, line in enumerate(lines, 1):
        try:
            record = json.loads(line)
            if not isinstance(record, dict):
                raise ValueError("not an object")
        except ValueError:
            if number == len(lines):
                log.warning("%s: dropping its partial last line %d", path, number)
                break
            raise TrainingError(
                f"{path} line {number} is not a JSON record: the log is corrupt "
                "(move it away to resume without it)"
            ) from None
        records.append(record)
    return records


def write_metrics(path: Path, records: Sequence[dict[str, Any]]) -> None:
    """metrics.jsonl rewritten whole, atomically (one JSON record per line)."""
    text = "".join(json.dumps(r) + "\n" for r in records)
    atomic_write(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))


def _rng_states() -> dict[str, Any]:
    name, keys, pos, has_gauss, cached = np.random.get_state()
    return {
        "torch": torch.get_rng_state(),
        "python": random.getstate(),
        "numpy": [name, torch.from_numpy(keys.astype(np.int64)), pos, has_gauss, cached],
    }


def _set_rng_states(states: dict[str, Any]) -> None:
    torch.set_rng_state(states["torch"])
    random.setstate(states["python"])
    name, keys, pos, has_gauss, cached = states["numpy"]
    np.random.set_state((name, keys.numpy().astype(np.uint32), pos, has_gauss, cached))


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """A training checkpoint (weights_only load); TrainingError if missing or unreadable."""
    path = Path(path)
    if not path.is_file():
        raise TrainingError(f"checkpoint not found: {path}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise TrainingError(f"cannot read checkpoint {path}: {first[:200]}") from exc
    if not isinstance(ckpt, dict) or "model" not in ckpt or "config" not in ckpt:
        raise TrainingError(f"{path} is not a GLAMpoints training checkpoint")
    return ckpt


def config_from_dict(d: dict[str, Any]) -> TrainConfig:
    """TrainConfig from its stored dict (unknown keys ignored, tuples restored)."""
    names = {f.name for f in dataclasses.fields(TrainConfig)}
    kwargs = {k: v for k, v in d.items() if k in names}
    if "betas" in kwargs:
        kwargs["betas"] = tuple(kwargs["betas"])
    return TrainConfig(**kwargs)


def _preprocess_name(cfg: dict[str, Any]) -> str:
    if not cfg.get("preprocess", True):
        return "grey"
    if cfg.get("preprocess_crops", False):
        return "green; crops: clahe+bilateral (the app's)"
    return "green+clahe"


def export_weights(checkpoint: str | Path, dest: str | Path) -> Path:
    """Write the model weights of a training checkpoint (+ a small metadata dict) to `dest`."""
    ckpt = load_checkpoint(checkpoint)
    cfg = ckpt["config"]
    meta = {
        "architecture": "UNet-4 (8,16,32,64,128), sigmoid output",
        "trained_epochs": int(ckpt.get("epochs_done", 0)),
        "trained_steps": int(ckpt.get("step", 0)),
        "git": str(ckpt.get("git", "unknown")),
        "nms_window_px": int(cfg.get("nms_window_px", 10)),
        "preprocess": _preprocess_name(cfg),
        "init": str(cfg.get("init", "")),
        "seed": int(cfg.get("seed", 0)),
        "val": {k: float(v) for k, v in (ckpt.get("val_last") or {}).items()},
        "val_sift": {k: float(v) for k, v in (ckpt.get("val_sift") or {}).items()},
    }
    dest = Path(dest)
    save_weights(ckpt["model"], dest, meta)
    log.info("exported %s -> %s (%.1f kB)", checkpoint, dest, dest.stat().st_size / 1024)
    return dest


# ---------------------------------------------------------------------------------------------
# Training loop


def _batch(
    bases: Sequence[np.ndarray], items: np.ndarray, cfg: TrainConfig, epoch: int
) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """Pairs of the given (image, k) items; each pair's generator depends on (seed, epoch, item)."""
    I1s, I2s, Hs = [], [], []
    for item in items.tolist():
        i = item // cfg.pairs_per_image
        k = item % cfg.pairs_per_image
        rng = np.random.default_rng([cfg.seed, 1, epoch, i, k])
        I1, I2, H = make_pair(bases[i], rng, cfg.crop)
        I1, I2 = augment(I1, rng, p_jpeg=cfg.jpeg_p), augment(I2, rng, p_jpeg=cfg.jpeg_p)
        if cfg.preprocess_crops:
            I1, I2 = frame_preprocess(I1), frame_preprocess(I2)
        I1s.append(I1)
        I2s.append(I2)
        Hs.append(H)
    return I1s, I2s, Hs


def _load_bases(files: Sequence[Path], cfg: TrainConfig) -> list[np.ndarray]:
    clahe = not cfg.preprocess_crops  # crops get CLAHE after their appearance changes instead
    return [load_base_image(p, cfg.preprocess, cfg.max_base_side, clahe) for p in files]


def validation_pairs(cfg: TrainConfig) -> list[Pair]:
    """The fixed validation pairs of a run, pre-processed as the training crops are."""
    pairs = fixed_pairs(
        _load_bases(list_images(cfg.val_dir), cfg),
        cfg.seed + 1000,
        cfg.val_pairs_per_image,
        cfg.val_crop,
    )
    if cfg.preprocess_crops:
        pairs = [(frame_preprocess(a), frame_preprocess(b), H) for a, b, H in pairs]
    return pairs


def _initial_weights(path: str) -> dict[str, torch.Tensor]:
    try:
        state, _ = load_weights(path)
    except WeightsError as exc:
        raise TrainingError(f"--init: {exc}") from exc
    return state


def _select_score(val: dict[str, float]) -> tuple[float, float]:
    """Model selection key: acceptable-registration fraction, then matching score."""
    return (val["acceptable"], val["matching_score"])


def _rewrite_metrics(path: Path, epochs_done: int) -> None:
    """Drop metrics lines of epochs a resumed run will redo."""
    if not path.exists():
        return
    records = read_metrics(path)
    write_metrics(path, [r for r in records if r.get("epoch", 0) <= epochs_done])


def _resume_state(ckpt: dict[str, Any], net: UNet, opt: torch.optim.Optimizer, path: Path) -> None:
    """Load a checkpoint's network and optimiser; TrainingError when it does not fit."""
    try:
        net.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        _set_rng_states(ckpt["rng"])
        int(ckpt["epoch"]), int(ckpt["step_in_epoch"]), int(ckpt["step"])
        dict(ckpt["val_sift"])
    except (KeyError, RuntimeError, ValueError, TypeError) as exc:
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:120]
        raise TrainingError(
            f"{path} does not fit this network or training code ({first}): "
            "resume it with the version that wrote it, or start a new output folder"
        ) from exc


def _settings(
    cfg: TrainConfig, resume: bool, last_path: Path
) -> tuple[TrainConfig, dict[str, Any] | None]:
    """The settings to train with and the checkpoint resumed from (None for a new training):
    a resumed training keeps its checkpoint's settings but RESUME_OVERRIDES."""
    if not resume:
        if last_path.exists():
            raise TrainingError(
                f"{last_path} exists: pass --resume or choose another output folder"
            )
        return cfg, None
    ckpt = load_checkpoint(last_path)
    stored = config_from_dict(ckpt["config"])
    overrides = {k: getattr(cfg, k) for k in RESUME_OVERRIDES}
    ignored = {
        k: (getattr(cfg, k), getattr(stored, k))
        for k in {f.name for f in dataclasses.fields(TrainConfig)} - set(RESUME_OVERRIDES)
        if getattr(cfg, k) != getattr(stored, k)
    }
    if ignored:
        log.warning("resuming with the checkpoint's settings, ignoring %s", sorted(ignored))
    return dataclasses.replace(stored, **overrides), ckpt


def _seed(cfg: TrainConfig) -> None:
    torch.set_num_threads(cfg.num_threads)
    cv2.setNumThreads(cfg.num_threads)
    torch.manual_seed(cfg.seed)
    random.seed(cfg.seed)
    np.random.seed(cfg.seed)


def _new_epoch_stats() -> dict[str, Any]:
    return {"loss": 0.0, "n_tp": 0.0, "n_kp": 0.0, "steps": 0, "time": 0.0}


class _Training:
    """One training's state (network, optimiser, where it stands, the best validation) and
    its steps, epochs and checkpoints."""

    def __init__(
        self,
        cfg: TrainConfig,
        ckpt: dict[str, Any] | None,
        names: list[str],
        val_pairs: list[Pair],
        out: Path,
    ):
        self.cfg, self.names = cfg, names
        self.last_path, self.best_path = out / "last.pt", out / "best.pt"
        self.metrics_path = out / "metrics.jsonl"
        # channels-last layout: about 2.5x faster convolutions on CPU (oneDNN) than NCHW
        self.net = UNet().to(memory_format=torch.channels_last)
        self.opt = torch.optim.Adam(self.net.parameters(), lr=cfg.lr, betas=tuple(cfg.betas))
        self.epoch, self.step_in_epoch, self.step = 0, 0, 0
        self.best: tuple[float, float] = (-math.inf, -math.inf)
        self.epoch_stats = _new_epoch_stats()
        if ckpt is None and cfg.init:
            try:
                self.net.load_state_dict(_initial_weights(cfg.init), strict=True)
            except RuntimeError as exc:
                raise TrainingError(f"--init {cfg.init} does not fit the UNet") from exc
            log.info("initialised from %s", cfg.init)
        if ckpt is not None:
            _resume_state(ckpt, self.net, self.opt, self.last_path)
            self.epoch, self.step_in_epoch = ckpt["epoch"], ckpt["step_in_epoch"]
            self.step = ckpt["step"]
            self.best = tuple(ckpt.get("best", self.best))  # type: ignore[assignment]
            self.epoch_stats = dict(ckpt.get("epoch_stats", self.epoch_stats))
            _rewrite_metrics(self.metrics_path, self.epoch)
            self.val_sift = {k: float(v) for k, v in ckpt["val_sift"].items()}
            log.info(
                "resumed at epoch %d step %d (global step %d)",
                self.epoch + 1,
                self.step_in_epoch,
                self.step,
            )
        else:
            log.info("validating SIFT baseline")
            self.val_sift = evaluate_sift(val_pairs, cfg)
            log.info("SIFT validation: %s", _fmt(self.val_sift))
        self.git = git_hash()
        self.val_last: dict[str, float] = dict(ckpt.get("val_last", {})) if ckpt else {}
        self.saved_step = self.step if ckpt is not None else None  # the step last.pt holds

    def save(self, path: Path) -> None:
        if path == self.last_path:
            self.saved_step = self.step
        atomic_torch_save(
            {
                "model": self.net.state_dict(),
                "optimizer": self.opt.state_dict(),
                "epoch": self.epoch,
                "step_in_epoch": self.step_in_epoch,
                "step": self.step,
                "epochs_done": self.epoch,
                "best": list(self.best),
                "epoch_stats": self.epoch_stats,
                "rng": _rng_states(),
                "config": asdict(self.cfg),
                "files": self.names,
                "git": self.git,
                "val_sift": self.val_sift,
                "val_last": self.val_last,
            },
            path,
        )

    def run_epoch(self, bases: list[np.ndarray], n_items: int, steps_per_epoch: int) -> bool:
        """The rest of the current epoch's steps; False where `max_steps` stopped it."""
        cfg = self.cfg
        order = np.random.default_rng([cfg.seed, 0, self.epoch]).permutation(n_items)
        bar = tqdm(
            total=steps_per_epoch,
            initial=self.step_in_epoch,
            desc=f"epoch {self.epoch + 1}/{cfg.epochs}",
            mininterval=5.0,
            dynamic_ncols=True,
        )
        try:
            while self.step_in_epoch < steps_per_epoch:
                if cfg.max_steps is not None and self.step >= cfg.max_steps:
                    return False
                first = self.step_in_epoch * cfg.batch_size
                loss, n_tp = self._step(bases, order[first : first + cfg.batch_size])
                bar.update(1)
                bar.set_postfix(loss=f"{loss:.4f}", tp=f"{n_tp:.1f}", refresh=False)
                if self.step % cfg.checkpoint_every == 0:
                    self.save(self.last_path)
        finally:
            bar.close()
        return True

    def _step(self, bases: list[np.ndarray], items: np.ndarray) -> tuple[float, float]:
        """One optimisation step on a batch; its loss and true positives."""
        cfg = self.cfg
        t_step = time.perf_counter()
        I1s, I2s, Hs = _batch(bases, items, cfg, self.epoch)
        rng = np.random.default_rng([cfg.seed, 2, self.epoch, self.step_in_epoch])
        out_step = glampoints_loss(self.net, I1s, I2s, Hs, cfg, rng)
        loss = float(out_step["total"].detach())
        if not math.isfinite(loss):  # stop before the step: the checkpoints stay good
            kept = "no checkpoint written yet"
            if self.saved_step is not None:
                kept = f"{self.last_path} holds step {self.saved_step}"
            raise TrainingError(
                f"non-finite loss at step {self.step + 1} (epoch {self.epoch + 1}): training "
                f"stopped, {kept} (try a lower --lr)"
            )
        self.opt.zero_grad(set_to_none=True)
        if out_step["mined"] > 0:
            out_step["total"].backward()
            self.opt.step()
        self.step_in_epoch += 1
        self.step += 1
        stats = self.epoch_stats
        stats["loss"] += loss
        stats["n_tp"] += out_step["n_tp"]
        stats["n_kp"] += out_step["n_kp"]
        stats["steps"] += 1
        stats["time"] += time.perf_counter() - t_step
        return loss, out_step["n_tp"]

    def end_epoch(self, val_pairs: list[Pair]) -> None:
        """Validate, record the epoch's metrics, keep the best and the last checkpoint."""
        val = evaluate_glampoints(self.net, val_pairs, self.cfg)
        stats = self.epoch_stats
        n = max(stats["steps"], 1)
        record = {
            "epoch": self.epoch + 1,
            "step": self.step,
            "train_loss": stats["loss"] / n,
            "train_n_tp": stats["n_tp"] / n,
            "train_n_kp": stats["n_kp"] / n,
            "s_per_step": stats["time"] / n,
            "val": val,
            "val_sift": self.val_sift,
        }
        write_metrics(self.metrics_path, [*read_metrics(self.metrics_path), record])
        log.info(
            "epoch %d: loss %.4f, train #TP %.1f, %.2f s/step | val GLAMpoints %s | SIFT %s",
            self.epoch + 1,
            record["train_loss"],
            record["train_n_tp"],
            record["s_per_step"],
            _fmt(val),
            _fmt(self.val_sift),
        )
        self.val_last = val
        self.epoch += 1
        self.step_in_epoch = 0
        self.epoch_stats = _new_epoch_stats()
        if _select_score(val) > self.best:
            self.best = _select_score(val)
            self.save(self.best_path)
            log.info("new best checkpoint (acceptable %.3f)", val["acceptable"])
        self.save(self.last_path)


def train(cfg: TrainConfig, resume: bool = False) -> dict[str, Any]:
    """Run (or resume) a training; returns a summary dict. Writes last.pt, best.pt and
    metrics.jsonl to cfg.out_dir."""
    out = Path(cfg.out_dir)
    cfg, ckpt = _settings(cfg, resume, out / "last.pt")
    out.mkdir(parents=True, exist_ok=True)
    _seed(cfg)

    files = list_images(cfg.data_dir)
    names = [p.name for p in files]
    if ckpt is not None and list(ckpt.get("files", [])) != names:
        raise TrainingError(f"the images in {cfg.data_dir} differ from the checkpoint's list")
    t0 = time.perf_counter()
    bases = _load_bases(files, cfg)  # the very files the checkpoint's list was checked against
    val_pairs = validation_pairs(cfg)
    log.info(
        "%d training images, %d validation pairs (%.1f s to load)",
        len(bases),
        len(val_pairs),
        time.perf_counter() - t0,
    )
    n_items = len(bases) * cfg.pairs_per_image
    steps_per_epoch = n_items // cfg.batch_size
    if steps_per_epoch == 0:
        raise TrainingError(
            f"{n_items} pairs per epoch is fewer than one batch of {cfg.batch_size}"
        )

    run = _Training(cfg, ckpt, names, val_pairs, out)
    run.net.train()
    while run.epoch < cfg.epochs and run.run_epoch(bases, n_items, steps_per_epoch):
        run.end_epoch(val_pairs)
    run.save(run.last_path)
    return {
        "epoch": run.epoch,
        "step": run.step,
        "step_in_epoch": run.step_in_epoch,
        "best": run.best,
    }


def _fmt(v: dict[str, float]) -> str:
    return (
        f"rep {v['repeatability']:.3f} M.score {v['matching_score']:.3f} #TP {v['n_tp']:.1f} "
        f"#kp {v['n_kp']:.0f} acceptable {v['acceptable']:.3f} failed {v['failed']:.3f}"
    )
