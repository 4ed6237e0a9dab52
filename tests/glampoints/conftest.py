"""Shared fixtures: deterministic synthetic vessel-like images (no real data needed)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from torch import nn

SHARED_DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"


def vessel_image(shape: tuple[int, int], seed: int) -> np.ndarray:
    """uint8 grey image with random curved 'vessels', blobs and mild noise (fundus-like)."""
    rng = np.random.default_rng(seed)
    h, w = shape
    img = np.full((h, w), 60, dtype=np.float32)
    for _ in range(max(6, (h * w) // 4000)):
        pts = np.cumsum(rng.normal(0, 12, size=(8, 2)), axis=0) + rng.uniform(0, [w, h])
        cv2.polylines(
            img,
            [pts.astype(np.int32)],
            False,
            float(rng.uniform(120, 230)),
            int(rng.integers(1, 4)),
            cv2.LINE_AA,
        )
    for _ in range(max(4, (h * w) // 8000)):
        c = tuple(int(v) for v in rng.uniform(0, [w, h]))
        cv2.circle(img, c, int(rng.integers(2, 6)), float(rng.uniform(0, 255)), -1)
    img = cv2.GaussianBlur(img, (0, 0), 1.0)
    img += rng.normal(0, 3, size=img.shape).astype(np.float32)
    return np.clip(img, 0, 255).astype(np.uint8)


@pytest.fixture
def texture() -> np.ndarray:
    return vessel_image((160, 200), seed=3)


def randomise_batchnorm(net: nn.Module, seed: int = 0) -> nn.Module:
    """Give every BatchNorm non-trivial statistics and affine parameters (eval behaviour)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, nn.BatchNorm2d):
                n = m.num_features
                m.running_mean.copy_(torch.rand(n, generator=g) * 0.4 - 0.2)
                m.running_var.copy_(torch.rand(n, generator=g) * 1.5 + 0.5)
                m.weight.copy_(torch.rand(n, generator=g) + 0.5)
                m.bias.copy_(torch.rand(n, generator=g) * 0.2 - 0.1)
    return net.eval()
