"""Image-pair datasets with ground truth, for `glampoints evaluate`.

Three layouts, each yielding `Pair`s (image 1 = reference, image 2 = transformed):
- `fire`: the FIRE retinal registration set: `Images/XNN_1.jpg`, `Images/XNN_2.jpg` and
  `Ground Truth/control_points_XNN_1_2.txt` (lines `x1 y1 x2 y2`, the same retina point in
  image 1 and image 2); the category is the first letter of XNN (S, P or A).
- `hpatches`: one folder per sequence with images `1..6` (`1.ppm` or Oxford's `img1.ppm`; ppm,
  pgm, png or jpg) and homographies `H_1_N` (HPatches) or `H1toNp` (Oxford) mapping image 1
  into image N. The root may be one sequence or a folder of sequences.
- `synthetic`: a folder of images; pairs come from the training generator's homography ranges
  (`glampoints.synthetic.fixed_pairs`), the same set for the same seed.

Images are loaded lazily, one pair at a time (FIRE images are 2912x2912).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from mosaic.errors import InputError
from mosaic.features import HomographyRanges, fixed_pairs
from mosaic.io import natural_key, read_image

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".ppm", ".pgm", ".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
FIRE_CATEGORIES = ("S", "P", "A")
SYNTHETIC_MAX_SIDE_PX = 800  # base images are downscaled to this, as in training


@dataclass(frozen=True)
class Pair:
    """Two images of the same scene with ground truth: a homography or control points."""

    name: str
    category: str  # FIRE: S / P / A; HPatches: i / v; Oxford: the sequence; synthetic: ""
    image1: np.ndarray  # BGR uint8, the reference
    image2: np.ndarray  # BGR uint8
    H_1_to_2: np.ndarray | None = None  # 3x3 float64 ground truth (homography datasets)
    control_points: np.ndarray | None = None  # (N, 4) float64 rows x1 y1 x2 y2 (FIRE)


@dataclass(frozen=True)
class PairDataset:
    """Named pairs loaded on demand; `len` is known before any image is read."""

    root: Path
    format: str
    names: tuple[str, ...]
    loaders: tuple[Callable[[], Pair], ...]

    def __len__(self) -> int:
        return len(self.loaders)

    def __iter__(self) -> Iterator[Pair]:
        for load in self.loaders:
            yield load()


def _images_in(folder: Path) -> list[Path]:
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    return sorted(files, key=lambda p: natural_key(p.name))


def read_matrix(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """Whitespace- or comma-separated numbers of a text file as a float64 array of `shape`."""
    try:
        values = np.array(path.read_text(encoding="utf-8").replace(",", " ").split(), float)
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"cannot read numbers from {path}: {exc}") from exc
    rows, cols = shape
    if rows < 0:  # any number of rows
        if values.size == 0 or values.size % cols:
            raise InputError(f"{path} must hold rows of {cols} numbers, got {values.size}")
        return values.reshape(-1, cols)
    if values.size != rows * cols or not np.isfinite(values).all():
        raise InputError(f"{path} must hold {rows}x{cols} finite numbers, got {values.size}")
    return values.reshape(rows, cols)


# --------------------------------------------------------------------------------------------
# FIRE
# --------------------------------------------------------------------------------------------

_FIRE_GT = re.compile(r"control_points_(\w+?)_1_2\.txt$")


def fire_truth(root: Path) -> list[tuple[str, Path]]:
    """(pair name, control-point file) of each pair of a FIRE folder (`Images/` and
    `Ground Truth/control_points_XNN_1_2.txt`), in natural order."""
    images, truth = root / "Images", root / "Ground Truth"
    if not images.is_dir() or not truth.is_dir():
        raise InputError(f"{root} is not a FIRE folder (needs 'Images/' and 'Ground Truth/')")
    found = [
        (m.group(1), gt)
        for gt in sorted(truth.iterdir(), key=lambda p: natural_key(p.name))
        if (m := _FIRE_GT.match(gt.name)) is not None
    ]
    if not found:
        raise InputError(f"no control_points_*_1_2.txt files in {truth}")
    return found


def fire_category(name: str) -> str:
    """FIRE's category of a pair (S, P or A: the name's first letter), "" for others."""
    return name[0].upper() if name[:1].upper() in FIRE_CATEGORIES else ""


def load_fire(root: Path) -> PairDataset:
    """The FIRE layout: `Images/` and `Ground Truth/control_points_XNN_1_2.txt`."""
    images = root / "Images"
    names, loaders = [], []
    for name, gt in fire_truth(root):
        first = [images / f"{name}_1{s}" for s in (".jpg", ".png", ".tif", ".jpeg")]
        found = [p for p in first if p.is_file()]
        if not found:
            raise InputError(f"FIRE pair {name}: image {images / (name + '_1.jpg')} not found")
        path1 = found[0]
        path2 = path1.with_name(f"{name}_2{path1.suffix}")
        names.append(name)
        loaders.append(_fire_loader(name, path1, path2, gt))
    return PairDataset(root, "fire", tuple(names), tuple(loaders))


def _fire_loader(name: str, path1: Path, path2: Path, gt: Path) -> Callable[[], Pair]:
    def load() -> Pair:
        points = read_matrix(gt, (-1, 4))
        return Pair(name, fire_category(name), read_image(path1), read_image(path2), None, points)

    return load


# --------------------------------------------------------------------------------------------
# HPatches / Oxford
# --------------------------------------------------------------------------------------------

_H_NAMES = ("H_1_{n}", "H1to{n}p", "H1to{n}")


def _sequence_pairs(folder: Path) -> list[tuple[Path, Path, Path]]:
    """(image 1, image N, H_1_N) triples of one HPatches / Oxford sequence folder."""
    by_index: dict[int, Path] = {}
    for p in _images_in(folder):
        m = re.fullmatch(r"(?:img)?(\d+)", p.stem, flags=re.IGNORECASE)
        if m is not None:
            by_index.setdefault(int(m.group(1)), p)
    if 1 not in by_index:
        return []
    triples = []
    for n in sorted(by_index):
        if n == 1:
            continue
        for pattern in _H_NAMES:
            h_path = folder / pattern.format(n=n)
            if h_path.is_file():
                triples.append((by_index[1], by_index[n], h_path))
                break
    return triples


def load_hpatches(root: Path) -> PairDataset:
    """HPatches (`1.ppm`, `H_1_2`, ...) or Oxford (`img1.ppm`, `H1to2p`, ...) sequences."""
    folders = [root, *sorted((p for p in root.iterdir() if p.is_dir()), key=lambda p: p.name)]
    names, loaders = [], []
    for folder in folders:
        for path1, path_n, h_path in _sequence_pairs(folder):
            seq = folder.name
            category = seq.split("_", 1)[0] if "_" in seq else seq
            name = f"{seq}/{path1.stem}-{path_n.stem}"
            names.append(name)
            loaders.append(_hpatches_loader(name, category, path1, path_n, h_path))
    if not names:
        raise InputError(f"no HPatches/Oxford sequences (1.ppm + H_1_2 or H1to2p) in {root}")
    return PairDataset(root, "hpatches", tuple(names), tuple(loaders))


def _hpatches_loader(
    name: str, category: str, path1: Path, path2: Path, h_path: Path
) -> Callable[[], Pair]:
    def load() -> Pair:
        H = read_matrix(h_path, (3, 3))
        return Pair(name, category, read_image(path1), read_image(path2), H / H[2, 2])

    return load


# --------------------------------------------------------------------------------------------
# Synthetic pairs from the training generator
# --------------------------------------------------------------------------------------------


def _base_image(path: Path, max_side: int) -> np.ndarray:
    """Green channel of a fundus image (best vessel contrast), longest side <= max_side."""
    image = read_image(path)
    green = np.ascontiguousarray(image[:, :, 1])
    scale = max_side / max(green.shape)
    if scale < 1.0:
        size = (round(green.shape[1] * scale), round(green.shape[0] * scale))
        green = cv2.resize(green, size, interpolation=cv2.INTER_AREA)
    return green


def load_synthetic(
    root: Path,
    seed: int = 0,
    pairs_per_image: int = 4,
    crop_px: int = 256,
    ranges: HomographyRanges | None = None,
) -> PairDataset:
    """Pairs warped from each image of `root` with the training generator's ranges.

    Pair k of image i is the same for the same seed whatever else is in the folder's order
    (`fixed_pairs` seeds each pair with (seed, i, k)); appearance changes are applied too.
    The images are small (crop_px square), so they are made up front.
    """
    files = _images_in(root)
    if not files:
        raise InputError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in {root}")
    bases = [_base_image(p, SYNTHETIC_MAX_SIDE_PX) for p in files]
    made = fixed_pairs(
        bases, seed, pairs_per_image, crop=crop_px, ranges=ranges or HomographyRanges()
    )
    names, loaders = [], []
    for k, (I1, I2, H) in enumerate(made):
        name = f"{files[k // pairs_per_image].stem}#{k % pairs_per_image}"
        pair = Pair(
            name, "", cv2.cvtColor(I1, cv2.COLOR_GRAY2BGR), cv2.cvtColor(I2, cv2.COLOR_GRAY2BGR), H
        )
        names.append(name)
        loaders.append(lambda pair=pair: pair)
    return PairDataset(root, "synthetic", tuple(names), tuple(loaders))


# --------------------------------------------------------------------------------------------
# Entry point
# --------------------------------------------------------------------------------------------

FORMATS: dict[str, Callable[..., PairDataset]] = {
    "fire": load_fire,
    "hpatches": load_hpatches,
    "synthetic": load_synthetic,
}


def detect_format(root: Path) -> str:
    """Guess the layout of a dataset folder: fire, hpatches or synthetic."""
    if (root / "Images").is_dir() and (root / "Ground Truth").is_dir():
        return "fire"
    folders = [root] + [p for p in root.iterdir() if p.is_dir()]
    if any(_sequence_pairs(f) for f in folders):
        return "hpatches"
    return "synthetic"


def open_dataset(
    root: str | Path, fmt: str | None = None, seed: int = 0, pairs_per_image: int = 4
) -> PairDataset:
    """The pairs of a dataset folder in layout `fmt` (guessed when None)."""
    path = Path(root).expanduser()
    if not path.is_dir():
        raise InputError(f"dataset folder not found: {path}")
    fmt = fmt or detect_format(path)
    if fmt not in FORMATS:
        raise InputError(f"unknown dataset format {fmt!r} (choices: {', '.join(FORMATS)})")
    if fmt == "synthetic":
        if pairs_per_image < 1:
            raise InputError(f"pairs per image must be >= 1, got {pairs_per_image}")
        dataset = load_synthetic(path, seed=seed, pairs_per_image=pairs_per_image)
    else:
        dataset = FORMATS[fmt](path)
    log.info("dataset %s: %s layout, %d pairs", path, fmt, len(dataset))
    return dataset
