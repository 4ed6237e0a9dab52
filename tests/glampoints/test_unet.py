"""UNet architecture: parameter count, channel widths, arbitrary input sizes."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from glampoints.unet import UNet, count_parameters


def test_parameter_count_matches_paper_architecture():
    # 4-level UNet, channels 8-16-32-64-128, double 3x3 conv + BN + ReLU blocks:
    # 487,145 learnable parameters (about 487k).
    n = count_parameters(UNet())
    assert n == 487_145
    assert abs(n - 487_000) / 487_000 < 0.02


def test_channel_widths_and_layers():
    net = UNet()
    convs = [m for m in net.modules() if isinstance(m, nn.Conv2d)]
    outs = [c.out_channels for c in convs]
    assert outs == [8, 8, 16, 16, 32, 32, 64, 64, 128, 128, 64, 64, 32, 32, 16, 16, 8, 8, 1]
    assert all(c.kernel_size == (3, 3) for c in convs[:-1])
    assert convs[-1].kernel_size == (1, 1)
    ups = [m for m in net.modules() if isinstance(m, nn.ConvTranspose2d)]
    assert [(u.kernel_size, u.stride) for u in ups] == [((2, 2), (2, 2))] * 4
    assert sum(isinstance(m, nn.BatchNorm2d) for m in net.modules()) == 18


@pytest.mark.parametrize("shape", [(100, 123), (17, 33), (5, 7), (64, 64)])
def test_any_input_size_gives_same_size_probabilities(shape):
    torch.manual_seed(0)
    net = UNet().eval()
    x = torch.rand(2, 1, *shape)
    with torch.no_grad():
        y = net(x)
    assert y.shape == (2, 1, *shape)
    assert float(y.min()) >= 0.0 and float(y.max()) <= 1.0


def test_no_padding_needed_for_multiples_of_16():
    torch.manual_seed(1)
    net = UNet().eval()
    x = torch.rand(1, 1, 48, 80)
    with torch.no_grad():
        assert torch.equal(net(x), net.forward_padded(x))


def test_gradients_reach_first_layer():
    torch.manual_seed(2)
    net = UNet()
    net(torch.rand(2, 1, 32, 32)).mean().backward()
    first = net.down[0][0].weight.grad
    assert first is not None and float(first.abs().sum()) > 0
