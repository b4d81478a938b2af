"""The A2CAT-VN network (Flax linen): the model on top of the layers of `layers.py`.

`A2CATNet` is the conv base (shared observation / target stream, `SplitConv` conv3),
the memory core (LSTM or frame stack) and the heads (actor-critic, pixel control,
reward prediction, depth / segmentation in the layouts of `VNHeads` and
`TransposedVNHeads`). `make_networks` wraps it in `Networks`, pure functions of
(params, inputs), so the rest of the package never sees Flax. The design is described
in docs/architecture.md, speed measurements are in docs/benchmarks.md.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from a2catvn_jax.agent.layers import (Conv, Inits, Upsample2x, conv1_padding, conv2d, conv_transpose, depth_to_space,
                                      on_blocks, same_pad_before)
from a2catvn_jax.config import RP_FRAMES, AgentConfig, Config
from a2catvn_jax.env.scenes.spec import NUM_CLASSES

REWARD_CLASSES = 3  # zero, positive, negative
VN_HEADS = ("depth", "segmentation", "target_segmentation")
SHARED_LAYERS = ("conv1", "conv2", "conv3", "conv4")  # the conv base every head's gradient reaches
_PC_CHANNELS = 32


class Conv1(nn.Module):
    """conv1: kernel x kernel, stride `stride` on uint8 RGB; optional space-to-depth (the
    same function computed on stride x stride pixel blocks, `layers.on_blocks`).

    padding "same": `kernel - stride` pixels at the top/left and enough at the
    bottom/right for ceil(H / stride) outputs; "valid": none."""

    features: int
    space_to_depth: bool = False
    kernel_size: int = 8
    stride: int = 4
    padding: str = "same"
    kernel_init: Any = nn.initializers.lecun_normal()
    impl: str = "auto"

    @nn.compact
    def __call__(self, image):
        n, h, w, c = image.shape
        k, s = self.kernel_size, self.stride
        kernel = self.param("kernel", self.kernel_init, (k, k, c, self.features))
        bias = self.param("bias", nn.initializers.zeros, (self.features,))
        # conv(image / 255, kernel) = conv(image, kernel / 255): the image stays uint8 through
        # the padding and the rearranging into blocks and patches (a quarter of the bytes).
        x, scaled = image, kernel * (1.0 / 255.0)
        if self.padding == "same":
            x = jnp.pad(x, ((0, 0), conv1_padding(h, k, s), conv1_padding(w, k, s), (0, 0)))
        else:  # only the rows and columns the windows reach (a multiple of the stride when the kernel is)
            oh, ow = (h - k) // s + 1, (w - k) // s + 1
            x = x[:, : (oh - 1) * s + k, : (ow - 1) * s + k]
        if self.space_to_depth:
            y = conv2d(*on_blocks(x, scaled, s), 1, "VALID", self.impl)
        else:
            y = conv2d(x, scaled, s, "VALID", self.impl)
        return y + bias


class SplitConv(nn.Module):
    """conv3: a conv layer on two maps side by side, observation features `a` [N, ...,
    c_a] and target features `b` [.., c_b], with the parameters of `Conv` on their
    concatenation ("kernel" [k, k, c_a + c_b, F], "bias" [F]).

    A convolution is linear in its input channels, so conv(concat(a, b)) = conv(a,
    kernel[:, :, :c_a]) + conv(b, kernel[:, :, c_a:]) (padding adds zeros to both). The
    network's targets are few (one image per goal) and every frame of a goal has the
    same target features, so `target` runs once per distinct target image and each
    frame adds its target's result (`observation(a) + target(b)[index]`), instead of
    every frame convolving its copy of the target's features."""

    features: int
    kernel_size: int
    stride: int
    padding: Any
    in_observation: int
    in_target: int
    kernel_init: Any = nn.initializers.lecun_normal()
    impl: str = "auto"

    def setup(self):
        k, c = self.kernel_size, self.in_observation + self.in_target
        self.kernel = self.param("kernel", self.kernel_init, (k, k, c, self.features))
        self.bias = self.param("bias", nn.initializers.zeros, (self.features,))

    def observation(self, a):
        """The observation channels' part, bias included."""
        return conv2d(a, self.kernel[:, :, : self.in_observation], self.stride, self.padding, self.impl) + self.bias

    def target(self, b):
        """The target channels' part."""
        return conv2d(b, self.kernel[:, :, self.in_observation :], self.stride, self.padding, self.impl)


