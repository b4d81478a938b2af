"""The A2CAT-VN conv base and visual-navigation heads in PyTorch, for speed comparisons.

Same layers and sizes as `networks.A2CATNet` (conv1 8x8/4 padded 4 at the top/left,
conv2 4x4/2, conv3 and conv4 3x3/1, dense; depth / segmentation / target
segmentation heads of a 4x4/2 transposed convolution and a 3x3 conv), written the
way a PyTorch implementation usually is: NCHW, both image streams computed for every
frame, `nn.ConvTranspose2d` for the deconvolutions. Needs `pip install torch==2.13.0`
(the `bench` extra); nothing else in the package imports it.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn


class TorchConvBase(nn.Module):
    def __init__(self, image_size: int, channels=(16, 32, 32, 32), dense: int = 256, seg_out: int = 3):
        super().__init__()
        c1, c2, c3, c4 = channels
        self.size = image_size
        self.conv1 = nn.Conv2d(3, c1, 8, stride=4)
        self.conv2 = nn.Conv2d(c1, c2, 4, stride=2)
        self.conv3 = nn.Conv2d(2 * c2, c3, 3, padding=1)
        self.conv4 = nn.Conv2d(c3, c4, 3, padding=1)
        g = math.ceil(math.ceil(image_size / 4) / 2)
        self.dense = nn.Linear(c4 * g * g, dense)
        self.heads = nn.ModuleDict({
            name: nn.Sequential(nn.ConvTranspose2d(c4, hidden, 4, stride=2, padding=1), nn.ReLU(),
                                nn.Conv2d(hidden, out, 3, padding=1))
            for name, hidden, out in (("depth", 32, 1), ("segmentation", 64, seg_out), ("target_segmentation", 64, seg_out))
        })

    def stream(self, rgb_uint8):
        x = rgb_uint8.float() / 255.0
        h = x.shape[-1]
        hp = math.ceil(h / 4) * 4
        x = F.pad(x, (4, hp - h, 4, hp - h))
        x = F.relu(self.conv1(x))
        n = x.shape[-1]
        total = max((math.ceil(n / 2) - 1) * 2 + 4 - n, 0)  # "SAME" padding of a 4x4/2 conv
        x = F.pad(x, (total // 2, total - total // 2, total // 2, total - total // 2))
        return F.relu(self.conv2(x))

    def forward(self, rgb, target_rgb):
        x = torch.cat([self.stream(rgb), self.stream(target_rgb)], 1)
        conv4 = F.relu(self.conv4(F.relu(self.conv3(x))))
        feats = F.relu(self.dense(conv4.flatten(1)))
        a = self.size // 4
        return feats, {name: head(conv4)[..., :a, :a] for name, head in self.heads.items()}


def step_fn(image_size: int, frames: int, seed: int = 0):
    """A closure doing one forward+backward pass over `frames` (observation, target) pairs."""
    torch.manual_seed(seed)
    model = TorchConvBase(image_size)
    rgb = torch.randint(0, 256, (frames, 3, image_size, image_size), dtype=torch.uint8)
    target = torch.randint(0, 256, (frames, 3, image_size, image_size), dtype=torch.uint8)

    def step():
        model.zero_grad(set_to_none=True)
        feats, heads = model(rgb, target)
        loss = feats.square().mean() + sum(h.square().mean() for h in heads.values())
        loss.backward()

    return step
