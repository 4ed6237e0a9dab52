"""Make the documentation's pictures (docs/img/*.jpg) with the app's own commands.

    python docs/make_pictures.py [sample] [matches] [hard] [evaluation] [curved] [curved-val]
                                 [compare] [--work DIR] [--force]

Each picture runs `mosaic ...` commands (printed as they run; their outputs go to the work
folder, default /tmp/retina-mosaic-pictures, and are reused unless --force), then frames
their outputs into a small JPEG with OpenCV. No argument: all of them.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
IMG = REPO / "docs" / "img"
SAMPLE = REPO / "samples" / "sample.mp4"
QUALITY = 85  # JPEG
GAP = 8  # px between tiles
WHITE = (255, 255, 255)


def run(command: str, work: Path, makes: Path, force: bool) -> None:
    """Run a command in `work`, unless what it makes is already there."""
    if makes.exists() and not force:
        print(f"(kept) {command}")
        return
    print(f"$ {command}", flush=True)
    subprocess.run(shlex.split(command), cwd=work, check=True)


def frames_of(video: Path, indices: list[int]) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(video))
    out, i = {}, 0
    while len(out) < len(indices):
        ok, frame = cap.read()
        if not ok:
            break
        if i in indices:
            out[i] = frame
        i += 1
    cap.release()
    return [out[i] for i in indices]


def fit(image: np.ndarray, width: int | None = None, height: int | None = None) -> np.ndarray:
    h, w = image.shape[:2]
    f = width / w if width is not None else height / h
    size = (max(1, round(w * f)), max(1, round(h * f)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def label(image: np.ndarray, text: str) -> np.ndarray:
    out = image.copy()
    font, scale = cv2.FONT_HERSHEY_SIMPLEX, 0.55
    (w, h), base = cv2.getTextSize(text, font, scale, 1)
    cv2.rectangle(out, (0, 0), (w + 12, h + base + 10), (0, 0, 0), -1)
    cv2.putText(out, text, (6, h + 5), font, scale, WHITE, 1, cv2.LINE_AA)
    return out


def row(tiles: list[np.ndarray]) -> np.ndarray:
    height = max(t.shape[0] for t in tiles)
    padded = []
    for i, t in enumerate(tiles):
        pad = np.full((height, t.shape[1] + (GAP if i else 0), 3), WHITE, np.uint8)
        pad[: t.shape[0], (GAP if i else 0) :] = t
        padded.append(pad)
    return np.hstack(padded)


def column(tiles: list[np.ndarray]) -> np.ndarray:
    width = max(t.shape[1] for t in tiles)
    padded = []
    for i, t in enumerate(tiles):
        pad = np.full((t.shape[0] + (GAP if i else 0), width, 3), WHITE, np.uint8)
        pad[(GAP if i else 0) :, : t.shape[1]] = t
        padded.append(pad)
    return np.vstack(padded)


def save(name: str, image: np.ndarray) -> None:
    path = IMG / name
    cv2.imwrite(str(path), image, [cv2.IMWRITE_JPEG_QUALITY, QUALITY])
    print(
        f"wrote {path.relative_to(REPO)} ({image.shape[1]}x{image.shape[0]}, "
        f"{path.stat().st_size // 1024} KB)"
    )


def sample(work: Path, force: bool) -> None:
    """docs/img/sample.jpg: frames 0, 24 and 47 of the sample clip beside its mosaic."""
    run(f"mosaic build {SAMPLE} -o sample/mosaic.png", work, work / "sample" / "mosaic.png", force)
    frames = [fit(f, width=300) for f in frames_of(SAMPLE, [0, 24, 47])]
    frames = [label(f, f"frame {i}") for f, i in zip(frames, [0, 24, 47], strict=True)]
    left = column(frames)
    mosaic = label(
        fit(cv2.imread(str(work / "sample" / "mosaic.png")), height=left.shape[0]),
        "mosaic (48 frames)",
    )
    save("sample.jpg", row([left, mosaic]))


def matches(work: Path, force: bool) -> None:
    """docs/img/matches.jpg: frames 0 and 16 of the sample clip, keypoints and inlier matches."""
    for i, frame in zip((0, 16), frames_of(SAMPLE, [0, 16]), strict=True):
        if force or not (work / f"frame{i:02d}.png").exists():
            cv2.imwrite(str(work / f"frame{i:02d}.png"), frame)
    run(
        "mosaic register frame00.png frame16.png --matches matches.png",
        work,
        work / "matches.png",
        force,
    )
    save("matches.jpg", fit(cv2.imread(str(work / "matches.png")), width=960))


def hard(work: Path, force: bool) -> None:
    """docs/img/hard_chain_vs_keyframes.jpg: a hard synthetic video, both strategies."""
    run(
        "mosaic synth -o hard_s11.mp4 --hard --frames 150 --seed 11",
        work,
        work / "hard_s11.mp4",
        force,
    )
    tiles = []
    for strategy in ("keyframes", "chain"):
        out = work / "hard" / f"{strategy}.png"
        run(
            f"mosaic build hard_s11.mp4 -o hard/{strategy}.png --strategy {strategy}",
            work,
            out,
            force,
        )
        tiles.append(cv2.imread(str(out)))
    run(
        "mosaic evaluate hard_s11.mp4 --detector glampoints --strategy keyframes,chain "
        "--out evalhard",
        work,
        work / "evalhard" / "video_summary.csv",
        force,
    )  # the caption
    # a detail at 1:1 around where each mosaic put the centre of frame 120
    h, w, crops = 300, 420, []
    for tile, strategy in zip(tiles, ("keyframes", "chain"), strict=True):
        report = json.loads((work / "hard" / f"{strategy}.json").read_text())
        H = np.array(next(f for f in report["frames"] if f["index"] == 120)["H_to_canvas"])
        x, y = (H @ [330.0, 175.0, 1.0])[:2] / (H @ [330.0, 175.0, 1.0])[2]
        x0 = int(np.clip(x - w / 2, 0, tile.shape[1] - w))
        y0 = int(np.clip(y - h / 2, 0, tile.shape[0] - h))
        crops.append(label(tile[y0 : y0 + h, x0 : x0 + w], f"{strategy}: frame 120, 1:1"))
    wholes = [label(fit(t, width=w), s) for t, s in zip(tiles, ("keyframes", "chain"), strict=True)]
    save("hard_chain_vs_keyframes.jpg", column([row(wholes), row(crops)]))


def evaluation(work: Path, force: bool) -> None:
    """docs/img/video_error.jpg, video_frames_until_failure.jpg: `mosaic evaluate`'s plots."""
    for seed in (1, 2):
        run(
            f"mosaic synth -o real{seed}.mp4 --realistic --frames 60 --seed {seed}",
            work,
            work / f"real{seed}.mp4",
            force,
        )
    run(
        "mosaic evaluate real1.mp4 real2.mp4 --detector glampoints,sift --out eval",
        work,
        work / "eval" / "video_error.png",
        force,
    )
    for name in ("video_error", "video_frames_until_failure"):
        save(f"{name}.jpg", fit(cv2.imread(str(work / "eval" / f"{name}.png")), width=720))


