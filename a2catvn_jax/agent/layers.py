"""Generic convolution kernels, layers and initialisers of the network (Flax linen).

`conv2d` computes a square convolution either by XLA's convolution or by matrix
products (the same function); its "auto" picks, on XLA's CPU backend, the one that timed
faster on this CPU for layers of that shape (`auto_impl`), on other backends XLA's. Also here: the `Conv` and
`Upsample2x` layers, the transposed convolution of the "transposed" vision heads, and
the kernel initialisers of `agent.init` (`Inits`). The model itself is in
`networks.py`; timings in docs/benchmarks.md, the design in docs/architecture.md.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp


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


_DIMS = ("NHWC", "HWIO", "NHWC")


def conv_padding(size: tuple, kernel: int, stride: int, padding) -> tuple:
    """Explicit ((top, bottom), (left, right)) padding: "VALID", "SAME" (as `lax`: half
    at the top/left, the rest at the bottom/right, for ceil(n / stride) outputs), or
    already explicit."""
    if not isinstance(padding, str):
        return tuple(tuple(p) for p in padding)
    if padding.upper() == "VALID":
        return ((0, 0), (0, 0))
    pads = []
    for n in size:
        total = max((-(-n // stride) - 1) * stride + kernel - n, 0)
        pads.append((total // 2, total - total // 2))
    return tuple(pads)


# `conv2d`'s "auto" on the CPU, chosen by timing this package's layers both ways on this
# CPU in its two networks at 32 and 84 px (docs/benchmarks.md, "Convolutions as matrix
# products"): matrix products for layers whose input has at most MATMUL_MAX_CHANNELS
# channels (counted on stride x stride pixel blocks for a strided layer: conv1, conv3's
# two parts and conv4 (32 channels each), the heads' upsampling, the depth output) and
# for strided layers on at least MATMUL_STRIDED_CHANNELS channels (the authors' conv2
# and conv3); XLA's convolution for the others (conv2 on 16 channels, the 3x3
# segmentation outputs on 64).
MATMUL_MAX_CHANNELS = 48
MATMUL_STRIDED_CHANNELS = 32


def auto_impl(stride: int, channels: int) -> str:
    """The implementation `conv2d`'s "auto" takes on the CPU for a layer of this stride on
    this many input channels (see MATMUL_MAX_CHANNELS)."""
    suits = stride * stride * channels <= MATMUL_MAX_CHANNELS or (stride > 1 and channels >= MATMUL_STRIDED_CHANNELS)
    return "matmul" if suits else "xla"


def conv1_padding(n: int, kernel: int, stride: int) -> tuple[int, int]:
    """`Conv1`'s "same" padding of an n-pixel side: kernel - stride pixels before, and
    after enough for ceil(n / stride) outputs."""
    return kernel - stride, -(-n // stride) * stride - n


def on_blocks(x, kernel, stride: int):
    """A VALID stride-s convolution of x [N, H, W, C] by kernel [k, k, C, F] as a stride-1
    one on s x s pixel blocks: (x's blocks [N, H', W', s*s*C], the kernel [m, m, s*s*C, F],
    m = ceil(k / s)), the same function. The kernel is zero-padded to m*s taps; x is cropped
    to the rows and columns the windows reach, or zero-padded up to them (they meet the
    padded kernel's zero taps)."""
    s, k = stride, kernel.shape[0]
    n, h, w, c = x.shape
    f, m = kernel.shape[-1], -(-k // stride)
    if m * s > k:
        kernel = jnp.pad(kernel, ((0, m * s - k), (0, m * s - k), (0, 0), (0, 0)))
    kernel = kernel.reshape(m, s, m, s, c, f).transpose(0, 2, 1, 3, 4, 5).reshape(m, m, s * s * c, f)
    hh, ww = s * ((h - k) // s + m), s * ((w - k) // s + m)
    x = x[:, :hh, :ww]
    if x.shape[1] < hh or x.shape[2] < ww:
        x = jnp.pad(x, ((0, 0), (0, hh - x.shape[1]), (0, ww - x.shape[2]), (0, 0)))
    return space_to_depth(x, s), kernel


def conv2d(x, kernel, stride: int = 1, padding="VALID", impl: str = "auto", form=None):
    """2-D convolution of x [N, H, W, C] (float, or integer: converted to the kernel's
    dtype) by kernel [k, k, C, F] (square kernel and stride; padding as `conv_padding`)
    -> [N, H', W', F], by XLA's convolution ("xla"), by matrix products ("matmul"), or
    "auto": on the CPU the one of the two that the layer's shape suits (`auto_impl`),
    XLA's convolution on other backends. Both compute the same function.

    "matmul" runs a strided conv as a stride-1 conv on stride x stride pixel blocks
    (`on_blocks`), then in the `form` "patches" (the kernel offsets' shifted inputs side
    by side times the kernel) or "shift" (the input times every offset's kernel, the
    shifted results summed); by default "shift" for layers with few outputs (at most a
    quarter of their inputs), else "patches"."""
    k = kernel.shape[0]
    pads = conv_padding(x.shape[1:3], k, stride, padding)
    if impl == "auto":
        impl = auto_impl(stride, x.shape[-1]) if jax.default_backend() == "cpu" else "xla"
    if impl == "xla":
        x = x.astype(kernel.dtype)
        return jax.lax.conv_general_dilated(x, kernel, (stride, stride), pads, dimension_numbers=_DIMS)
    if impl != "matmul":
        raise ValueError(f"conv impl must be 'auto', 'xla' or 'matmul', got {impl!r}")
    if any(pads[0] + pads[1]):
        x = jnp.pad(x, ((0, 0), pads[0], pads[1], (0, 0)))
    n, h, w, _ = x.shape
    oh, ow = (h - k) // stride + 1, (w - k) // stride + 1
    if stride > 1:
        x, kernel = on_blocks(x, kernel, stride)
    k, c, f = kernel.shape[0], kernel.shape[2], kernel.shape[3]
    x = x[:, : oh + k - 1, : ow + k - 1]
    taps = [(i, j) for i in range(k) for j in range(k)]
    if form is None:
        form = "shift" if 4 * f <= c else "patches"
    elif form not in ("shift", "patches"):
        raise ValueError(f"conv form must be 'patches' or 'shift', got {form!r}")
    # An integer input (uint8 images) is rearranged as it is, a quarter of float32's bytes,
    # and converted just before the product.
    if form == "shift":  # few outputs: every offset's outputs at every input pixel, shifted and summed
        z = jnp.dot(x.astype(kernel.dtype), kernel.transpose(2, 0, 1, 3).reshape(c, k * k * f))
        z = z.reshape(n, oh + k - 1, ow + k - 1, k * k, f)
        return sum(z[:, i : i + oh, j : j + ow, i * k + j] for i, j in taps)
    patches = jnp.concatenate([x[:, i : i + oh, j : j + ow] for i, j in taps], -1) if k > 1 else x
    return jnp.dot(patches.astype(kernel.dtype), kernel.reshape(k * k * c, f))


class Conv(nn.Module):
    """`flax.linen.Conv` for square kernels and strides (the same parameters, "kernel"
    [k, k, C, F] and "bias" [F]), computed by `conv2d` with implementation `impl`."""

    features: int
    kernel_size: int
    stride: int = 1
    padding: Any = "SAME"
    kernel_init: Any = nn.initializers.lecun_normal()
    impl: str = "auto"

    @nn.compact
    def __call__(self, x):
        k = self.kernel_size
        kernel = self.param("kernel", self.kernel_init, (k, k, x.shape[-1], self.features))
        bias = self.param("bias", nn.initializers.zeros, (self.features,))
        return conv2d(x, kernel, self.stride, self.padding, self.impl) + bias


def fan_in_uniform(transposed: bool = False):
    """Initialiser of kernels [..., in, out] uniform in +-1/sqrt(fan_in). fan_in is the
    kernel area times the input channels; for a transposed conv (`transposed`), the
    kernel area times the output channels, the count PyTorch's initialisers take for a
    transposed convolution's weight."""

    def init(key, shape, dtype=jnp.float32):
        fan_in = math.prod(shape[:-2]) * (shape[-1] if transposed else shape[-2])
        bound = 1.0 / math.sqrt(fan_in)
        return jax.random.uniform(key, shape, dtype, -bound, bound)

    return init


def _gates_glorot_uniform(gates: int = 4):
    """Initialiser of one gate's kernel [in, hidden] of an LSTM, Glorot-uniform over the
    `gates` gates' kernels together ([in, gates * hidden])."""

    def init(key, shape, dtype=jnp.float32):
        bound = math.sqrt(6.0 / (shape[0] + gates * shape[1]))
        return jax.random.uniform(key, shape, dtype, -bound, bound)

    return init


@dataclasses.dataclass(frozen=True)
class Inits:
    """The kernel initialisers of one `agent.init` choice. "lecun": conv and dense kernels
    LeCun-normal, the policy head orthogonal(0.01), the LSTM flax's defaults;
    "uniform_fan_in": every conv, transposed-conv and dense kernel (the policy head's
    too) uniform in +-1/sqrt(fan_in) (`fan_in_uniform`), the LSTM's input kernels
    Glorot-uniform over its four gates together, its recurrent kernels orthogonal over
    the four gates together. Biases start at zero in both."""

    kernel: Any  # conv and dense kernels
    transposed: Any  # transposed-conv kernels
    policy: Any  # the policy head's kernel
    lstm: dict  # OptimizedLSTMCell's initialiser arguments

    @staticmethod
    def of(name: str) -> "Inits":
        if name == "lecun":
            lecun = nn.initializers.lecun_normal()
            return Inits(lecun, lecun, nn.initializers.orthogonal(0.01), {})
        # The four gates' recurrent kernels, each orthogonal and scaled by 1/2, stacked
        # into [4 * hidden, hidden] have orthonormal columns.
        lstm = {"kernel_init": _gates_glorot_uniform(4), "recurrent_kernel_init": nn.initializers.orthogonal(0.5)}
        return Inits(fan_in_uniform(), fan_in_uniform(transposed=True), fan_in_uniform(), lstm)


class Upsample2x(nn.Module):
    """A learned stride-2 upsampling ("deconvolution") as a sub-pixel convolution: a 2x2
    conv to 4x the channels, each output pixel's 2x2 block taken from its own channels.

    Like a 4x4 stride-2 transposed convolution, every output pixel is an affine map of a
    2x2 input neighbourhood with weights that depend on its position in the block, at
    the same cost; it runs several times faster than `nn.ConvTranspose` on XLA's CPU
    backend (docs/benchmarks.md).
    """

    features: int
    kernel_init: Any = nn.initializers.lecun_normal()
    impl: str = "auto"

    @nn.compact
    def __call__(self, x):
        y = Conv(4 * self.features, 2, 1, ((0, 1), (0, 1)), self.kernel_init, self.impl)(x)
        return depth_to_space(y, 2)


def conv_transpose(x, kernel, stride: int):
    """Transposed convolution without padding of x [N, h, w, C] by kernel [k, k, C, F]
    (k a multiple of the stride): input pixel l adds x[l] * kernel[t] to output pixel
    stride * l + t (t < k), so the output is (h - 1) * stride + k pixels high.

    Computed as one matrix product (every input pixel's k x k x F contribution) and an
    overlap-add: with m = k / stride, output block j (pixels stride * j + r, r < stride)
    sums the contributions of input pixels j - a (a < m) at taps stride * a + r. On XLA's
    CPU backend this runs faster than a convolution of the stride-dilated input or a
    sub-pixel convolution (docs/benchmarks.md)."""
    k, s = kernel.shape[0], stride
    m, c, f = k // s, kernel.shape[2], kernel.shape[3]
    n, h, w, _ = x.shape
    z = jnp.dot(x, kernel.transpose(2, 0, 1, 3).reshape(c, k * k * f)).reshape(n, h, w, m, s, m, s, f)
    y = 0.0
    for a in range(m):
        for b in range(m):
            y = y + jnp.pad(z[:, :, :, a, :, b], ((0, 0), (a, m - 1 - a), (b, m - 1 - b), (0, 0), (0, 0), (0, 0)))
    return y.transpose(0, 1, 3, 2, 4, 5).reshape(n, (h + m - 1) * s, (w + m - 1) * s, f)


def same_pad_before(n: int, kernel: int, stride: int) -> int:
    """Padding `lax`'s "SAME" puts before an n-pixel input."""
    out = -(-n // stride)
    return max((out - 1) * stride + kernel - n, 0) // 2
