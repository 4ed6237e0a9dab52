"""The random streams of a synthetic video and the smooth signals drawn from them.

Each group of effects draws from its own child of `SeedSequence(seed)`, so switching one
group on or off never changes what the others draw, nor the trajectory.
"""

from __future__ import annotations

import numpy as np

# the streams' indices
GEOMETRY, NUISANCE, HARD_GEOMETRY, HARD_NUISANCE = 0, 1, 2, 3
REAL_GEOMETRY, REAL_NUISANCE, REFLEX, DUST, RIM = 4, 5, 6, 7, 8


def stream(seed: int, index: int) -> np.random.Generator:
    """Random generator of stream `index` of a video's seed."""
    return np.random.default_rng(np.random.SeedSequence(seed).spawn(index + 1)[index])


def smooth_signal(rng: np.random.Generator, t: np.ndarray, n_terms: int = 3) -> np.ndarray:
    """Random sum of low-frequency sinusoids of t in [0, 1], rescaled to span exactly [-1, 1]."""
    if t.size < 2:
        return np.zeros_like(t)
    freqs = rng.uniform(0.3, 1.6, n_terms) * np.arange(1, n_terms + 1)
    amps = rng.uniform(0.5, 1.0, n_terms) / np.arange(1, n_terms + 1)
    phases = rng.uniform(0, 2 * np.pi, n_terms)
    sig = (amps * np.sin(2 * np.pi * t[:, None] * freqs + phases)).sum(axis=1)
    lo, hi = sig.min(), sig.max()
    return (2 * sig - (lo + hi)) / max(hi - lo, 1e-12)
