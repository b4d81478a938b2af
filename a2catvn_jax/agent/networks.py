"""The A2CAT-VN network (Flax linen).

Conv base: the observation and the target image each pass the same two strided conv
layers (shared weights: conv1 8x8/4, conv2 4x4/2); the two feature maps are
concatenated and pass conv3 and conv4 (3x3/1) and one dense layer, ReLU everywhere.
These features, the one-hot previous action and the previous reward clipped to
[-1, 1] feed the memory core: an LSTM, or (the frame-stack variant) a dense layer over
the features of the last `stack` frames. Heads:

- actor (policy logits) and critic (value): affine maps of the core output;
- pixel control: dense + stride-2 deconvolution from the core output to a
  (image // cell)^2 grid of Q-values per action, dueling (V + A - mean A);
- reward prediction: conv4 features of three consecutive frames -> 3 classes
  (zero, positive, negative reward);
- depth, observation segmentation, target segmentation: stride-2 deconvolution heads
  on conv4, at 1/`aux_downsize` of the image resolution.

`make_networks` wraps the Flax module in `Networks`, a set of pure functions of
(params, inputs): the rest of the package never sees Flax. The network is split into
functions so that the update can run the conv base on a whole rollout at once, the
core step by step (`lax.scan`), and each head only where its loss has a non-zero
weight. The target stream (conv1, conv2 of the target image) is a function of its own
because targets are few: it runs once per distinct target image and the result is
gathered.

conv1 works on uint8 images. With `space_to_depth` it is computed as a 2x2/1 conv on
4x4 pixel blocks (48 channels) with the same 8x8x3 kernel rearranged: the same
function, which some backends run faster (docs/benchmarks.md). Both paths pad the image by 4 pixels at the
top/left (and to a multiple of 4 at the bottom/right), so conv1 maps an HxW image to
ceil(H/4) x ceil(W/4).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from a2catvn_jax.config import AgentConfig, Config
from a2catvn_jax.env.scenes.spec import NUM_CLASSES

REWARD_CLASSES = 3  # zero, positive, negative
RP_FRAMES = 3  # frames seen by the reward-prediction head
VN_HEADS = ("depth", "segmentation", "target_segmentation")
SHARED_LAYERS = ("conv1", "conv2", "conv3", "conv4")  # the conv base every head's gradient reaches
_PC_CHANNELS = 32


def depth_to_space(x, block: int):
    """[N, H, W, b*b*C] -> [N, H*b, W*b, C], the inverse of `space_to_depth`."""
    n, h, w, c = x.shape
    c //= block * block
    x = x.reshape(n, h, w, block, block, c).transpose(0, 1, 3, 2, 4, 5)
    return x.reshape(n, h * block, w * block, c)


def space_to_depth(x, block: int):
    """[N, H, W, C] -> [N, H/b, W/b, b*b*C], channels ordered (row in block, col in block, C)."""
    n, h, w, c = x.shape
    x = x.reshape(n, h // block, block, w // block, block, c)
    return x.transpose(0, 1, 3, 2, 4, 5).reshape(n, h // block, w // block, block * block * c)


class Conv1(nn.Module):
    """conv1: 8x8 stride 4 on uint8 RGB, padded 4 at the top/left; optional space-to-depth."""

    features: int
    space_to_depth: bool = False

    @nn.compact
    def __call__(self, image):
        n, h, w, c = image.shape
        kernel = self.param("kernel", nn.initializers.lecun_normal(), (8, 8, c, self.features))
        bias = self.param("bias", nn.initializers.zeros, (self.features,))
        hp, wp = -(-h // 4) * 4, -(-w // 4) * 4
        x = image.astype(jnp.float32) * (1.0 / 255.0)
        x = jnp.pad(x, ((0, 0), (4, hp - h), (4, wp - w), (0, 0)))
        dims = ("NHWC", "HWIO", "NHWC")
        if self.space_to_depth:
            x = space_to_depth(x, 4)
            k = kernel.reshape(2, 4, 2, 4, c, self.features).transpose(0, 2, 1, 3, 4, 5).reshape(2, 2, 16 * c, self.features)
            y = jax.lax.conv_general_dilated(x, k, (1, 1), "VALID", dimension_numbers=dims)
        else:
            y = jax.lax.conv_general_dilated(x, kernel, (4, 4), "VALID", dimension_numbers=dims)
        return y + bias


class A2CATNet(nn.Module):
    """The network. Shapes: images [N, H, W, 3] uint8; features [N, dense_size]."""

    cfg: AgentConfig
    num_actions: int
    image_size: int
    pc_cell: int = 4
    aux_downsize: int = 4
    num_classes: int = 25

    def setup(self):
        c1, c2, c3, c4 = self.cfg.conv_channels
        self.conv1 = Conv1(c1, self.cfg.space_to_depth)
        self.conv2 = nn.Conv(c2, (4, 4), (2, 2), padding="SAME")
        self.conv3 = nn.Conv(c3, (3, 3), (1, 1), padding="SAME")
        self.conv4 = nn.Conv(c4, (3, 3), (1, 1), padding="SAME")
        self.dense = nn.Dense(self.cfg.dense_size)
        if self.cfg.memory == "lstm":
            self.lstm = nn.OptimizedLSTMCell(self.cfg.core_size)
        else:
            self.stack_dense = nn.Dense(self.cfg.core_size)
        self.policy = nn.Dense(self.num_actions, kernel_init=nn.initializers.orthogonal(0.01))
        self.value = nn.Dense(1)
        # Pixel control.
        g = self.pc_grid
        self.pc_half = -(-g // 2)
        self.pc_dense = nn.Dense(self.pc_half * self.pc_half * _PC_CHANNELS)
        self.pc_value = Upsample2x(1)
        self.pc_advantage = Upsample2x(self.num_actions)
        # Reward prediction.
        self.rp = nn.Dense(REWARD_CLASSES)
        # Visual-navigation auxiliary heads.
        seg_out = 3 if self.cfg.segmentation_loss == "mse_rgb" else self.num_classes
        self.vn = VNHeads({"depth": 1, "segmentation": seg_out, "target_segmentation": seg_out}, self.aux_size)

    # -- sizes ----------------------------------------------------------------------

    @property
    def pc_grid(self) -> int:
        return self.image_size // self.pc_cell

    @property
    def aux_size(self) -> int:
        return self.image_size // self.aux_downsize

    # -- conv base --------------------------------------------------------------------

    def target_stream(self, target_rgb):
        """conv1, conv2 of target images: [N, g, g, c2]."""
        return self._stream(target_rgb)

    def _stream(self, rgb):
        return nn.relu(self.conv2(nn.relu(self.conv1(rgb))))

    def encode(self, rgb, target_features):
        """Observation images and their targets' stream features -> (conv4 maps, dense features)."""
        x = jnp.concatenate([self._stream(rgb), target_features], axis=-1)
        conv4 = nn.relu(self.conv4(nn.relu(self.conv3(x))))
        feats = nn.relu(self.dense(conv4.reshape(conv4.shape[0], -1)))
        return conv4, feats

    # -- memory core ------------------------------------------------------------------

    def initial_carry(self, batch: int):
        if self.cfg.memory == "lstm":
            z = jnp.zeros((batch, self.cfg.core_size), jnp.float32)
            return (z, z)
        return jnp.zeros((batch, self.cfg.stack - 1, self.cfg.dense_size), jnp.float32)

    def core(self, carry, features, prev_action, prev_reward):
        """One step of the memory core: (carry, [N, core_size])."""
        extra = [jax.nn.one_hot(prev_action, self.num_actions), jnp.clip(prev_reward, -1.0, 1.0)[:, None]]
        if self.cfg.memory == "lstm":
            return self.lstm(carry, jnp.concatenate([features] + extra, -1))
        frames = jnp.concatenate([carry, features[:, None]], axis=1)
        out = nn.relu(self.stack_dense(jnp.concatenate([frames.reshape(frames.shape[0], -1)] + extra, -1)))
        return frames[:, 1:], out

    # -- heads ------------------------------------------------------------------------

    def actor_critic(self, core_out):
        """(policy logits [N, A], value [N])."""
        return self.policy(core_out), self.value(core_out)[:, 0]

    def pixel_control(self, core_out):
        """Dueling Q-values [N, G, G, A] on the pixel-control grid."""
        h = nn.relu(self.pc_dense(core_out)).reshape(-1, self.pc_half, self.pc_half, _PC_CHANNELS)
        g = self.pc_grid
        v = self.pc_value(h)[:, :g, :g]
        a = self.pc_advantage(h)[:, :g, :g]
        return v + a - a.mean(-1, keepdims=True)

    def reward_prediction(self, conv4_frames):
        """conv4 maps of RP_FRAMES consecutive frames [N, RP_FRAMES, g, g, c4] -> logits [N, 3]."""
        return self.rp(conv4_frames.reshape(conv4_frames.shape[0], -1))

    def vn_heads(self, conv4, heads=VN_HEADS):
        """Predictions of the named visual-navigation heads from conv4 maps [N, g, g, c4]:
        depth [N, a, a]; segmentation and target_segmentation [N, a, a, 3 or classes]."""
        out = self.vn(conv4, tuple(heads))
        if "depth" in out:
            out["depth"] = out["depth"][..., 0]
        return out

    def __call__(self, rgb, target_rgb, prev_action, prev_reward):
        """Every parameter in one pass (used to initialise)."""
        conv4, feats = self.encode(rgb, self.target_stream(target_rgb))
        carry, out = self.core(self.initial_carry(rgb.shape[0]), feats, prev_action, prev_reward)
        logits, value = self.actor_critic(out)
        stacked = jnp.stack([conv4] * RP_FRAMES, axis=1)
        return {
            "logits": logits,
            "value": value,
            "pixel_control": self.pixel_control(out),
            "reward_prediction": self.reward_prediction(stacked),
            **self.vn_heads(conv4),
        }


