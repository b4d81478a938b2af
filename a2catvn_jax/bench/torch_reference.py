"""The A2CAT-VN conv base and visual-navigation heads in PyTorch, for speed comparisons.

`TorchNetwork(cfg)` has the layers and sizes of `networks.A2CATNet` for a
configuration: conv1 and conv2 per image stream (`agent.conv_kernels`, `conv_strides`,
`conv_channels`, `conv_padding`; with "same", conv1 pads kernel - stride pixels at the
top/left as `networks.Conv1` does and the others pad as XLA's "SAME"), the two streams
concatenated, conv3, conv4 and the dense layer; then the depth, segmentation and
target-segmentation heads of `agent.vision_heads` with the outputs of
`agent.segmentation_loss`: "upsample" as a 4x4/2 transposed convolution (padding 1, the
same x2 upsampling as the package's sub-pixel convolution) and a 3x3 conv, cropped to
the auxiliary size; "transposed" as two 4x4/2 transposed convolutions without padding
through 16 channels (the authors' layout) and the same window of their output as
`networks.TransposedVNHeads` (edge pixels repeated where it leaves the map). It is
written the way a PyTorch implementation usually is: NCHW, both image streams computed
for every frame, `nn.ConvTranspose2d` for the deconvolutions. The default configuration
gives the package's network, `configs/presets/authors_network.yaml` the authors'. Needs
`pip install torch==2.13.0` (the `bench` extra); nothing else in the package imports it.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from a2catvn_jax.agent.layers import conv1_padding, conv_padding
from a2catvn_jax.agent.networks import TransposedVNHeads, VNHeads, transposed_heads_offset
from a2catvn_jax.env.scenes.spec import NUM_CLASSES


def same_padding(layer: int, n: int, kernel: int, stride: int) -> tuple[int, int]:
    """(before, after) padding of an n-pixel side for conv layer `layer` (0: conv1) with
    `conv_padding` "same": conv1's as `networks.Conv1`, the others' as XLA's "SAME"."""
    return conv1_padding(n, kernel, stride) if layer == 0 else conv_padding((n,), kernel, stride, "SAME")[0]


class TorchNetwork(nn.Module):
    def __init__(self, cfg):
        super().__init__()
        agent, size = cfg.agent, cfg.env.render.image_size
        (c1, c2, c3, c4), kernels, strides = agent.conv_channels, agent.conv_kernels, agent.conv_strides
        self.kernels, self.strides, self.same = kernels, strides, agent.conv_padding == "same"
        self.sizes = agent.conv_sizes(size)
        self.aux = size // cfg.train.aux_downsize
        self.convs = nn.ModuleList(nn.Conv2d(c_in, c_out, k, stride=s) for c_in, c_out, k, s in
                                   zip((3, c1, 2 * c2, c3), (c1, c2, c3, c4), kernels, strides))
        self.dense = nn.Linear(c4 * self.sizes[4] ** 2, agent.dense_size)
        seg_out = 3 if agent.segmentation_loss == "mse_rgb" else NUM_CLASSES
        outputs = {"depth": 1, "segmentation": seg_out, "target_segmentation": seg_out}
        self.offset = None
        if agent.vision_heads == "upsample":
            self.heads = nn.ModuleDict({
                name: nn.Sequential(nn.ConvTranspose2d(c4, VNHeads.HIDDEN[name], 4, stride=2, padding=1), nn.ReLU(),
                                    nn.Conv2d(VNHeads.HIDDEN[name], out, 3, padding=1))
                for name, out in outputs.items()})
        else:
            hidden = TransposedVNHeads.HIDDEN
            self.heads = nn.ModuleDict({
                name: nn.Sequential(nn.ConvTranspose2d(c4, hidden, 4, stride=2), nn.ReLU(),
                                    nn.ConvTranspose2d(hidden, out, 4, stride=2))
                for name, out in outputs.items()})
            self.offset = transposed_heads_offset(agent, size, cfg.train.aux_downsize)

    def conv(self, i: int, x):
        if self.same:
            x = F.pad(x, same_padding(i, x.shape[-1], self.kernels[i], self.strides[i]) * 2)
        return F.relu(self.convs[i](x))

    def stream(self, rgb_uint8):
        return self.conv(1, self.conv(0, rgb_uint8.float() / 255.0))

    def window(self, z):
        """The heads' aux x aux output: cropped ("upsample"), or TransposedVNHeads' window."""
        a = self.aux
        if self.offset is None:
            return z[..., :a, :a]
        n, start = z.shape[-1], self.offset
        before, after = max(0, -start), max(0, start + a - n)
        if before or after:
            z = F.pad(z, (before, after, before, after), mode="replicate")
        return z[..., start + before : start + before + a, start + before : start + before + a]

    def forward(self, rgb, target_rgb):
        x = torch.cat([self.stream(rgb), self.stream(target_rgb)], 1)
        conv4 = self.conv(3, self.conv(2, x))
        feats = F.relu(self.dense(conv4.flatten(1)))
        return feats, {name: self.window(head(conv4)) for name, head in self.heads.items()}


def step_fn(cfg, frames: int, seed: int = 0):
    """A closure doing one forward+backward pass over `frames` (observation, target)
    pairs of the network of configuration `cfg`."""
    torch.manual_seed(seed)
    model = TorchNetwork(cfg)
    size = cfg.env.render.image_size
    rgb = torch.randint(0, 256, (frames, 3, size, size), dtype=torch.uint8)
    target = torch.randint(0, 256, (frames, 3, size, size), dtype=torch.uint8)

    def step():
        model.zero_grad(set_to_none=True)
        feats, heads = model(rgb, target)
        loss = feats.square().mean() + sum(h.square().mean() for h in heads.values())
        loss.backward()

    return step
