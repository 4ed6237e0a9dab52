"""`glampoints` command line: detect keypoints, train the detector, export weights, benchmark.

User errors (missing files, bad weights, bad folders, a training that cannot go on) print one
line on stderr and exit 2; Ctrl-C exits 130; an unexpected error prints one line and exits 1
(the traceback with -v where the command has it, else in the log at INFO).
"""

# (The docstring above is `glampoints --help`.) The `glampoints` console script lives in mosaic:
# detect, bench, export and evaluate use the application (its I/O, field-of-view mask,
# precision rule and evaluation), and the model package `glampoints` imports no mosaic. Beside
# `features`, this edge is the one mosaic module that imports glampoints. The application's
# modules are imported in the commands that need them, so that `train` starts without them.

from __future__ import annotations

import sys

try:  # Ctrl-C while the libraries load (torch takes seconds): exit 130, no traceback
    import json
    import logging
    from importlib.metadata import PackageNotFoundError, version
    from pathlib import Path
    from typing import Annotated, NoReturn

    import cv2
    import numpy as np
    import typer

    from glampoints.detector import DEFAULT_WEIGHTS, GlamPoints, WeightsError, benchmark
    from glampoints.synthetic import green_clahe
except KeyboardInterrupt:
    sys.stderr.write("interrupted\n")
    raise SystemExit(130) from None

app = typer.Typer(add_completion=False, no_args_is_help=True, help=__doc__)
log = logging.getLogger("glampoints")


def _print_version(value: bool) -> None:
    """`--version`: the installed retina-mosaic's (glampoints ships in it)."""
    if value:
        try:
            installed = version("retina-mosaic")
        except PackageNotFoundError:  # a source tree that was never installed
            installed = "unknown (not installed)"
        typer.echo(f"glampoints {installed}")
        raise typer.Exit()


@app.callback()
def _main(
    show_version: Annotated[
        bool,
        typer.Option(
            "--version", callback=_print_version, is_eager=True, help="Print the version and exit."
        ),
    ] = False,
) -> None:
    pass


def _fail(message: str) -> NoReturn:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code=2)


def _setup_logging(verbose: bool) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )


@app.command()
def detect(
    image: Annotated[Path, typer.Argument(help="input image (colour or grey)")],
    output: Annotated[
        Path | None, typer.Option("-o", "--output", help="write the image with keypoints drawn")
    ] = None,
    as_json: Annotated[
        bool, typer.Option("--json", help="print keypoints (xy, scores) as JSON")
    ] = False,
    weights: Annotated[Path | None, typer.Option(help="weights file (default: shipped)")] = None,
    max_keypoints: Annotated[int | None, typer.Option(min=1, help="keep the strongest N")] = None,
    nms_window: Annotated[int, typer.Option(min=1, help="NMS window in pixels")] = 10,
    preprocess: Annotated[
        bool, typer.Option(help="green channel + CLAHE first, as in training")
    ] = True,
    fov_mask: Annotated[
        bool,
        typer.Option(
            help="no keypoints on the dark border around the field of view (as the mosaic "
            "pipeline: [preprocess] fov_threshold, fov_erode_px)"
        ),
    ] = True,
) -> None:
    """Detect GLAMpoints keypoints in one image."""
    # mosaic's I/O (atomic writes, output checks) and field-of-view mask
    from mosaic.config import PreprocessConfig
    from mosaic.errors import MosaicError
    from mosaic.io import IMAGE_WRITE_SUFFIXES, check_output_path, read_image, write_image
    from mosaic.preprocess import field_of_view_mask, to_gray

    try:
        img = read_image(image)
        if output is not None:
            output = check_output_path(output, IMAGE_WRITE_SUFFIXES)
    except MosaicError as exc:
        _fail(str(exc))
    grey = green_clahe(img) if preprocess else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    mask = None
    if fov_mask:
        pre = PreprocessConfig()
        mask = field_of_view_mask(to_gray(img, True), pre.fov_threshold, pre.fov_erode_px)
    try:
        det = GlamPoints.from_pretrained(
            weights, nms_window_px=nms_window, max_keypoints=max_keypoints
        )
    except WeightsError as exc:
        _fail(str(exc))
    kps = det.detect(grey, mask)
    if output is not None:
        canvas = img.copy()
        for x, y in np.round(kps.xy).astype(int).tolist():
            cv2.circle(canvas, (x, y), 3, (0, 255, 0), 1, lineType=cv2.LINE_AA)
        try:
            write_image(output, canvas)
        except MosaicError as exc:
            _fail(str(exc))
    if as_json:
        typer.echo(json.dumps({"xy": kps.xy.tolist(), "scores": kps.scores.tolist()}))
    else:
        typer.echo(f"{len(kps)} keypoints")


