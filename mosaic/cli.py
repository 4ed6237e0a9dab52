"""`mosaic` command line: build, batch, synth, register, compare, evaluate, bench. The only
module of `mosaic` importing typer.

Every `MosaicError` (bad path, unreadable video, invalid config or weights, ...) becomes one line
on stderr and exit code 2. `build` and `batch` run each video through `runner.run_video`: Ctrl-C
still writes the partial mosaic and report (exit 130), and a failure while refining or
re-rendering writes the live mosaic (exit 1). Each command parses its options, calls the
application and prints; what it prints without typer is made in `cli_support`.
"""

from __future__ import annotations

import sys

try:  # Ctrl-C while the libraries load (torch takes seconds): exit 130, no traceback
    import json
    import logging
    import time
    from collections.abc import Iterator
    from contextlib import contextmanager
    from importlib.metadata import PackageNotFoundError, version
    from pathlib import Path
    from typing import Annotated, Any

    import typer
    from tqdm.contrib.logging import logging_redirect_tqdm

    from mosaic.cli_support import (
        options_config,
        pair_text,
        require_detectors,
        setup_logging,
        summary_text,
        terminate_as_interrupt,
        viewer_args,
    )
    from mosaic.config import Config, for_photographs, load_config, with_overrides
    from mosaic.errors import InputError, MosaicError
    from mosaic.features import DETECTORS, FeatureExtractor
    from mosaic.io import (
        IMAGE_WRITE_SUFFIXES,
        REPORT_SUFFIXES,
        VideoInfo,
        check_distinct_paths,
        check_output_path,
        open_frames,
    )
    from mosaic.pair_files import pair_answer, pairs_file_answers
    from mosaic.registration import MODELS
    from mosaic.runner import Outputs, one_line, run_video
    from mosaic.synthetic.request import SynthRequest, parse_size, synthesize
    from mosaic.viz import VIEWER_MODES, RerunViewer, Viewer, make_viewer
except KeyboardInterrupt:
    sys.stderr.write("interrupted\n")
    raise SystemExit(130) from None

PAIR_MODELS = (*MODELS, "quadratic")  # `register`: photographs of a curved retina
BENCH_DETECTORS = "glampoints,sift,orb,akaze"

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="Retinal video mosaicking with GLAMpoints keypoints.",
)
log = logging.getLogger("mosaic")

EXIT_FAILED = 1
EXIT_USER_ERROR = 2
EXIT_INTERRUPTED = 130
VERBOSE_HELP = "Log each stage's details (INFO), OpenCV's own lines and an error's traceback."


# Options several commands share (and, above each command, those whose help takes lines):
# named once, so that each command's signature stays short.
Verbose = Annotated[bool, typer.Option("--verbose", "-v", help=VERBOSE_HELP)]
ConfigFile = Annotated[
    Path | None, typer.Option("--config", "-c", help="TOML config (see sample_config.toml).")
]
MaxFrames = Annotated[int | None, typer.Option(help="Stop after N frames (0: all).")]
Step = Annotated[int | None, typer.Option(help="Process every K-th frame.")]
ViewerFlag = Annotated[bool, typer.Option("--viewer", help="Short for --rerun spawn.")]


def package_version() -> str:
    """The installed version of retina-mosaic (both `mosaic` and `glampoints` ship in it)."""
    try:
        return version("retina-mosaic")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown (not installed)"


def _print_version(value: bool) -> None:
    if value:
        typer.echo(f"mosaic {package_version()}")
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


@contextmanager
def _user_errors() -> Iterator[None]:
    """Turn errors a user can act on into one line on stderr and exit code 2."""
    try:
        yield
    except MosaicError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(EXIT_USER_ERROR) from None


def _serve_until_interrupted(url: str | None) -> None:
    """Keep the rerun server (and the recording it buffers) alive for late viewers."""
    typer.echo(f"still serving the recording at {url} (Ctrl-C to stop)")
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass


