"""A small convolutional backbone for the 4-channel (RGB + depth) camera images.

    images [N, 4, H_in, W_in] -> stride 2 (c1) -> stride 4 (c2) -> stride 8 (c2)
    -> tokens [N, D, H_in/4, W_in/4] = 1x1(stride 4) + upsampled 1x1(stride 8)

Objects are small (median 8 x 10 pixels, pedestrians 5 x 12), so the tokens stay at stride 4;
the stride-8 stage only adds context (receptive field ~50 pixels) for trucks and buses.
"""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor, nn


def conv_bn_relu(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    """3x3 convolution + BatchNorm + ReLU."""
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1, bias=False),
                         nn.BatchNorm2d(c_out), nn.ReLU(inplace=True))


class ImageBackbone(nn.Module):
    """Three stride-2 stages of two 3x3 convolutions each, merged at stride 4."""

    def __init__(self, c1: int, c2: int, d_model: int, in_channels: int = 4) -> None:
        super().__init__()
        self.stage1 = nn.Sequential(conv_bn_relu(in_channels, c1, 2), conv_bn_relu(c1, c1))
        self.stage2 = nn.Sequential(conv_bn_relu(c1, c2, 2), conv_bn_relu(c2, c2))
        self.stage3 = nn.Sequential(conv_bn_relu(c2, c2, 2), conv_bn_relu(c2, c2))
        self.lateral = nn.Conv2d(c2, d_model, 1)
        self.top = nn.Conv2d(c2, d_model, 1)

    def forward(self, images: Tensor) -> Tensor:
        """`[N, 4, H_in, W_in]` -> `[N, D, H_in/4, W_in/4]`."""
        s2 = self.stage2(self.stage1(images))
        s3 = self.stage3(s2)
        return self.lateral(s2) + F.interpolate(self.top(s3), size=s2.shape[-2:],
                                                mode="nearest")