@app.command()
def train(
    data: Annotated[Path, typer.Option(help="folder of training base images")],
    val: Annotated[Path, typer.Option(help="folder of validation base images")],
    out: Annotated[Path, typer.Option(help="output folder (checkpoints, metrics.jsonl)")],
    epochs: Annotated[int, typer.Option(min=1)] = 35,
    max_steps: Annotated[int | None, typer.Option(min=1, help="stop after N steps")] = None,
    resume: Annotated[bool, typer.Option(help="continue from OUT/last.pt")] = False,
    threads: Annotated[int, typer.Option(min=1, help="CPU threads")] = 2,
    seed: Annotated[int, typer.Option()] = 0,
    batch_size: Annotated[int, typer.Option(min=1)] = 5,
    pairs_per_image: Annotated[int, typer.Option(min=1)] = 7,
    init: Annotated[
        Path | None,
        typer.Option(help="start from these weights (weights file or checkpoint): fine-tuning"),
    ] = None,
    preprocess_crops: Annotated[
        bool,
        typer.Option(
            help="the app's CLAHE + bilateral on every augmented crop instead of CLAHE on the "
            "base image (measured worse on videos: see glampoints/training.py)"
        ),
    ] = False,
    descriptor_size: Annotated[
        float,
        typer.Option(min=1.0, help="keypoint diameter of the reward's root-SIFT descriptor"),
    ] = 10.0,
    lr: Annotated[float, typer.Option(min=0.0, help="Adam learning rate (paper: 1e-3)")] = 1e-3,
    jpeg_p: Annotated[
        float,
        typer.Option(
            min=0.0, max=1.0, help="probability of JPEG-compressing each crop (not the paper's)"
        ),
    ] = 0.0,
    verbose: Annotated[bool, typer.Option("-v", "--verbose")] = False,
) -> None:
    """Train GLAMpoints on synthetic pairs from the base images (the paper's schedule)."""
    from glampoints.training import TrainConfig, TrainingError
    from glampoints.training import train as run_training

    _setup_logging(verbose)
    cfg = TrainConfig(
        data_dir=str(data),
        val_dir=str(val),
        out_dir=str(out),
        epochs=epochs,
        max_steps=max_steps,
        num_threads=threads,
        seed=seed,
        batch_size=batch_size,
        pairs_per_image=pairs_per_image,
        preprocess_crops=preprocess_crops,
        init=str(init) if init else "",
        descriptor_size_px=descriptor_size,
        lr=lr,
        jpeg_p=jpeg_p,
    )
    try:
        summary = run_training(cfg, resume=resume)
    except TrainingError as exc:
        _fail(str(exc))
    typer.echo(f"stopped at epoch {summary['epoch']} step {summary['step']}", err=True)