class Upsample2x(nn.Module):
    """A learned stride-2 upsampling ("deconvolution") as a sub-pixel convolution: a 2x2
    conv to 4x the channels, each output pixel's 2x2 block taken from its own channels.

    Like a 4x4 stride-2 transposed convolution, every output pixel is an affine map of a
    2x2 input neighbourhood with weights that depend on its position in the block, at
    the same cost; it runs several times faster than `nn.ConvTranspose` on XLA's CPU
    backend (docs/benchmarks.md).
    """

    features: int

    @nn.compact
    def __call__(self, x):
        y = nn.Conv(4 * self.features, (2, 2), padding=((0, 1), (0, 1)))(x)
        return depth_to_space(y, 2)


class VNHeads(nn.Module):
    """Depth / observation segmentation / target segmentation heads on conv4.

    Each head is a stride-2 learned upsampling to HIDDEN[head] channels, ReLU, and a 3x3
    conv to its outputs, cropped (or resized) to `size` x `size`. The upsampling layers
    of the requested heads read the same input, so they run as one convolution with
    their kernels side by side: the same function as separate layers, in one pass.
    """

    outputs: dict  # head -> output channels
    size: int
    HIDDEN = {"depth": 32, "segmentation": 64, "target_segmentation": 64}

    @nn.compact
    def __call__(self, x, heads: tuple):
        c_in = x.shape[-1]
        kernels = {h: self.param(f"{h}_up_kernel", nn.initializers.lecun_normal(), (2, 2, c_in, 4 * n))
                   for h, n in self.HIDDEN.items()}
        biases = {h: self.param(f"{h}_up_bias", nn.initializers.zeros, (4 * n,)) for h, n in self.HIDDEN.items()}
        finals = {h: nn.Conv(self.outputs[h], (3, 3), padding="SAME", name=f"{h}_out") for h in self.HIDDEN}
        if not heads:
            return {}
        kernel = jnp.concatenate([kernels[h] for h in heads], axis=-1)
        bias = jnp.concatenate([biases[h] for h in heads])
        y = jax.lax.conv_general_dilated(x, kernel, (1, 1), ((0, 1), (0, 1)), dimension_numbers=("NHWC", "HWIO", "NHWC"))
        y = nn.relu(y + bias)
        out, start = {}, 0
        for h in heads:
            width = 4 * self.HIDDEN[h]
            z = finals[h](depth_to_space(y[..., start : start + width], 2))
            start += width
            if z.shape[1] >= self.size:
                z = z[:, : self.size, : self.size]
            else:
                z = jax.image.resize(z, (z.shape[0], self.size, self.size, z.shape[-1]), "bilinear")
            out[h] = z
        return out


