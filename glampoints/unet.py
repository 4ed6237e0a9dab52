"""The GLAMpoints score network: a standard 4-level UNet with a sigmoid output.

Paper ("Network"): 3x3 convolution blocks with batch normalisation and ReLU, a 4-level UNet
(Ronneberger et al.) and a final sigmoid, so the output is a per-pixel keypoint probability.
Channels 8, 16, 32, 64 on the way down, 128 at the bottleneck; max-pooling down, 2x2 stride-2
transposed convolutions up, skip connections by concatenation: 487,145 learnable parameters.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F  # noqa: N812 (PyTorch convention)
from torch import nn

CHANNELS: tuple[int, ...] = (8, 16, 32, 64, 128)
LEVELS = len(CHANNELS) - 1  # 4 poolings: inputs are padded to a multiple of 2**4
MULTIPLE = 2**LEVELS


def conv_block(c_in: int, c_out: int) -> nn.Sequential:
    """Two (3x3 conv, BatchNorm, ReLU) layers; padding keeps the size."""
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, padding=1),
        nn.BatchNorm2d(c_out),
        nn.ReLU(inplace=True),
        nn.Conv2d(c_out, c_out, 3, padding=1),
        nn.BatchNorm2d(c_out),
        nn.ReLU(inplace=True),
    )


class UNet(nn.Module):
    """Grey image (B,1,H,W) in [0,1] -> keypoint score map (B,1,H,W) in [0,1].

    Any H, W is accepted: the input is reflect-padded (zero-padded when too small to reflect)
    on the bottom/right to a multiple of 16 and the output cropped back.
    """

    def __init__(self, in_channels: int = 1, channels: tuple[int, ...] = CHANNELS) -> None:
        super().__init__()
        self.channels = tuple(channels)
        self.down = nn.ModuleList()
        c_prev = in_channels
        for c in self.channels[:-1]:
            self.down.append(conv_block(c_prev, c))
            c_prev = c
        self.bottleneck = conv_block(self.channels[-2], self.channels[-1])
        self.up = nn.ModuleList()
        self.dec = nn.ModuleList()
        for c_hi, c in zip(self.channels[:0:-1], self.channels[-2::-1], strict=True):
            self.up.append(nn.ConvTranspose2d(c_hi, c, kernel_size=2, stride=2))
            self.dec.append(conv_block(2 * c, c))
        self.head = nn.Conv2d(self.channels[0], 1, kernel_size=1)

    def features_padded(self, x: torch.Tensor) -> torch.Tensor:
        """Last decoder features (B,8,H,W); H and W must be multiples of 16."""
        skips = []
        for block in self.down:
            x = block(x)
            skips.append(x)
            x = F.max_pool2d(x, 2)
        x = self.bottleneck(x)
        for up, dec, skip in zip(self.up, self.dec, reversed(skips), strict=True):
            x = dec(torch.cat([up(x), skip], dim=1))
        return x

    def forward_padded(self, x: torch.Tensor) -> torch.Tensor:
        """The network proper; H and W must be multiples of 16."""
        return torch.sigmoid(self.head(self.features_padded(x)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        x = pad_to_multiple(x, MULTIPLE)
        return self.forward_padded(x)[..., :h, :w]


def pad_to_multiple(x: torch.Tensor, multiple: int = MULTIPLE) -> torch.Tensor:
    """Pad the bottom/right of (B,C,H,W) to multiples of `multiple`: reflect, or zeros if tiny."""
    h, w = x.shape[-2:]
    ph, pw = (-h) % multiple, (-w) % multiple
    if ph == 0 and pw == 0:
        return x
    mode = "reflect" if ph < h and pw < w else "constant"
    return F.pad(x, (0, pw, 0, ph), mode=mode)


def count_parameters(net: nn.Module) -> int:
    """Number of learnable parameters."""
    return sum(p.numel() for p in net.parameters() if p.requires_grad)
