"""retina-mosaic: retinal video mosaicking with GLAMpoints keypoints."""

import os

# One OpenBLAS thread: numpy's matrix products here are small (descriptor distances), and an
# idle OpenBLAS worker busy-waits on a core that torch's two threads need for the GLAMpoints
# network (measured: GLAMpoints detect 83 -> 46 ms per frame on 2 cores). Set before numpy
# is first imported; an explicit setting in the environment wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