@app.command()
def export(
    checkpoint: Annotated[Path, typer.Argument(help="training checkpoint (best.pt / last.pt)")],
    output: Annotated[
        Path,
        typer.Option(
            "-o", "--output", help="weights file to write (not the weights shipped in the package)"
        ),
    ],
) -> None:
    """Write the model weights of a training checkpoint as a shippable weights file."""
    from glampoints.training import TrainingError, export_weights
    from mosaic.io import same_file

    if same_file(output, DEFAULT_WEIGHTS):  # every run without --weights loads them
        _fail(
            f"{output} is the weights shipped in the package: export to another file "
            "(and copy it over them by hand to replace them on purpose)"
        )
    try:
        dest = export_weights(checkpoint, output)
    except (TrainingError, OSError) as exc:
        _fail(str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
    typer.echo(str(dest))


@app.command()
def bench(
    width: Annotated[int, typer.Option(min=16)] = 660,
    height: Annotated[int, typer.Option(min=16)] = 350,
    repeats: Annotated[int, typer.Option(min=1)] = 20,
    precision: Annotated[
        str,
        typer.Option(
            help="float32 | bfloat16 | auto (as the app: bfloat16 where the CPU has it in hardware)"
        ),
    ] = "auto",
    threads: Annotated[int | None, typer.Option(min=1)] = None,
    weights: Annotated[Path | None, typer.Option(help="weights file (default: shipped)")] = None,
) -> None:
    """Time the score map and NMS on the CPU for an image of WIDTH x HEIGHT."""
    import torch

    from glampoints.detector import cpu_has_native_bfloat16
    from mosaic.config import FeaturesConfig
    from mosaic.features import resolve_precision

    if threads is not None:
        torch.set_num_threads(threads)
    ran = resolve_precision(FeaturesConfig(precision=precision), cpu_has_native_bfloat16())
    try:
        det = GlamPoints.from_pretrained(weights, precision=ran)
    except (WeightsError, ValueError) as exc:
        _fail(str(exc))
    res = benchmark(det, (height, width), repeats)
    named = f"{ran} ({precision})" if precision == "auto" else ran
    typer.echo(
        f"{width}x{height} {named}, {int(res['threads'])} threads: "
        f"score map {res['score_map_ms']:.1f} ms (min {res['score_map_min_ms']:.1f}), "
        f"NMS {res['nms_ms']:.1f} ms (medians)"
    )


@app.command()
def evaluate(
    dataset: Annotated[Path, typer.Argument(help="dataset folder (FIRE, HPatches/Oxford, images)")],
    fmt: Annotated[
        str | None,
        typer.Option("--format", help="fire | hpatches | synthetic (default: guessed)"),
    ] = None,
    detector: Annotated[
        str | None, typer.Option(help="comma-separated detectors (default: all registered)")
    ] = None,
    out: Annotated[Path, typer.Option(help="folder for tables (CSV, JSON) and plots")] = Path(
        "evaluation"
    ),
    scale: Annotated[
        float | None,
        typer.Option(help="detection scale (default: 0.15 for fire, the paper's; 1 otherwise)"),
    ] = None,
    seed: Annotated[int, typer.Option(help="synthetic pairs: random seed")] = 0,
    pairs_per_image: Annotated[int, typer.Option(min=1, help="synthetic pairs per image")] = 4,
    max_pairs: Annotated[int, typer.Option(min=0, help="evaluate the first N pairs (0: all)")] = 0,
    config: Annotated[
        Path | None, typer.Option("--config", "-c", help="mosaic TOML config (pipeline stages)")
    ] = None,
    answers: Annotated[
        Path | None,
        typer.Option(
            help="FIRE: score the JSON lines of `mosaic register --pairs` at the control points "
            "instead of registering (the answer and H_moving_to_fixed)"
        ),
    ] = None,
    verbose: Annotated[bool, typer.Option("-v", "--verbose")] = False,
) -> None:
    """Compare detectors on image pairs with the paper's metrics and the FIRE protocol."""
    # the evaluation runs mosaic's pipeline stages
    from tqdm.contrib.logging import logging_redirect_tqdm

    from mosaic.config import load_config, with_overrides
    from mosaic.errors import MosaicError
    from mosaic.eval.common import parse_detectors
    from mosaic.eval.datasets import open_dataset
    from mosaic.eval.pair_eval import format_pair_tables, run_pair_evaluation, summarize_models
    from mosaic.features import FeatureExtractor

    _setup_logging(verbose)
    if answers is not None:
        _score_answers(dataset, fmt, answers, out)
        return
    try:
        with logging_redirect_tqdm():
            names = parse_detectors(detector)
            mosaic_config = load_config(config)
            for name in names if detector is not None else ():  # named: must load, or an error
                named = with_overrides(mosaic_config, features={"detector": name})
                FeatureExtractor(named.features)
            data = open_dataset(dataset, fmt, seed=seed, pairs_per_image=pairs_per_image)
            results, summary = run_pair_evaluation(
                data,
                mosaic_config,
                names,
                out,
                scale=scale,
                max_pairs=max_pairs,
                explicit=detector is not None,
                progress=True,
            )
    except (MosaicError, WeightsError) as exc:
        _fail(str(exc))
    typer.echo(format_pair_tables(summary, summarize_models(results)))
    typer.echo(f"tables and plots: {out}")


def _score_answers(dataset: Path, fmt: str | None, answers: Path, out: Path) -> None:
    """`evaluate --answers`: the FIRE protocol of `mosaic register --pairs` answers."""
    from mosaic.errors import MosaicError
    from mosaic.eval.pair_eval import (
        format_answer_table,
        read_answers,
        score_answers,
        write_answer_tables,
    )

    if fmt not in (None, "fire"):
        _fail(f"--answers scores FIRE pairs, not --format {fmt}")
    try:
        rows, summary = score_answers(dataset, read_answers(answers))
        write_answer_tables(rows, summary, out)
    except MosaicError as exc:
        _fail(str(exc))
    typer.echo(format_answer_table(summary))
    typer.echo(f"tables: {out}")


def main() -> None:
    """Console-script entry point: an unexpected exception (a bug) is one line and exit 1."""
    try:
        app()
    except Exception as exc:
        log.info("internal error", exc_info=True)
        text = (str(exc).strip().splitlines() or [""])[0]
        typer.echo(f"error: internal error: {type(exc).__name__}: {text}", err=True)
        raise SystemExit(1) from None