def _build_paths(
    video: Path,
    output: Path,
    report: Path | None,
    config_path: Path | None,
    rerun: tuple[str, str | None, bool],
) -> tuple[Path, Path, str, str | None]:
    """`build`'s outputs checked (writable, none over an input or another output): the mosaic,
    the report, and the viewer's mode and target from (--rerun, --rerun-target, --viewer)."""
    output = check_output_path(output, IMAGE_WRITE_SUFFIXES)
    report_path = report or output.with_suffix(".json")
    mode, target = viewer_args(*rerun, output)
    recording = {"--rerun-target": Path(str(target))} if mode == "save" else {}
    check_distinct_paths(
        {"--output": output, "--report": report_path, **recording},
        {"VIDEO": video} | ({"--config": config_path} if config_path else {}),
    )
    return output, check_output_path(report_path, REPORT_SUFFIXES), mode, target


# `build`'s options whose help takes lines
BuildRerun = Annotated[
    str,
    typer.Option(
        help=f"Live rerun viewer: {' | '.join(VIEWER_MODES)} (serve prints a browser URL)."
    ),
]
BuildRerunTarget = Annotated[
    str | None,
    typer.Option(
        help="save: the .rrd file (default: next to the output); "
        "connect: the viewer's URL (default rerun+http://127.0.0.1:9876/proxy)."
    ),
]


@app.command()
def build(
    video: Annotated[Path, typer.Argument(help="Video file OpenCV reads, or a folder of frames.")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Mosaic image (PNG).")] = Path(
        "mosaic.png"
    ),
    config_path: ConfigFile = None,
    detector: Annotated[
        str | None, typer.Option(help=f"Keypoint detector: {', '.join(DETECTORS)}.")
    ] = None,
    report: Annotated[
        Path | None, typer.Option(help="Report JSON (default: next to the output, .json).")
    ] = None,
    max_frames: MaxFrames = None,
    step: Step = None,
    strategy: Annotated[
        str | None, typer.Option(help="keyframes (default) | chain (the paper's frame-to-frame).")
    ] = None,
    on_failure: Annotated[
        str | None, typer.Option(help="stop | skip | restart (new mosaic segment).")
    ] = None,
    rerun: BuildRerun = "off",
    rerun_target: BuildRerunTarget = None,
    viewer_flag: ViewerFlag = False,
    rerun_canvas_every: Annotated[
        int, typer.Option(min=1, help="Send the mosaic canvas to the viewer every N frames.")
    ] = 10,
    verbose: Verbose = False,
) -> None:
    """Build a retina mosaic from a video, streaming frame by frame."""
    setup_logging(verbose)
    made: list[Viewer] = []
    try:
        with _user_errors(), terminate_as_interrupt():
            config = options_config(
                config_path,
                detector,
                max_frames=max_frames,
                step=step,
                on_failure=on_failure,
                strategy=strategy,
            )
            output, report_path, rerun, rerun_target = _build_paths(
                video, output, report, config_path, (rerun, rerun_target, viewer_flag)
            )

            def viewer(info: VideoInfo) -> Viewer:  # made once the input is open
                made.append(
                    make_viewer(rerun, rerun_target, config, info, canvas_every=rerun_canvas_every)
                )
                if isinstance(made[-1], RerunViewer) and made[-1].url:
                    typer.echo(f"rerun viewer: {made[-1].url}")
                return made[-1]

            run = run_video(
                video,
                config,
                Outputs(mosaic=output, report=report_path),
                viewer=viewer,
                progress="mosaic",
                opener=open_frames,  # looked up here: tests replace it
            )
            if run.interrupted:
                typer.echo("interrupted: partial mosaic and report written", err=True)
            elif run.error is not None:
                typer.echo(f"error: {run.error}; the live mosaic and report written", err=True)
            typer.echo(summary_text(run.report, output, report_path))
            if rerun == "save":
                typer.echo(f"recording: {rerun_target}")
    except KeyboardInterrupt:  # before the first frame or while writing: nothing to save
        typer.echo("interrupted", err=True)
        raise typer.Exit(EXIT_INTERRUPTED) from None
    if run.interrupted or run.error is not None:
        raise typer.Exit(EXIT_INTERRUPTED if run.interrupted else EXIT_FAILED)
    if rerun == "serve":
        _serve_until_interrupted(getattr(made[0] if made else None, "url", None))