class A2CATNet(nn.Module):
    """The network. Shapes: images [N, H, W, 3] uint8; features [N, dense_size]."""

    cfg: AgentConfig
    num_actions: int
    image_size: int
    pc_cell: int = 4
    aux_downsize: int = 4
    num_classes: int = 25

    def setup(self):
        cfg, init = self.cfg, Inits.of(self.cfg.init)
        c1, c2, c3, c4 = cfg.conv_channels
        k1, k2, k3, k4 = cfg.conv_kernels
        s1, s2, s3, s4 = cfg.conv_strides
        pad, impl = cfg.conv_padding.upper(), cfg.conv_impl
        self.conv1 = Conv1(c1, cfg.space_to_depth, k1, s1, cfg.conv_padding, init.kernel, impl)
        self.conv2 = Conv(c2, k2, s2, pad, init.kernel, impl)
        self.conv3 = SplitConv(c3, k3, s3, pad, c2, c2, init.kernel, impl)
        self.conv4 = Conv(c4, k4, s4, pad, init.kernel, impl)
        self.dense = nn.Dense(cfg.dense_size, kernel_init=init.kernel)
        if cfg.memory == "lstm":
            self.lstm = nn.OptimizedLSTMCell(cfg.core_size, **init.lstm)
        else:
            self.stack_dense = nn.Dense(cfg.core_size, kernel_init=init.kernel)
        self.policy = nn.Dense(self.num_actions, kernel_init=init.policy)
        self.value = nn.Dense(1, kernel_init=init.kernel)
        # Pixel control.
        g = self.pc_grid
        self.pc_half = -(-g // 2)
        self.pc_dense = nn.Dense(self.pc_half * self.pc_half * _PC_CHANNELS, kernel_init=init.kernel)
        self.pc_value = Upsample2x(1, init.kernel, impl)
        self.pc_advantage = Upsample2x(self.num_actions, init.kernel, impl)
        # Reward prediction.
        self.rp = nn.Dense(REWARD_CLASSES, kernel_init=init.kernel)
        # Visual-navigation auxiliary heads.
        seg_out = 3 if cfg.segmentation_loss == "mse_rgb" else self.num_classes
        outputs = {"depth": 1, "segmentation": seg_out, "target_segmentation": seg_out}
        if cfg.vision_heads == "transposed":
            self.vn = TransposedVNHeads(outputs, self.aux_size, transposed_heads_offset(cfg, self.image_size, self.aux_downsize),
                                        init.transposed)
        else:
            self.vn = VNHeads(outputs, self.aux_size, init.kernel, impl)

    # -- sizes ----------------------------------------------------------------------

    @property
    def pc_grid(self) -> int:
        return self.image_size // self.pc_cell

    @property
    def aux_size(self) -> int:
        return self.image_size // self.aux_downsize

    # -- conv base --------------------------------------------------------------------

    def target_stream(self, target_rgb):
        """What target images add to conv3 (before its ReLU): conv1, conv2 and conv3's
        target part (`SplitConv`) -> [N, g3, g3, c3]."""
        return self.conv3.target(self._stream(target_rgb))

    def _stream(self, rgb):
        return nn.relu(self.conv2(nn.relu(self.conv1(rgb))))

    def encode(self, rgb, target_features):
        """Observation images and their targets' stream features -> (conv4 maps, dense features)."""
        x = nn.relu(self.conv3.observation(self._stream(rgb)) + target_features)
        conv4 = nn.relu(self.conv4(x))
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


class VNHeads(nn.Module):
    """Depth / observation segmentation / target segmentation heads on conv4, layout
    "upsample" (`agent.vision_heads`).

    Each head is a stride-2 learned upsampling to HIDDEN[head] channels, ReLU, and a 3x3
    conv to its outputs, cropped at the bottom/right (or, when smaller, bilinearly
    resized) to `size` x `size`. With the default conv stack conv4 is at 1/8 of the
    image resolution and the heads at 1/4. The upsampling layers of the requested heads
    read the same input, so they run as one convolution with their kernels side by
    side: the same function as separate layers, in one pass.
    """

    outputs: dict  # head -> output channels
    size: int
    kernel_init: Any = nn.initializers.lecun_normal()
    impl: str = "auto"
    HIDDEN = {"depth": 32, "segmentation": 64, "target_segmentation": 64}

    @nn.compact
    def __call__(self, x, heads: tuple):
        c_in = x.shape[-1]
        kernels = {h: self.param(f"{h}_up_kernel", self.kernel_init, (2, 2, c_in, 4 * n))
                   for h, n in self.HIDDEN.items()}
        biases = {h: self.param(f"{h}_up_bias", nn.initializers.zeros, (4 * n,)) for h, n in self.HIDDEN.items()}
        finals = {h: Conv(self.outputs[h], 3, 1, "SAME", self.kernel_init, self.impl, name=f"{h}_out")
                  for h in self.HIDDEN}
        if not heads:
            return {}
        kernel = jnp.concatenate([kernels[h] for h in heads], axis=-1)
        bias = jnp.concatenate([biases[h] for h in heads])
        y = conv2d(x, kernel, 1, ((0, 1), (0, 1)), self.impl)
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


def transposed_heads_offset(cfg: AgentConfig, image_size: int, aux_downsize: int) -> int:
    """Where the `TransposedVNHeads` output's window of auxiliary-target cells starts.

    Follows where each layer's pixels lie in the image: a conv's output pixel at the
    centre of its window (padding included), output pixel m of a 4x4/2 transposed conv
    at input position (m - 3/2) / 2 (where bilinear interpolation puts it). After the
    conv stack and the two transposed convs, output pixel q lies at image position
    a + b * q with b = aux_downsize (config-checked); target cell t (the image's pixels
    [t * b, (t + 1) * b)) is centred on t * b + b / 2. The offset puts each cell on the
    output pixel nearest to it."""
    a, b = 0.5, 1.0  # the image's pixel x is centred on x + 0.5
    sizes = cfg.conv_sizes(image_size)
    for i, (k, s) in enumerate(zip(cfg.conv_kernels, cfg.conv_strides)):
        if cfg.conv_padding == "valid":
            before = 0
        else:
            before = k - s if i == 0 else same_pad_before(sizes[i], k, s)
        a, b = a + b * ((k - 1) / 2 - before), b * s
    for _ in range(2):  # the transposed convs' output pixel m at input position (m - 3/2) / 2
        a, b = a - b * 3 / 4, b / 2
    return math.floor((aux_downsize / 2 - a) / b + 0.5)


class TransposedVNHeads(nn.Module):
    """Depth / observation segmentation / target segmentation heads on conv4, layout
    "transposed" (`agent.vision_heads`).

    Each head is a 4x4/2 transposed conv (no padding) to HIDDEN channels, ReLU, and a
    4x4/2 transposed conv to its outputs: an n x n conv4 map becomes 4n + 6 pixels wide,
    at a quarter of conv4's stride in the image. Of that map the heads return the
    `size` x `size` window starting at `offset` (`transposed_heads_offset`), which
    aligns the output pixels with the target cells; where the window leaves the map
    (rows and columns of the image that conv4 does not see, e.g. with valid padding) its
    pixels repeat the map's nearest edge pixel, where it is larger than needed the rest
    is cropped. The first layers of the requested heads run as one transposed conv with
    their kernels side by side.
    """

    outputs: dict  # head -> output channels
    size: int
    offset: int
    kernel_init: Any = nn.initializers.lecun_normal()
    HIDDEN = 16
    HEADS = ("depth", "segmentation", "target_segmentation")

    @nn.compact
    def __call__(self, x, heads: tuple):
        c_in, hid = x.shape[-1], self.HIDDEN
        k1 = {h: self.param(f"{h}_deconv1_kernel", self.kernel_init, (4, 4, c_in, hid)) for h in self.HEADS}
        b1 = {h: self.param(f"{h}_deconv1_bias", nn.initializers.zeros, (hid,)) for h in self.HEADS}
        k2 = {h: self.param(f"{h}_deconv2_kernel", self.kernel_init, (4, 4, hid, self.outputs[h])) for h in self.HEADS}
        b2 = {h: self.param(f"{h}_deconv2_bias", nn.initializers.zeros, (self.outputs[h],)) for h in self.HEADS}
        if not heads:
            return {}
        y = conv_transpose(x, jnp.concatenate([k1[h] for h in heads], axis=-1), 2)
        y = nn.relu(y + jnp.concatenate([b1[h] for h in heads]))
        out = {}
        for i, h in enumerate(heads):
            z = conv_transpose(y[..., i * hid : (i + 1) * hid], k2[h], 2) + b2[h]
            out[h] = self._window(z)
        return out

    def _window(self, z):
        n, start, end = z.shape[1], self.offset, self.offset + self.size
        before, after = max(0, -start), max(0, end - n)
        if before or after:
            z = jnp.pad(z, ((0, 0), (before, after), (before, after), (0, 0)), mode="edge")
        return z[:, start + before : end + before, start + before : end + before]


Params = Any  # the network's parameter pytree
Carry = Any  # the memory core's state pytree, leaves [N, ...]


@functools.partial(jax.jit, static_argnums=0)
def _init(module: A2CATNet, key) -> Params:
    img = jnp.zeros((1, module.image_size, module.image_size, 3), jnp.uint8)
    return module.init(key, img, img, jnp.zeros((1,), jnp.int32), jnp.zeros((1,)))


@dataclasses.dataclass(frozen=True)
class Networks:
    """The A2CAT-VN network as pure functions of its parameters (shapes: N frames).

    images [N, H, W, 3] uint8; target features (what a target adds to conv3,
    `A2CATNet.target_stream`) [N, g3, g3, c3]; conv4 maps
    [N, g, g, c4]; features [N, dense]; core outputs [N, core]. `blind` (controls of what
    an agent uses its sight for): "both" sees every observation and target image as
    zeros, "target" the target images only (it sees the house, not the goal),
    "observation" the observations only (it sees the goal, not the house).
    """

    module: A2CATNet
    num_actions: int
    blind: str = "none"

    def init(self, key) -> Params:
        """Freshly initialised parameters (one compiled program per network: called
        outside `jit`, Flax's init would run op by op, an XLA compile per operation)."""
        return _init(self.module, key)

    def initial_carry(self, batch: int) -> Carry:
        """The memory core's state at an episode start, for `batch` agents."""
        return self.module.apply({}, batch, method=A2CATNet.initial_carry)

    def clear(self, carry: Carry, reset) -> Carry:
        """`carry` with the state of the agents where `reset` [N] is set back to the initial one."""
        init = self.initial_carry(reset.shape[0])
        return jax.tree_util.tree_map(
            lambda c, z: jnp.where(reset.reshape((-1,) + (1,) * (c.ndim - 1)), z, c), carry, init)

    def target_stream(self, params: Params, target_rgb):
        """What target images [K, H, W, 3] add to conv3: conv1, conv2 and conv3's target
        part -> [K, g3, g3, c3]."""
        if self.blind in ("both", "target"):
            target_rgb = jnp.zeros_like(target_rgb)
        return self.module.apply(params, target_rgb, method=A2CATNet.target_stream)

    def encode(self, params: Params, rgb, target_features):
        """Observations [N, H, W, 3] and their targets' stream features -> (conv4 maps, features)."""
        if self.blind in ("both", "observation"):
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


def num_params(params: Params) -> int:
    """Number of scalars in a parameter pytree."""
    return sum(int(x.size) for x in jax.tree_util.tree_leaves(params))