def _curved(work: Path, force: bool, source: str, folder: str) -> np.ndarray:
    """A curved pair (`mosaic synth --curved-pairs`: C01 of the measured set, seed 0) registered
    by `mosaic register --model homography` and `--model quadratic`: both `--warp`
    checkerboards, and 1:1 details around the control point the homography misses most."""
    run(
        f"mosaic synth {source} --curved-pairs 1 --seed 0 -o {folder}".replace("  ", " "),
        work,
        work / folder / "pairs.csv",
        force,
    )
    images = f"{folder}/Images/C01_1.jpg {folder}/Images/C01_2.jpg"
    points = np.loadtxt(work / folder / "Ground Truth" / "control_points_C01_1_2.txt")
    checks, errors = {}, {}
    for model in ("homography", "quadratic"):
        out = work / folder / f"{model}.png"
        if force or not out.exists():
            command = f"mosaic register {images} --model {model} --warp {folder}/{model}.png --json"
            print(f"$ {command} > {folder}/{model}.json", flush=True)
            result = subprocess.run(
                shlex.split(command), cwd=work, check=True, capture_output=True, text=True
            )
            (work / folder / f"{model}.json").write_text(result.stdout)
        answer = json.loads((work / folder / f"{model}.json").read_text())
        warped = cv2.imread(str(out))
        checks[model] = warped[:, warped.shape[1] // 2 :]  # the checkerboard half
        xy = np.column_stack([points[:, 2:], np.ones(len(points))])
        if answer["Q_moving_to_fixed"] is not None:
            x, y = xy[:, 0], xy[:, 1]
            mapped = (
                np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)])
                @ np.array(answer["Q_moving_to_fixed"]).T
            )
        else:
            p = xy @ np.array(answer["H_moving_to_fixed"]).T
            mapped = p[:, :2] / p[:, 2:]
        errors[model] = np.linalg.norm(mapped - points[:, :2], axis=1)
    worst = int(np.argmax(errors["homography"]))
    cx, cy = points[worst, :2]
    h, w = 360, 480
    wholes, crops = [], []
    for model, check in checks.items():
        x0 = int(np.clip(cx - w / 2, 0, check.shape[1] - w))
        y0 = int(np.clip(cy - h / 2, 0, check.shape[0] - h))
        detail = check[y0 : y0 + h, x0 : x0 + w].copy()
        cv2.circle(detail, (round(cx - x0), round(cy - y0)), 12, (0, 255, 255), 2, cv2.LINE_AA)
        e = errors[model]
        wholes.append(label(fit(check, width=w), f"{model}: mean error {e.mean():.1f} px"))
        crops.append(label(detail, f"1:1, the circled point {e[worst]:.1f} px off"))
    return column([row(wholes), row(crops)])


