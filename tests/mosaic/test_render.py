"""The re-render's frame source: `ReadAhead` reads the frames while the pose graph is solved.
(`render_segments` itself is tested with the photometry it corrects by, test_photometry.py.)"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from mosaic.render import ReadAhead


def test_read_ahead_reads_before_it_is_called_and_gives_the_frames_in_order():
    """`ReadAhead` reads in its thread from the moment it is made, holds at most about
    `keep_bytes` of frames (one more frame while it waits), gives them in order to its first
    call, reads afresh for a later one, and raises the reader's error where the frame failed."""
    read: list[int] = []
    more = threading.Event()

    def frames():
        for index in range(10):
            if index == 3:
                more.wait(5.0)
            read.append(index)
            yield index, np.full((4, 5, 3), index, np.uint8), np.full((4, 5), 255, np.uint8)

    ahead = ReadAhead(frames, keep_bytes=2 * 80)  # two frames (60 + 20 bytes each)
    deadline = time.monotonic() + 5.0
    while len(read) < 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert read == [0, 1, 2]  # read before the call; the third waits for room
    more.set()
    got = [(i, int(image[0, 0, 0])) for i, image, _ in ahead()]
    assert got == [(i, i) for i in range(10)]
    assert [i for i, _, _ in ahead()] == list(range(10))  # afresh: all read again
    ahead.close()

    def broken():
        yield 0, np.zeros((2, 2, 3), np.uint8), np.zeros((2, 2), np.uint8)
        raise ValueError("cannot decode frame 1")

    failing = ReadAhead(broken)
    taken = failing()
    assert next(taken)[0] == 0
    with pytest.raises(ValueError, match="frame 1"):
        next(taken)
    failing.close()