# `batch`'s options whose help takes lines
BatchInput = Annotated[
    Path,
    typer.Argument(
        metavar="INPUT",
        help="Folder searched recursively for videos and folders of frames, or a CSV "
        "manifest (columns video, optional config and id; patient and/or eye with visit: "
        "each patient's visits compared onto the first).",
    ),
]
CpusPerVideo = Annotated[
    int | None,
    typer.Option(
        min=1,
        help="Threads (local) or Ray num_cpus (ray) per video "
        "(default: the cores shared by the workers; ray: 1).",
    ),
]
Resume = Annotated[
    bool,
    typer.Option(
        "--resume/--no-resume",
        help="Skip videos whose report says complete (--no-resume redoes them).",
    ),
]


@app.command()
def batch(
    source: BatchInput,
    out_dir: Annotated[
        Path, typer.Option("--output", "-o", help="Output folder: OUT_DIR/<id>/ per video.")
    ],
    config_path: Annotated[
        Path | None, typer.Option("--config", "-c", help="TOML config for every video.")
    ] = None,
    workers: Annotated[
        int | None,
        typer.Option(min=1, help="local: worker processes (default: one per core)."),
    ] = None,
    engine: Annotated[
        str, typer.Option(help="local (a process pool) | ray (one Ray task per video).")
    ] = "local",
    ray_address: Annotated[
        str | None,
        typer.Option(help="ray: the cluster to join (default: start a local Ray)."),
    ] = None,
    ray_timeout: Annotated[
        float,
        typer.Option(min=1.0, help="ray: give up reaching --ray-address after this many seconds."),
    ] = 60.0,
    cpus_per_video: CpusPerVideo = None,
    resume: Resume = True,
    pattern: Annotated[
        str | None,
        typer.Option(
            help="Glob on paths relative to INPUT (or names) picking the videos, e.g. '*.avi'."
        ),
    ] = None,
    rerun: Annotated[str, typer.Option(help="off | save (OUT_DIR/<id>/recording.rrd).")] = "off",
    verbose: Verbose = False,
) -> None:
    """Build the mosaics of many videos: one folder per video, OUT_DIR/summary.csv / .json and
    a browsable OUT_DIR/index.html; patients' visits (manifest) compared onto the first into
    OUT_DIR/compare/. Exit 0: all built (and compared), 1: any not, 130: interrupted."""
    from mosaic.batch import run_batch

    setup_logging(verbose)
    try:
        with _user_errors(), terminate_as_interrupt(children=True):
            config = load_config(config_path)
            result = run_batch(
                source,
                out_dir,
                config,
                workers=workers,
                engine=engine,
                ray_address=ray_address,
                ray_timeout_s=ray_timeout,
                cpus_per_video=cpus_per_video,
                resume=resume,
                pattern=pattern,
                rerun=rerun,
            )
    except KeyboardInterrupt:
        typer.echo("interrupted", err=True)
        raise typer.Exit(EXIT_INTERRUPTED) from None
    counts = ", ".join(f"{n} {status}" for status, n in result.counts.items() if n)
    typer.echo(f"{len(result.rows)} videos: {counts}")
    if result.patients is not None:
        later = sum(len(p["visits"]) for p in result.patients.values())
        typer.echo(
            f"{len(result.patients)} patients, {later} later visits: "
            f"{later - result.not_compared} compared, {result.not_compared} not"
        )
    typer.echo(f"summary: {Path(out_dir) / 'index.html'}")
    if result.interrupted:
        typer.echo("interrupted: rerun the same command to resume", err=True)
        raise typer.Exit(EXIT_INTERRUPTED)
    if result.failed or result.not_compared:
        raise typer.Exit(EXIT_FAILED)


