"""Thread scheduling of `MosaicBuilder.stream`: whether to extract the next frames in a
background thread while the current one registers (`OverlapTrial`), and the turns the
detector's network and the registration take when both want every core (`Turns`).
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

import numpy as np

log = logging.getLogger(__name__)

T = TypeVar("T")


class OverlapTrial:
    """Whether to extract the next frame while this one registers (`[pipeline] overlap`).

    "on" / "off" fix it. "auto" times both on the stream's first frames and keeps the faster:
    overlapping pays only where the machine has a core to spare for it (measured on 2 cores,
    GLAMpoints before `Turns`: its two threads and the registration contended, 87 against 78
    ms a frame serially; with them 72-76; SIFT gained 40-60 %). Results are the same either
    way, only the speed differs. Serial first: where overlapping loses, fewer frames pay for
    the trial.
    Frame time is the caller's wall time between two frames; the frames right after a switch
    are not timed. Trials run again every `RETRIAL` frames.
    """

    WARMUP = 3  # frames before timing: first frames carry one-off costs (weights, buffers)
    FRAMES = 12  # timed frames each way (the two ways may differ by only ~5 %)
    RETRIAL = 500  # frames between two trials: the machine's load changes, a close call errs

    def __init__(self, mode: str, clock: Callable[[], float] = time.perf_counter) -> None:
        self.mode, self._clock = mode, clock
        self.chosen: bool | None = None if mode == "auto" else mode == "on"
        self._frames = 0  # frames delivered after the first
        self._trial_start: int | None = 0 if mode == "auto" else None  # of the running trial
        self._next_trial = 0
        self._times: dict[bool, list[float]] = {True: [], False: []}
        self._last: float | None = None

    def ahead(self) -> bool:
        """Extract ahead while the coming frame registers?"""
        if self._trial_start is None:
            return bool(self.chosen)
        # serial first, then overlapped
        return self._frames - self._trial_start >= self.WARMUP + self.FRAMES

    def tick(self) -> None:
        """A frame was delivered: time it during a trial and, when both ways are timed,
        choose; start the next trial `RETRIAL` frames later."""
        now = self._clock()
        last, self._last = self._last, now
        if self.mode != "auto" or last is None:
            return
        self._frames += 1
        if self._trial_start is None:
            if self._frames >= self._next_trial:
                self._trial_start, self._times = self._frames, {True: [], False: []}
            return
        at, switched = self._frames - self._trial_start, self.WARMUP + self.FRAMES
        if at > self.WARMUP and at not in (switched + 1, switched + 2):
            self._times[at > switched].append(now - last)
        if len(self._times[True]) == self.FRAMES:
            on, off = (float(np.median(self._times[k])) for k in (True, False))
            self.chosen = on < off
            self._trial_start, self._next_trial = None, self._frames + self.RETRIAL
            log.info(
                "overlap %s: %.1f ms a frame overlapped, %.1f serially",
                "on" if self.chosen else "off",
                on * 1e3,
                off * 1e3,
            )


#: Python's GIL switch interval while the registration and the describer share it (`Turns`):
#: both are numpy-heavy Python, and at the default 5 ms one waits out the other's whole slice
#: after every call that released the GIL (measured on 2 cores: 12.7 -> 13.4 frames/s).
SWITCH_INTERVAL_S = 0.0005


class Turns:
    """The detector's network and the registration take turns when frames are extracted ahead
    (`stream`) and the network runs on every core (GLAMpoints on torch's CPU threads).

    Registering beside the network slows both (the network's threads wait on the core the
    registration holds). So the network of frame k+1 runs while no frame registers, and the
    registration of frame k after it, beside the single-threaded rest of extracting frame k+1
    and k+2 (describing, decoding, pre-processing). Measured on 2 cores: 72-76 ms a frame
    against 77-79 serially; without turns, 85-87.

    The detector of item k waits until item k-2 is registered; the registration of item j
    waits until item j+1 is detected (or the items end). Items skipped before detection count
    as detected. Without `on`, or while items are not extracted ahead, nothing waits.
    """

    def __init__(self, on: bool) -> None:
        self.on = on
        self._cond = threading.Condition()
        self._detected = 0  # items past detection (or skipped before it)
        self._registered = 0
        self._ahead = False
        self._ended = False  # the items ran out, or the stream stopped: nothing waits any more
        self._interval = sys.getswitchinterval()

    def before_detect(self) -> None:
        if self.on:
            with self._cond:
                k = self._detected
                self._cond.wait_for(
                    lambda: not self._ahead or self._ended or self._registered >= k - 1
                )

    @property
    def n_detected(self) -> int:
        return self._detected

    def detected(self) -> None:
        with self._cond:
            self._detected += 1
            self._cond.notify_all()

    def before_register(self, j: int, ahead: bool) -> None:
        with self._cond:
            self._ahead = ahead
            self._cond.notify_all()
            if self.on and ahead:
                self._cond.wait_for(lambda: self._ended or self._detected >= j + 2)

    def registered(self) -> None:
        with self._cond:
            self._registered += 1
            self._cond.notify_all()

    def ended_after(self, items: Iterable[T]) -> Iterator[T]:
        """`items`, then the end is marked."""
        yield from items
        self._end()

    def _end(self) -> None:
        with self._cond:
            self._ended = True
            self._cond.notify_all()

    def __enter__(self) -> Turns:
        self._interval = sys.getswitchinterval()
        if self.on:
            sys.setswitchinterval(SWITCH_INTERVAL_S)
        return self

    def __exit__(self, *exc: object) -> None:
        self._end()  # a stream left early: the extraction in flight must not wait
        sys.setswitchinterval(self._interval)