Params = Any  # the network's parameter pytree
Carry = Any  # the memory core's state pytree, leaves [N, ...]


@dataclasses.dataclass(frozen=True)
class Networks:
    """The A2CAT-VN network as pure functions of its parameters (shapes: N frames).

    images [N, H, W, 3] uint8; target features [N, g, g, c2]; conv4 maps
    [N, g, g, c4]; features [N, dense]; core outputs [N, core]. A `blind` network sees
    every observation and target image as zeros (the control that tells whether an
    agent uses its sight).
    """

    module: A2CATNet
    num_actions: int
    blind: bool = False

    def init(self, key) -> Params:
        """Freshly initialised parameters."""
        size = self.module.image_size
        img = jnp.zeros((1, size, size, 3), jnp.uint8)
        return self.module.init(key, img, img, jnp.zeros((1,), jnp.int32), jnp.zeros((1,)))

    def initial_carry(self, batch: int) -> Carry:
        """The memory core's state at an episode start, for `batch` agents."""
        return self.module.apply({}, batch, method=A2CATNet.initial_carry)

    def clear(self, carry: Carry, reset) -> Carry:
        """`carry` with the state of the agents where `reset` [N] is set back to the initial one."""
        init = self.initial_carry(reset.shape[0])
        return jax.tree_util.tree_map(
            lambda c, z: jnp.where(reset.reshape((-1,) + (1,) * (c.ndim - 1)), z, c), carry, init)

    def target_stream(self, params: Params, target_rgb):
        """conv1, conv2 of target images [K, H, W, 3] -> [K, g, g, c2]."""
        if self.blind:
            target_rgb = jnp.zeros_like(target_rgb)
        return self.module.apply(params, target_rgb, method=A2CATNet.target_stream)

    def encode(self, params: Params, rgb, target_features):
        """Observations [N, H, W, 3] and their targets' stream features -> (conv4 maps, features)."""
        if self.blind:
            rgb = jnp.zeros_like(rgb)
        return self.module.apply(params, rgb, target_features, method=A2CATNet.encode)

    def core(self, params: Params, carry: Carry, features, prev_action, prev_reward):
        """One step of the memory core: (carry, outputs [N, core])."""
        return self.module.apply(params, carry, features, prev_action, prev_reward, method=A2CATNet.core)

    def actor_critic(self, params: Params, core_out):
        """(policy logits [N, A], value [N])."""
        return self.module.apply(params, core_out, method=A2CATNet.actor_critic)

    def pixel_control(self, params: Params, core_out):
        """Dueling Q-values [N, G, G, A] on the pixel-control grid."""
        return self.module.apply(params, core_out, method=A2CATNet.pixel_control)

    def reward_prediction(self, params: Params, conv4_frames):
        """conv4 maps of RP_FRAMES consecutive frames [N, RP_FRAMES, g, g, c4] -> logits [N, 3]."""
        return self.module.apply(params, conv4_frames, method=A2CATNet.reward_prediction)

    def vn_heads(self, params: Params, conv4, heads=VN_HEADS) -> dict:
        """The named depth / segmentation heads on conv4 maps [N, g, g, c4]."""
        return self.module.apply(params, conv4, tuple(heads), method=A2CATNet.vn_heads)


def make_networks(cfg: Config, num_actions: int) -> Networks:
    """The network of configuration `cfg` for `num_actions` actions."""
    tc = cfg.train
    module = A2CATNet(cfg.agent, num_actions, cfg.env.render.image_size, tc.pixel_control_cell, tc.aux_downsize,
                      NUM_CLASSES)
    return Networks(module, num_actions, cfg.agent.blind)


def apply_flat(fn, x, lead: int = 2):
    """`fn` applied to x [*lead_axes, ...] with its `lead` leading axes flattened into one
    and restored on every output."""
    shape = x.shape[:lead]
    y = fn(x.reshape((-1,) + x.shape[lead:]))
    return jax.tree_util.tree_map(lambda a: a.reshape(shape + a.shape[1:]), y)