# `synth`'s options whose help takes lines
SynthImage = Annotated[
    Path | None,
    typer.Argument(
        help="Source fundus image, or a folder of them (the seed picks one); "
        "default: the shipped CC0 sample."
    ),
]
Realistic = Annotated[
    bool,
    typer.Option(
        help="Like real magnified fundus video: 25-45 % of the source's view per frame, "
        "its rim at times, strong vignetting, gain/gamma changes, blur/defocus/glare bursts. "
        "Curved pairs: the aperture filled, each photograph as from its own visit (focus, "
        "illumination, gamma, colour, lesions, noise, JPEG quality)."
    ),
]
Interlaced = Annotated[
    bool,
    typer.Option(
        help="As an interlaced camera: each frame's odd rows from half a frame interval "
        "later (the truth is the even rows' pose)."
    ),
]
LensReflexes = Annotated[
    int,
    typer.Option(
        min=0,
        help="N bright reflections of the fundus lens that stay near one place of the frame "
        "(a few px of wander) while the retina moves under them.",
    ),
]
DustSpots = Annotated[
    int,
    typer.Option(
        min=0,
        help="N out-of-focus dust spots on the sensor or lens: soft dark blobs fixed in the "
        "frame (20-60 % of the light taken at their centre).",
    ),
]
Fast = Annotated[
    bool,
    typer.Option(
        help="With --realistic: faster and more magnified, 4-45 px of motion a frame and "
        "20-40 % of the source's view per frame."
    ),
]
LensRim = Annotated[
    bool,
    typer.Option(
        help="As through a handheld fundus lens: the retina only inside the lens's rim, a "
        "disc that moves about the frame, the face out of focus around it.",
    ),
]
HazeFrames = Annotated[
    int,
    typer.Option(
        min=0,
        help="The last N frames seen through haze: a veil of scattered light (contrast "
        "down to 25-55 %), slightly blurred.",
    ),
]
CurvedPairs = Annotated[
    int,
    typer.Option(
        min=0,
        help="Instead of a video: N pairs of photographs of a curved retina with exact "
        "control points, in FIRE's layout, into the folder OUTPUT (pair i: source and "
        "camera poses of seed + i).",
    ),
]
TurnDeg = Annotated[
    float,
    typer.Option(
        min=0.0,
        max=40.0,
        help="Curved pairs: the eye turns up to half this each way per photograph (the "
        "larger, the less overlap and the more curvature between the two).",
    ),
]
FollowupOf = Annotated[
    Path | None,
    typer.Option(
        help="A follow-up visit of this synthetic baseline video (or its .gt.json): its "
        "source with a new haemorrhage, a narrowed vessel and laser scars planted where both "
        "videos look, the changes in the ground truth (`followup`; see compare.md).",
    ),
]