def curved(work: Path, force: bool) -> None:
    """docs/img/curved_pair.jpg: a curved pair rendered from the CC0 sample, registered with
    the homography and with the quadratic (`--warp` checkerboards)."""
    save("curved_pair.jpg", _curved(work, force, "", "curved_sample"))


def curved_val(work: Path, force: bool) -> None:
    """The same for a curved pair rendered from a validation photograph (not shipped: the LMC
    photographs may not be redistributed, so this picture stays in the work folder)."""
    val = REPO.parent / "shared" / "data" / "retina" / "val" / "lmc"
    picture = _curved(work, force, str(val), "curved_val")
    path = work / "curved_val_pair.jpg"
    cv2.imwrite(str(path), picture, [cv2.IMWRITE_JPEG_QUALITY, QUALITY])
    print(f"wrote {path} (not under docs/img: rendered from a photograph we may not ship)")


def compare(work: Path, force: bool) -> None:
    """docs/img/compare_visits.jpg: `mosaic compare` of two synthetic visits of one eye (the
    follow-up with a haemorrhage, a narrowed vessel and laser scars planted)."""
    out = work / "compare"
    out.mkdir(exist_ok=True)
    run("mosaic synth -o compare/base.mp4 --seed 0 --frames 60", work, out / "base.mp4", force)
    run(
        "mosaic synth -o compare/follow.mp4 --seed 1 --frames 60 --followup-of compare/base.mp4",
        work,
        out / "follow.mp4",
        force,
    )
    run(
        "mosaic compare compare/base.mp4 compare/follow.mp4 -o compare/out",
        work,
        out / "out" / "compare.json",
        force,
    )
    names = [("baseline_mosaic.png", "baseline mosaic"),
             ("followup_warped.png", "follow-up on the baseline's map"),
             ("checkerboard.png", "checkerboard"), ("overlay.png", "two-colour overlay"),
             ("change_map.png", "change map, regions boxed")]  # fmt: skip
    tiles = [label(fit(cv2.imread(str(out / "out" / n)), width=320), t) for n, t in names]
    save("compare_visits.jpg", column([row(tiles[:3]), row(tiles[3:])]))


PICTURES = {
    "sample": sample,
    "matches": matches,
    "hard": hard,
    "evaluation": evaluation,
    "curved": curved,
    "curved-val": curved_val,
    "compare": compare,
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("pictures", nargs="*", help=", ".join(PICTURES) + " (default: all)")
    parser.add_argument("--work", type=Path, default=Path("/tmp/retina-mosaic-pictures"))
    parser.add_argument("--force", action="store_true", help="rerun the commands")
    args = parser.parse_args()
    unknown = set(args.pictures) - set(PICTURES)
    if unknown:
        parser.error(f"unknown picture(s) {', '.join(sorted(unknown))}")
    args.work.mkdir(parents=True, exist_ok=True)
    (args.work / "sample").mkdir(exist_ok=True)
    (args.work / "hard").mkdir(exist_ok=True)
    IMG.mkdir(parents=True, exist_ok=True)
    for name in args.pictures or PICTURES:
        PICTURES[name](args.work.resolve(), args.force)


if __name__ == "__main__":
    main()
