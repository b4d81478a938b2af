"""The A2CAT-VN conv base and visual-navigation heads in PyTorch, for speed comparisons.

`TorchNetwork(agent, image_size)` has the layers and sizes of `networks.A2CATNet` for
an `agent` configuration section: conv1 and conv2 per image stream (`conv_kernels`,
`conv_strides`, `conv_channels`, `conv_padding`: "same" pads as XLA does), the two
streams concatenated, conv3, conv4 and the dense layer; then the depth, segmentation
and target-segmentation heads of `agent.vision_heads`: "upsample" as a 4x4/2
transposed convolution (padding 1, the same x2 upsampling as the package's sub-pixel
convolution) and a 3x3 conv, "transposed" as two 4x4/2 transposed convolutions
without padding through 16 channels (the authors' layout). It is written the way a
PyTorch implementation usually is: NCHW, both image streams computed for every frame,
`nn.ConvTranspose2d` for the deconvolutions. The default section gives the package's
network, `configs/presets/authors_network.yaml` the authors'. Needs `pip install
torch==2.13.0` (the `bench` extra); nothing else in the package imports it.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

UPSAMPLE_HIDDEN = {"depth": 32, "segmentation": 64, "target_segmentation": 64}  # networks.VNHeads.HIDDEN
TRANSPOSED_HIDDEN = 16  # networks.TransposedVNHeads.HIDDEN


def _same_padding(n: int, kernel: int, stride: int) -> tuple[int, int]:
    """(before, after) padding of XLA's "SAME" for an n-pixel input."""
    total = max((-(-n // stride) - 1) * stride + kernel - n, 0)
    return total // 2, total - total // 2


class TorchNetwork(nn.Module):
    def __init__(self, agent, image_size: int, seg_out: int = 3):
        super().__init__()
        (c1, c2, c3, c4), kernels, strides = agent.conv_channels, agent.conv_kernels, agent.conv_strides
        self.kernels, self.strides, self.same = kernels, strides, agent.conv_padding == "same"
        self.sizes = agent.conv_sizes(image_size)
        self.aux = image_size // 4
        self.convs = nn.ModuleList(nn.Conv2d(c_in, c_out, k, stride=s) for c_in, c_out, k, s in
                                   zip((3, c1, 2 * c2, c3), (c1, c2, c3, c4), kernels, strides))
        self.dense = nn.Linear(c4 * self.sizes[4] ** 2, agent.dense_size)
        outputs = {"depth": 1, "segmentation": seg_out, "target_segmentation": seg_out}
        if agent.vision_heads == "upsample":
            self.heads = nn.ModuleDict({
                name: nn.Sequential(nn.ConvTranspose2d(c4, UPSAMPLE_HIDDEN[name], 4, stride=2, padding=1), nn.ReLU(),
                                    nn.Conv2d(UPSAMPLE_HIDDEN[name], out, 3, padding=1))
                for name, out in outputs.items()})
        else:
            self.heads = nn.ModuleDict({
                name: nn.Sequential(nn.ConvTranspose2d(c4, TRANSPOSED_HIDDEN, 4, stride=2), nn.ReLU(),
                                    nn.ConvTranspose2d(TRANSPOSED_HIDDEN, out, 4, stride=2))
                for name, out in outputs.items()})

    def conv(self, i: int, x):
        if self.same:
            top, bottom = _same_padding(x.shape[-1], self.kernels[i], self.strides[i])
            x = F.pad(x, (top, bottom, top, bottom))
        return F.relu(self.convs[i](x))

    def stream(self, rgb_uint8):
        return self.conv(1, self.conv(0, rgb_uint8.float() / 255.0))

    def forward(self, rgb, target_rgb):
        x = torch.cat([self.stream(rgb), self.stream(target_rgb)], 1)
        conv4 = self.conv(3, self.conv(2, x))
        feats = F.relu(self.dense(conv4.flatten(1)))
        a = self.aux
        return feats, {name: head(conv4)[..., :a, :a] for name, head in self.heads.items()}


def step_fn(agent, image_size: int, frames: int, seed: int = 0):
    """A closure doing one forward+backward pass over `frames` (observation, target)
    pairs of the network of `agent` (a configuration's agent section)."""
    torch.manual_seed(seed)
    model = TorchNetwork(agent, image_size)
    rgb = torch.randint(0, 256, (frames, 3, image_size, image_size), dtype=torch.uint8)
    target = torch.randint(0, 256, (frames, 3, image_size, image_size), dtype=torch.uint8)

    def step():
        model.zero_grad(set_to_none=True)
        feats, heads = model(rgb, target)
        loss = feats.square().mean() + sum(h.square().mean() for h in heads.values())
        loss.backward()

    return step