@app.command()
def synth(
    image: SynthImage = None,
    output: Annotated[Path, typer.Option("--output", "-o", help="Video (.mp4/.avi) or folder.")] = (
        Path("synthetic.mp4")
    ),
    frames: Annotated[int, typer.Option(min=2, help="Number of frames.")] = 60,
    size: Annotated[
        str | None,
        typer.Option(help="Frame size WIDTHxHEIGHT (default 660x350; curved pairs: 2912x2912)."),
    ] = None,
    seed: Annotated[int, typer.Option(help="Random seed of the trajectory.")] = 0,
    clean: Annotated[bool, typer.Option(help="No noise, blur or illumination changes.")] = False,
    hard: Annotated[
        bool, typer.Option(help="Hard like real video: loops, fast motion, blur bursts, glare.")
    ] = False,
    realistic: Realistic = False,
    fast: Fast = False,
    interlaced: Interlaced = False,
    lens_reflexes: LensReflexes = 0,
    dust_spots: DustSpots = 0,
    lens_rim: LensRim = False,
    haze_frames: HazeFrames = 0,
    curved_pairs: CurvedPairs = 0,
    turn_deg: TurnDeg = 16.0,
    followup_of: FollowupOf = None,
    verbose: Verbose = False,
) -> None:
    """Render a synthetic retinal video with ground-truth homographies (VIDEO.gt.json), or
    pairs of photographs of a curved retina with exact control points (--curved-pairs)."""
    setup_logging(verbose)
    with _user_errors():
        made = synthesize(
            SynthRequest(
                image=image,
                output=output,
                frames=frames,
                size=size,
                seed=seed,
                clean=clean,
                hard=hard,
                realistic=realistic,
                fast=fast,
                interlaced=interlaced,
                lens_reflexes=lens_reflexes,
                dust_spots=dust_spots,
                lens_rim=lens_rim,
                haze_frames=haze_frames,
                curved_pairs=curved_pairs,
                turn_deg=turn_deg,
                followup_of=followup_of,
            )
        )
    if made.ground_truth is not None:
        typer.echo(f"video: {output}\nground truth: {made.ground_truth}\nsource: {made.sources[0]}")
        return
    typer.echo(
        f"{made.curved_pairs} curved pairs: {output} (FIRE layout; {output / 'pairs.csv'} for "
        f"mosaic register --pairs)\nsources: {', '.join(sorted({s.name for s in made.sources}))}"
    )


