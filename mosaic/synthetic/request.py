"""What `mosaic synth` renders, from its options: a synthetic video (its `SynthParams`, the
source the seed picks, a follow-up visit's planted changes) or pairs of photographs of a curved
retina in FIRE's layout. The options are checked together here, so the command line only parses
them and prints what was written.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from mosaic.errors import InputError
from mosaic.io import sample_image_path
from mosaic.synthetic.synth import SynthParams, pick_source, write_synthetic_video

VIDEO_SIZE = "660x350"  # the default frame size of a video (the sample's)
CURVED_PAIR_SIZE = "2912x2912"  # the default photograph size of curved pairs (FIRE's)


def parse_size(size: str) -> tuple[int, int]:
    """`WIDTHxHEIGHT` as (width, height), at least 32x32 (`synth --size`, `bench --size`)."""
    try:
        width, height = (int(v) for v in size.lower().split("x"))
    except ValueError:
        raise InputError(f"size must look like 660x350, got {size!r}") from None
    if width < 32 or height < 32:
        raise InputError(f"size {size} is too small (at least 32x32)")
    return width, height


@dataclass(frozen=True)
class SynthRequest:
    """The options of `mosaic synth` as given (None: the default; see `mosaic synth --help`)."""

    image: Path | None  # a source image or a folder of them (None: the shipped sample)
    output: Path
    frames: int
    size: str | None  # WIDTHxHEIGHT (None: VIDEO_SIZE, or CURVED_PAIR_SIZE for curved pairs)
    seed: int
    clean: bool
    hard: bool
    realistic: bool
    fast: bool  # with realistic: faster and more magnified (`SynthParams.realistic_fast`)
    interlaced: bool
    lens_reflexes: int
    dust_spots: int
    lens_rim: bool
    haze_frames: int
    curved_pairs: int  # N > 0: curved pairs instead of a video
    turn_deg: float
    followup_of: Path | None  # a baseline video (or its .gt.json): render a follow-up visit


@dataclass(frozen=True)
class Synthesized:
    """What `synthesize` wrote: a video and its ground truth, or curved pairs."""

    output: Path
    sources: list[Path]  # the source photograph of the video, or of each pair
    ground_truth: Path | None  # the video's .gt.json (None: curved pairs)
    curved_pairs: int  # the pairs written (0: a video)


def check_request(request: SynthRequest) -> None:
    """Options that cannot go together: one line naming them (`InputError`)."""
    if request.hard and request.realistic:
        raise InputError("choose one of --hard and --realistic")
    if request.fast and not request.realistic:
        raise InputError("--fast: with --realistic (faster, more magnified realistic video)")
    video_only = {"--interlaced": request.interlaced, "--lens-reflexes": request.lens_reflexes,
                  "--dust-spots": request.dust_spots, "--lens-rim": request.lens_rim,
                  "--haze-frames": request.haze_frames}  # fmt: skip
    given = [name for name, value in video_only.items() if value]
    if request.followup_of is not None:
        given.append("--followup-of")
    if request.curved_pairs and given:
        raise InputError(f"{' and '.join(given)}: for videos, not --curved-pairs")


def synthesize(request: SynthRequest) -> Synthesized:
    """Check the options, then write the video with its ground truth, or the curved pairs."""
    check_request(request)
    if request.curved_pairs:
        return _write_curved_pairs(request)
    make = SynthParams  # the profile: its defaults, or hard, realistic or fast realistic ones
    if request.hard:
        make = SynthParams.hard
    elif request.realistic:
        make = SynthParams.realistic_fast if request.fast else SynthParams.realistic
    params = make(
        n_frames=request.frames,
        size=parse_size(request.size or VIDEO_SIZE),
        seed=request.seed,
        nuisances=not request.clean,
        interlaced=request.interlaced,
        lens_reflexes=request.lens_reflexes,
        dust_spots=request.dust_spots,
        lens_rim=request.lens_rim,
        haze_frames=request.haze_frames,
    )
    image, edit = request.image, None
    if request.followup_of is not None:  # the baseline's own photograph, changed
        from mosaic.synthetic.followup import followup_hook, load_baseline_gt

        baseline = load_baseline_gt(request.followup_of)
        image = image or Path(baseline["source"])
        edit = followup_hook(baseline, request.seed)
    source = pick_source(image or sample_image_path(), request.seed)
    gt = write_synthetic_video(source, request.output, params, edit)
    return Synthesized(request.output, [source], gt, 0)


def _write_curved_pairs(request: SynthRequest) -> Synthesized:
    """`synth --curved-pairs`: the pairs in FIRE's layout
    (`mosaic.synthetic.curved.write_fire_folder`), square photographs."""
    from mosaic.synthetic.curved import write_fire_folder

    image, seed, n_pairs = request.image or sample_image_path(), request.seed, request.curved_pairs
    size = request.size
    width, height = parse_size(size or CURVED_PAIR_SIZE)
    if width != height:
        raise InputError(f"curved pairs are square: --size {size} is not")
    sources = [pick_source(image, seed + i) for i in range(n_pairs)]
    write_fire_folder(
        sources,
        request.output,
        n_pairs,
        seed=seed,
        size=width,
        turn_deg=request.turn_deg,
        realistic=request.realistic,
    )
    return Synthesized(request.output, sources, None, n_pairs)
