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


SERIAL, OVERLAPPED, TURNS = "serial", "overlapped", "turns"  # the ways `OverlapTrial` tries


class OverlapTrial:
    """Whether to extract the next frame while this one registers (`[pipeline] overlap`), and
    whether the network then takes turns with the registration (`Turns`).

    "on" / "off" fix it ("on": with turns where the detector's network takes every core).
    "auto" times each way on the stream's first frames and keeps the fastest: serial,
    then, where the network takes every core, overlapped with turns, then overlapped freely.
    Which wins depends on the machine: on a 2-core AMD EPYC without bfloat16 (the network 40
    ms in float32) turns won (72-76 ms a frame against 85-87 without, 77-79 serially); on a
    2-core Xeon with AMX (12 ms in bfloat16, a registration grown to ~35 ms) turns lost
    (three videos' whole builds 57.6 s against 53.8 s overlapped freely). Results are the
    same every way, only the speed differs. Serial first: where overlapping loses, fewer
    frames pay for the trial.
    Frame time is the caller's wall time between two frames; the frames right after a switch
    are not timed. Trials run again every `RETRIAL` frames.
    """

    WARMUP = 3  # frames before timing: first frames carry one-off costs (weights, buffers)
    FRAMES = 12  # timed frames each way (the ways may differ by only ~5 %)
    SETTLE = 2  # frames not timed after a switch (the items in flight were extracted before)
    RETRIAL = 500  # frames between two trials: the machine's load changes, a close call errs

    def __init__(
        self, mode: str, clock: Callable[[], float] = time.perf_counter, turns: bool = False
    ) -> None:
        self.mode, self._clock = mode, clock
        self._ways = [SERIAL, TURNS, OVERLAPPED] if turns else [SERIAL, OVERLAPPED]
        fixed = {"on": self._ways[1], "off": SERIAL}
        self.way: str | None = fixed.get(mode)  # the way chosen (None: not yet)
        self._frames = 0  # frames delivered after the first
        self._trial_start: int | None = 0 if mode == "auto" else None  # of the running trial
        self._next_trial = 0
        self._times: list[list[float]] = [[] for _ in self._ways]
        self._last: float | None = None

    @property
    def chosen(self) -> bool | None:
        """Overlapped (either way), serial, or None before the first trial has chosen."""
        return None if self.way is None else self.way != SERIAL

    def ahead(self) -> bool:
        """Extract ahead while the coming frame registers?"""
        return self._current() != SERIAL

    def turns(self) -> bool:
        """Does the network take turns with the registration of the coming frame?"""
        return self._current() == TURNS

    def _current(self) -> str:
        if self._trial_start is None:
            return self.way or SERIAL
        return self._ways[self._way_at(self._frames - self._trial_start)[0]]

    def _way_at(self, at: int) -> tuple[int, bool]:
        """The way of a trial's frame `at` (0: its first) and whether that frame is timed."""
        first = self.WARMUP + self.FRAMES
        if at < first:
            return 0, at >= self.WARMUP
        k, settled = divmod(at - first, self.FRAMES + self.SETTLE)
        if k + 1 >= len(self._ways):
            return len(self._ways) - 1, False
        return k + 1, settled >= self.SETTLE

    def tick(self) -> None:
        """A frame was delivered: time it during a trial and, when every way is timed,
        choose; start the next trial `RETRIAL` frames later."""
        now = self._clock()
        last, self._last = self._last, now
        if self.mode != "auto" or last is None:
            return
        self._frames += 1
        if self._trial_start is None:
            if self._frames >= self._next_trial:
                self._trial_start = self._frames
                self._times = [[] for _ in self._ways]
            return
        k, timed = self._way_at(self._frames - 1 - self._trial_start)
        if timed:
            self._times[k].append(now - last)
        if len(self._times[-1]) == self.FRAMES:
            medians = [float(np.median(t)) for t in self._times]
            self.way = self._ways[int(np.argmin(medians))]
            self._trial_start, self._next_trial = None, self._frames + self.RETRIAL
            log.info(
                "extraction %s (ms a frame: %s)",
                self.way,
                ", ".join(f"{w} {m * 1e3:.1f}" for w, m in zip(self._ways, medians, strict=True)),
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
    as detected. Without `on`, or while items are not extracted ahead with turns (`taking`
    of `before_register`: `OverlapTrial` may find overlapping freely faster), nothing waits.
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

    def before_register(self, j: int, taking: bool) -> None:
        with self._cond:
            self._ahead = taking
            self._cond.notify_all()
            if self.on and taking:
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