@app.command()
def register(
    fixed: Annotated[Path | None, typer.Argument(help="Fixed image.")] = None,
    moving: Annotated[Path | None, typer.Argument(help="Moving image.")] = None,
    pairs: Annotated[
        Path | None, typer.Option(help="CSV with columns fixed,moving: many pairs, JSON lines.")
    ] = None,
    config_path: Annotated[Path | None, typer.Option("--config", "-c")] = None,
    detector: Annotated[str | None, typer.Option(help=f"{', '.join(DETECTORS)}.")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON.")] = False,
    model: Annotated[
        str,
        typer.Option(
            help="Motion model: auto (the model with the least expected corner error: "
            "photographs of a curved retina from two viewpoints need more than a similarity), "
            f"or one of {', '.join(PAIR_MODELS)} (quadratic: the curved retina, 12 parameters)."
        ),
    ] = "auto",
    warp: Annotated[
        Path | None,
        typer.Option(help="PNG: the moving image warped onto the fixed one, and a checkerboard."),
    ] = None,
    matches: Annotated[
        Path | None,
        typer.Option(help="Image: both images side by side, keypoints and inlier matches drawn."),
    ] = None,
    verbose: Verbose = False,
) -> None:
    """Register MOVING onto FIXED and print H_moving_to_fixed (full-resolution pixels)."""
    setup_logging(verbose)
    with _user_errors():
        if model not in ("auto", *PAIR_MODELS):
            raise InputError(
                f"--model must be auto or one of {', '.join(PAIR_MODELS)}, got {model!r}"
            )
        if pairs is not None and (fixed or moving or warp or matches):
            given = [n for n, v in (("FIXED/MOVING", fixed or moving), ("--warp", warp),
                                    ("--matches", matches)) if v]  # fmt: skip
            raise InputError(f"{' and '.join(given)}: one pair's; not with --pairs")
        given = {"--warp": warp, "--matches": matches}
        check_distinct_paths(
            {name: path for name, path in given.items() if path is not None},
            {name: path for name, path in (("FIXED", fixed), ("MOVING", moving)) if path},
        )
        if warp is not None:
            warp = check_output_path(warp, IMAGE_WRITE_SUFFIXES)
        if matches is not None:
            matches = check_output_path(matches, IMAGE_WRITE_SUFFIXES)
        config = for_photographs(options_config(config_path, detector))
        extractor = FeatureExtractor(config.features)
        if pairs is not None:
            _register_pairs_file(pairs, config, extractor, model)
            return
        if fixed is None or moving is None:
            raise InputError("give FIXED and MOVING images, or --pairs PAIRS.csv")
        result = pair_answer(fixed, moving, config, extractor, model, warp, matches)
        typer.echo(json.dumps(result, indent=2) if as_json else pair_text(result))
    if result["status"] != "registered":
        raise typer.Exit(1)


def _register_pairs_file(
    pairs: Path, config: Config, extractor: FeatureExtractor, model: str
) -> None:
    """`register --pairs`: one JSON line per pair, the counts on stderr; exit 1 if any failed."""
    from tqdm import tqdm

    n_pairs = failed = 0
    for result in pairs_file_answers(pairs, config, extractor, model):
        n_pairs += 1
        failed += result["status"] != "registered"
        tqdm.write(json.dumps(result), file=sys.stdout)  # above the bar on a terminal
    typer.echo(f"{n_pairs} pairs: {n_pairs - failed} registered, {failed} failed", err=True)
    if failed:
        raise typer.Exit(1)


# `compare`'s options whose help takes lines
Manifest = Annotated[
    Path | None,
    typer.Option(
        help="CSV with columns patient,visit,path: each patient's later visits compared "
        "onto the first, OUT/<patient>/<visit>/, summary.json and index.html.",
    ),
]
CompareRerun = Annotated[
    str,
    typer.Option(
        help=f"Rerun viewer: {' | '.join(VIEWER_MODES)}; baseline, warped follow-up and "
        "change map as layers of one space."
    ),
]
CompareRerunTarget = Annotated[
    str | None,
    typer.Option(
        help="save: the .rrd file (default OUT_DIR/compare.rrd); "
        "connect: the viewer's URL (default rerun+http://127.0.0.1:9876/proxy)."
    ),
]


@app.command()
def compare(
    baseline: Annotated[
        Path | None,
        typer.Argument(help="Baseline visit: a video, a mosaic (with its report) or a photograph."),
    ] = None,
    followup: Annotated[
        Path | None, typer.Argument(help="Follow-up visit: the same kinds.")
    ] = None,
    output: Annotated[
        Path, typer.Option("--output", "-o", help="Folder for the pictures and compare.json.")
    ] = Path("compare"),
    manifest: Manifest = None,
    config_path: Annotated[Path | None, typer.Option("--config", "-c")] = None,
    detector: Annotated[str | None, typer.Option(help=f"{', '.join(DETECTORS)}.")] = None,
    rerun: CompareRerun = "off",
    rerun_target: CompareRerunTarget = None,
    viewer_flag: ViewerFlag = False,
    verbose: Verbose = False,
) -> None:
    """Put a follow-up visit on the baseline's map: the follow-up warped, a checkerboard, a
    two-colour overlay, a change map and compare.json (H/Q_followup_to_baseline, changed
    regions). Different eyes or no overlap: one line, exit 1."""
    from mosaic.compare import NotComparableError, not_compared, run_compare, run_manifest
    from mosaic.viz import make_compare_viewer

    setup_logging(verbose)
    viewer = None
    with _user_errors():
        if manifest is not None:
            if baseline or followup:
                raise InputError("BASELINE and FOLLOWUP, or --manifest: not both")
            if rerun != "off" or viewer_flag:
                raise InputError("the rerun viewer shows one pair: not with --manifest")
            summary = run_manifest(manifest, output, options_config(config_path, detector))
            rows = [r for p in summary["patients"].values() for r in p["visits"]]
            missed = not_compared(summary["patients"])
            typer.echo(
                f"{len(summary['patients'])} patients, {len(rows)} later visits: "
                f"{len(rows) - missed} compared, {missed} not\nwritten: {output / 'index.html'}"
            )
            if missed:
                raise typer.Exit(EXIT_FAILED)
            return
        if baseline is None or followup is None:
            raise InputError("give BASELINE and FOLLOWUP, or --manifest VISITS.csv")
        check_distinct_paths({"--output": output}, {"BASELINE": baseline, "FOLLOWUP": followup})
        config = options_config(config_path, detector)
        if rerun != "off" or viewer_flag:  # the folder first: the recording goes into it
            output.mkdir(parents=True, exist_ok=True)
        rerun, rerun_target = viewer_args(rerun, rerun_target, viewer_flag, output / "compare.rrd")
        viewer = make_compare_viewer(rerun, rerun_target)
        if getattr(viewer, "url", None):
            typer.echo(f"rerun viewer: {viewer.url}")  # type: ignore[attr-defined]
        try:
            comparison, result = run_compare(baseline, followup, output, config, viewer)
        except NotComparableError as exc:
            typer.echo(f"not comparable: {exc}", err=True)
            raise typer.Exit(EXIT_FAILED) from None
        finally:
            viewer.close()
    model = "quadratic" if comparison.Q_followup_to_baseline is not None else comparison.model
    typer.echo(
        f"registered ({model}, residual {comparison.residual_px:.2f} px, overlap "
        f"{100 * comparison.overlap_share:.0f} %, agreement {comparison.correlation:.2f}); "
        f"{len(comparison.regions)} changed region(s)\nwritten: {output / 'compare.json'}, "
        + ", ".join(result["pictures"])
    )
    if rerun == "save":
        typer.echo(f"recording: {rerun_target}")
    elif rerun == "serve":
        _serve_until_interrupted(getattr(viewer, "url", None))


@app.command()
def evaluate(
    inputs: Annotated[
        list[Path], typer.Argument(help="Videos, frame folders, or folders holding videos.")
    ],
    detector: Annotated[
        str | None,
        typer.Option(help=f"Comma-separated detectors (default: all of {', '.join(DETECTORS)})."),
    ] = None,
    out: Annotated[Path, typer.Option(help="Folder for the tables (CSV, JSON) and plots.")] = Path(
        "evaluation"
    ),
    config_path: ConfigFile = None,
    max_frames: MaxFrames = None,
    step: Step = None,
    strategy: Annotated[
        str,
        typer.Option(help="Comma-separated strategies: keyframes, chain (the paper's)."),
    ] = "keyframes,chain",
    fidelity: Annotated[
        bool,
        typer.Option(
            "--fidelity/--no-fidelity",
            help="Score each mosaic against the source photograph named in VIDEO.gt.json "
            "(fidelity, good area) next to the oracle (frames placed by the truth).",
        ),
    ] = True,
    against: Annotated[
        Path | None,
        typer.Option(
            help="An earlier `mosaic evaluate --out` folder: each method is also compared with "
            "itself there, paired over the videos both runs hold (e.g. before / after a change).",
        ),
    ] = None,
    verbose: Verbose = False,
) -> None:
    """Compare detectors and strategies on videos: frames until failure, accuracy vs
    VIDEO.gt.json, drift, speed; paired differences with bootstrap intervals."""
    from mosaic.eval.common import parse_detectors
    from mosaic.eval.video_eval import run_video_evaluation
    from mosaic.eval.video_tables import format_video_tables, load_video_results

    setup_logging(verbose)
    with _user_errors(), logging_redirect_tqdm():
        config = options_config(config_path, None, max_frames=max_frames, step=step)
        strategies = [name.strip() for name in strategy.split(",") if name.strip()]
        for name in strategies:
            with_overrides(config, pipeline={"strategy": name})  # validates the name
        names = parse_detectors(detector)
        if detector is not None:
            require_detectors(config, names)
        previous = load_video_results(against) if against is not None else []
        results, summary = run_video_evaluation(
            inputs,
            config,
            names,
            out,
            explicit=detector is not None,
            progress=True,
            strategies=strategies,
            fidelity=fidelity,
            previous=previous,
        )
        typer.echo(format_video_tables(results, summary, previous))
        typer.echo(f"tables and plots: {out}")


# `bench`'s options whose help takes lines
WholeBuild = Annotated[
    bool,
    typer.Option(
        "--build/--no-build",
        help="Also time the whole `mosaic build` (re-render, written mosaic and report) of a "
        "realistic synthetic video of FRAMES frames with the first detector, next to its "
        "streaming rate.",
    ),
]
Profile = Annotated[
    int,
    typer.Option(
        help="Also print a cProfile of the first detector (serial run): the N functions "
        "with the most own time (0: none)."
    ),
]


@app.command()
def bench(
    size: Annotated[str, typer.Option(help="Frame size WIDTHxHEIGHT.")] = "660x350",
    frames: Annotated[int, typer.Option(min=10, help="Frames of the synthetic video.")] = 100,
    detector: Annotated[
        str | None,
        typer.Option(
            help="Comma-separated detectors; the first is used for the variants "
            f"(default: {BENCH_DETECTORS}, skipping any that cannot run)."
        ),
    ] = None,
    config_path: Annotated[Path | None, typer.Option("--config", "-c")] = None,
    rerun: Annotated[bool, typer.Option(help="Also measure the --rerun save overhead.")] = True,
    whole_build: WholeBuild = True,
    scales: Annotated[
        str,
        typer.Option(help="Comma-separated detection scales to time for the first detector."),
    ] = "0.75,0.5",
    as_json: Annotated[
        bool, typer.Option("--json", help="Print JSON instead of the table.")
    ] = False,
    profile: Profile = 0,
    verbose: Verbose = False,
) -> None:
    """Time the whole pipeline per detector on a synthetic video (ms per stage, frames/s)."""
    from mosaic.eval.bench import (
        bench_document,
        environment,
        format_bench,
        parse_scales,
        profile_pipeline,
        run_bench,
        run_build_bench,
    )

    setup_logging(verbose)
    with _user_errors():
        names = [name.strip() for name in (detector or BENCH_DETECTORS).split(",") if name.strip()]
        unknown = [name for name in names if name not in DETECTORS]
        if unknown:
            raise MosaicError(f"unknown detector(s) {', '.join(unknown)}")
        config = load_config(config_path)
        if detector is not None:  # before the video is made: named detectors must load
            require_detectors(config, names)
        scale_values = parse_scales(scales)
        factory = None
        if rerun:

            def factory(path: Path) -> Any:
                return make_viewer("save", path, config, None)

        rows = run_bench(
            names,
            parse_size(size),
            frames,
            config,
            factory,
            progress=lambda name: typer.echo(f"running {name} ...", err=True),
            scales=scale_values,
            explicit=detector is not None,
        )
        if not rows:
            raise MosaicError(f"none of the detectors {', '.join(names)} could run")
        builds = []
        if whole_build:
            typer.echo(f"running {rows[0].detector} (mosaic build) ...", err=True)
            builds.append(run_build_bench(rows[0].detector, parse_size(size), frames, config))
        env = environment()
        if as_json:
            typer.echo(json.dumps(bench_document(rows, builds, env)))
            return
        typer.echo(format_bench(rows, builds, env))
        if profile:
            typer.echo(f"\nprofile of {names[0]} (serial run, {frames} frames):")
            typer.echo(profile_pipeline(names[0], parse_size(size), frames, config, profile))


def main() -> None:
    """Console entry point. Ctrl-C anywhere exits 130 (typer); an unexpected exception (a bug)
    prints one line and exits 1, its traceback logged at INFO (-v)."""
    try:
        app()
    except Exception as exc:
        log.info("internal error", exc_info=True)
        typer.echo(f"error: internal error: {one_line(exc)} (-v shows the traceback)", err=True)
        raise SystemExit(EXIT_FAILED) from None
