"""The configurable network: the default one unchanged, the preset of
configs/presets/authors_network.yaml (shapes, parameter count, initialisation, one
update), the conv1 and transposed-conv building blocks against numpy, the alignment of
the transposed depth / segmentation heads with their targets, and the config errors of
impossible conv stacks.

The default network's reference values (tests/data/default_network_tiny.json) were
written by the network code before the conv stack became configurable, for
tests/tiny.py's configuration, seed 3 and 7 actions.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from a2catvn_jax.agent import layers, networks
from a2catvn_jax.agent import update as update_lib
from a2catvn_jax.config import ConfigError, load_config
from a2catvn_jax.env import make_env
from tiny import TINY_LEARNER, TINY_SYNTHETIC

ROOT = Path(__file__).resolve().parents[1]
PRESET = ROOT / "configs" / "presets" / "authors_network.yaml"
REFERENCE = Path(__file__).resolve().parent / "data" / "default_network_tiny.json"
ACTIONS = 8


def _preset(size: int, *extra: str):
    return load_config(PRESET, [f"env.render.image_size={size}", *extra])


def _shapes(net, size: int) -> dict:
    """Shapes of every function's outputs for 2 frames (traced, not run)."""
    params = jax.eval_shape(net.init, jax.random.PRNGKey(0))
    img = jax.ShapeDtypeStruct((2, size, size, 3), jnp.uint8)
    target = jax.eval_shape(net.target_stream, params, img)
    conv4, feats = jax.eval_shape(net.encode, params, img, target)
    carry = net.initial_carry(2)
    _, core = jax.eval_shape(net.core, params, carry, feats, jax.ShapeDtypeStruct((2,), jnp.int32),
                             jax.ShapeDtypeStruct((2,), jnp.float32))
    frames = jax.ShapeDtypeStruct((2, networks.RP_FRAMES) + conv4.shape[1:], jnp.float32)
    heads = jax.eval_shape(net.vn_heads, params, conv4)
    return {"target": target.shape, "conv4": conv4.shape, "features": feats.shape, "core": core.shape,
            "pixel_control": jax.eval_shape(net.pixel_control, params, core).shape,
            "reward_prediction": jax.eval_shape(net.reward_prediction, params, frames).shape,
            **{h: v.shape for h, v in heads.items()}}


# -- the default network ----------------------------------------------------------------------


def test_default_network_is_unchanged():
    """Parameter names, shapes and initial values, and the outputs for fixed inputs, of
    tests/tiny.py's network are those the network had before its conv stack became configurable."""
    want = json.loads(REFERENCE.read_text())
    cfg = load_config(None, TINY_LEARNER)
    net = networks.make_networks(cfg, 7)
    params = net.init(jax.random.PRNGKey(3))
    leaves = {jax.tree_util.keystr(p): np.asarray(x, np.float64)
              for p, x in jax.tree_util.tree_flatten_with_path(params)[0]}
    assert list(leaves) == list(want["params"])
    size = cfg.env.render.image_size
    rng = np.random.default_rng(0)
    img = jnp.asarray(rng.integers(0, 256, (2, size, size, 3), dtype=np.uint8))
    target = jnp.asarray(rng.integers(0, 256, (2, size, size, 3), dtype=np.uint8))
    outputs = net.module.apply(params, img, target, jnp.array([1, 2]), jnp.array([0.5, -2.0]))
    assert set(outputs) == set(want["outputs"])
    got = {**{("params", k): v for k, v in leaves.items()},
           **{("outputs", k): np.asarray(v, np.float64) for k, v in outputs.items()}}
    for (section, name), x in got.items():
        ref = want[section][name]
        assert list(x.shape) == ref["shape"], name
        np.testing.assert_allclose([x.sum(), np.abs(x).sum()], [ref["sum"], ref["abs_sum"]], rtol=1e-5, atol=1e-6,
                                   err_msg=name)
        np.testing.assert_allclose(x.ravel()[:3], ref["first"], rtol=1e-5, atol=1e-7, err_msg=name)


def test_default_config_is_the_previous_network():
    agent = load_config(None).agent
    assert (agent.conv_kernels, agent.conv_strides, agent.conv_padding) == ((8, 4, 3, 3), (4, 2, 1, 1), "same")
    assert (agent.vision_heads, agent.init) == ("upsample", "lecun")


# -- the authors' network: shapes and size ------------------------------------------------------


# image size -> (conv1, conv2, conv3 = conv4 sides), worked out from the kernels and strides
# (7/4, 4/2, 4/2, 1/1): valid n -> (n - k) // s + 1; same (32 px) n -> ceil(n / s). The
# target stream gives what targets add to conv3 (64 channels).
CONV_SIDES = {172: (42, 20, 9), 84: (20, 9, 3), 48: (11, 4, 1), 32: (8, 4, 2)}


@pytest.mark.parametrize("size", [32, 48, 84, 172])
def test_authors_preset_shapes(size):
    extra = ["agent.conv_padding=same"] if size == 32 else []  # 32 px is below valid padding's minimum of 43
    cfg = _preset(size, *extra)
    s1, s2, s4 = CONV_SIDES[size]
    assert cfg.agent.conv_sizes(size) == [size, s1, s2, s4, s4]
    shapes = _shapes(networks.make_networks(cfg, ACTIONS), size)
    aux, grid = size // cfg.train.aux_downsize, size // cfg.train.pixel_control_cell
    assert shapes == {
        "target": (2, s4, s4, 64), "conv4": (2, s4, s4, 32), "features": (2, 512), "core": (2, 512),
        "pixel_control": (2, grid, grid, ACTIONS), "reward_prediction": (2, 3),
        "depth": (2, aux, aux), "segmentation": (2, aux, aux, 3), "target_segmentation": (2, aux, aux, 3)}


def test_authors_preset_needs_43_pixels_with_valid_padding():
    with pytest.raises(ConfigError) as ei:
        _preset(32)
    msg = str(ei.value)
    assert msg.startswith("env.render.image_size: 32 is too small")
    assert "conv3 (4x4/2) gets 2x2" in msg and "32 -> 7 -> 2" in msg and "at least 43" in msg
    assert "agent.conv_padding=same" in msg
    _preset(43)


def test_authors_network_parameter_count_at_84():
    """Counted by hand: kernels + biases of every layer, 8 actions, the heads of this package."""
    conv1 = 7 * 7 * 3 * 32 + 32  # shared by observation and target
    conv2 = 4 * 4 * 32 * 32 + 32  # shared
    conv3 = 4 * 4 * 64 * 64 + 64  # on the 64 concatenated channels
    conv4 = 1 * 1 * 64 * 32 + 32
    dense = 3 * 3 * 32 * 512 + 512  # conv4 is 3x3 at 84 px
    lstm = 4 * ((512 + ACTIONS + 1) * 512 + 512 * 512 + 512)  # inputs: features, one-hot action, reward
    policy, value = 512 * ACTIONS + ACTIONS, 512 + 1
    half = math.ceil(84 // 4 / 2)  # pixel control: dense to a half-resolution grid, then x2 upsampling
    pixel_control = (512 * half * half * 32 + half * half * 32) + (2 * 2 * 32 * 4 + 4) + (2 * 2 * 32 * 4 * ACTIONS + 4 * ACTIONS)
    reward_prediction = 3 * 3 * 3 * 32 * 3 + 3  # conv4 of 3 frames -> 3 classes
    vision = 3 * (4 * 4 * 32 * 16 + 16) + (4 * 4 * 16 * 1 + 1) + 2 * (4 * 4 * 16 * 3 + 3)  # transposed convs
    want = conv1 + conv2 + conv3 + conv4 + dense + lstm + policy + value + pixel_control + reward_prediction + vision
    params = jax.eval_shape(networks.make_networks(_preset(84), ACTIONS).init, jax.random.PRNGKey(0))
    assert networks.num_params(params) == want == 4_379_047


# -- the authors' network: initialisation --------------------------------------------------------


def _bound(path: str, kernel: np.ndarray) -> float:
    if "deconv" in path:  # transposed conv [k, k, in, out]: fan_in = k * k * out
        return 1 / math.sqrt(kernel.shape[0] * kernel.shape[1] * kernel.shape[-1])
    return 1 / math.sqrt(math.prod(kernel.shape[:-1]))


def test_uniform_fan_in_initialisation():
    cfg = _preset(48, "agent.dense_size=128", "agent.core_size=128")  # smaller LSTM, same scheme
    params = jax.jit(networks.make_networks(cfg, ACTIONS).init)(jax.random.PRNGKey(1))["params"]
    flat = {jax.tree_util.keystr(p): np.asarray(x, np.float64) for p, x in jax.tree_util.tree_flatten_with_path(params)[0]}
    lstm = {k: v for k, v in flat.items() if "'lstm'" in k}
    checked = 0
    for path, w in flat.items():
        if path.endswith("bias']"):
            assert np.all(w == 0), path
            continue
        if path in lstm:
            continue
        bound = _bound(path, w)
        assert np.max(np.abs(w)) <= bound, path
        if w.size >= 2000:  # uniform in [-bound, bound]: mean 0, std bound / sqrt(3), |w| < bound / 2 half the time
            assert abs(w.mean()) < 0.1 * bound, path
            assert abs(w.std() / (bound / math.sqrt(3)) - 1) < 0.05, path
            assert abs(np.mean(np.abs(w) < bound / 2) - 0.5) < 0.05, path
            assert np.max(np.abs(w)) > 0.95 * bound, path
        checked += 1
    # conv1-4, dense, policy, value, pixel control (dense, 2 upsamplings), reward prediction, 3 heads x 2
    assert checked == 4 + 1 + 1 + 1 + 3 + 1 + 6
    # LSTM: input kernels Glorot-uniform over the four gates ([in, 4 * 128]); the recurrent
    # kernels of the four gates side by side [128, 4 * 128] have orthonormal rows.
    inputs = np.concatenate([lstm[f"['lstm']['i{g}']['kernel']"] for g in "ifgo"], axis=1)
    glorot = math.sqrt(6 / (inputs.shape[0] + inputs.shape[1]))
    assert np.max(np.abs(inputs)) <= glorot and np.max(np.abs(inputs)) > 0.95 * glorot
    recurrent = np.concatenate([lstm[f"['lstm']['h{g}']['kernel']"] for g in "ifgo"], axis=1)
    np.testing.assert_allclose(recurrent @ recurrent.T, np.eye(128), atol=1e-5)


# -- one update --------------------------------------------------------------------------------


def test_one_update_with_the_preset():
    """The tiny learner (small channels) with the preset's kernels, strides, padding, heads
    and initialisation, at 48 px."""
    cfg = load_config(PRESET, TINY_SYNTHETIC + ["env.render.image_size=48"])
    assert cfg.agent.vision_heads == "transposed" and cfg.agent.conv_padding == "valid"
    env = make_env(cfg.env)
    fns = update_lib.make_update(env, networks.make_networks(cfg, env.num_actions), cfg)
    ts = fns.init(jax.random.PRNGKey(0))
    before = jax.tree_util.tree_map(np.asarray, ts.params)
    ts, metrics = fns.update(ts)
    metrics = jax.device_get(metrics)
    assert {"loss/depth", "loss/segmentation", "loss/target_segmentation", "loss/pixel_control",
            "loss/reward_prediction", "loss/total"} <= set(metrics)
    assert all(np.all(np.isfinite(v)) for v in metrics.values())
    moved = jax.tree_util.tree_map(lambda a, b: bool(np.any(a != np.asarray(b))), before, ts.params)
    assert all(moved["params"][k] for k in ("conv1", "conv4", "vn"))


# -- building blocks ---------------------------------------------------------------------------


def _conv1_numpy(image, kernel, bias, k, s, padding):
    """conv1's definition: pad k - s at the top/left and up to a multiple of s at the
    bottom/right ("same"), or nothing ("valid"); windows every s pixels."""
    x = np.asarray(image, np.float64) / 255.0
    n = x.shape[1]
    if padding == "same":
        out = -(-n // s)
        x = np.pad(x, ((0, 0), (k - s, out * s - n), (k - s, out * s - n), (0, 0)))
    else:
        out = (n - k) // s + 1
    y = np.zeros((x.shape[0], out, out, kernel.shape[-1]))
    for i in range(out):
        for j in range(out):
            y[:, i, j] = np.einsum("nuvc,uvcf->nf", x[:, s * i : s * i + k, s * j : s * j + k], kernel)
    return y + bias


@pytest.mark.parametrize("k,s,padding,size", [(8, 4, "valid", 30), (8, 4, "valid", 32), (4, 2, "same", 17),
                                              (6, 2, "valid", 19), (7, 4, "same", 21), (7, 4, "valid", 43)])
def test_conv1_kernels_strides_and_padding(k, s, padding, size):
    rng = np.random.default_rng(k * 100 + size)
    image = jnp.asarray(rng.integers(0, 256, size=(2, size, size, 3), dtype=np.uint8))
    module = networks.Conv1(5, False, k, s, padding)
    params = module.init(jax.random.PRNGKey(0), image)
    params = {"params": dict(params["params"], bias=jnp.asarray(rng.normal(size=5).astype(np.float32)))}
    p = params["params"]
    ref = _conv1_numpy(image, np.asarray(p["kernel"], np.float64), np.asarray(p["bias"]), k, s, padding)
    for impl in ("xla", "matmul"):
        got = np.asarray(networks.Conv1(5, False, k, s, padding, impl=impl).apply(params, image))
        assert got.shape == ref.shape
        assert np.max(np.abs(got - ref)) < 1e-4, impl
    plain = np.asarray(module.apply(params, image))
    if k % s == 0:
        fast = np.asarray(networks.Conv1(5, True, k, s, padding).apply(params, image))
        assert np.max(np.abs(fast - plain)) < 1e-4


# (kernel, stride, padding, input side, input channels, output channels, form): strided
# layers with kernels that are and are not multiples of the stride, both matrix-product
# forms, the padding of each of the network's layers.
CONV_CASES = [
    (8, 4, "VALID", 24, 3, 16, None), (7, 4, "VALID", 23, 3, 8, None), (4, 2, "SAME", 11, 16, 32, None),
    (3, 2, "SAME", 9, 8, 6, None), (3, 1, "SAME", 7, 64, 32, None), (3, 1, "SAME", 10, 32, 1, None),
    (3, 1, "SAME", 10, 16, 5, "patches"), (3, 1, "SAME", 10, 8, 24, "shift"), (2, 1, ((0, 1), (0, 1)), 6, 32, 40, None),
    (1, 1, "VALID", 5, 12, 7, None), (4, 2, "VALID", 9, 4, 4, "shift"),
]


@pytest.mark.parametrize("k,s,padding,impl", [(3, 1, "SAME", "xla"), (3, 1, "SAME", "matmul"), (4, 2, "VALID", "auto")])
def test_split_conv_is_the_conv_of_the_concatenation(k, s, padding, impl):
    """conv3 (`SplitConv`): the observation part plus the target part, computed once per
    distinct target and gathered, is XLA's convolution of the two maps side by side,
    with the same parameters; so are its gradients."""
    a = jax.random.normal(jax.random.PRNGKey(0), (6, 9, 9, 5))
    b = jax.random.normal(jax.random.PRNGKey(1), (3, 9, 9, 7))
    index = jnp.array([2, 0, 1, 1, 0, 2])
    split = networks.SplitConv(4, k, s, padding, 5, 7, impl=impl)
    params = split.init(jax.random.PRNGKey(2), a, method=lambda m, x: m.observation(x))
    params = jax.tree_util.tree_map(lambda p: p + 0.1, params)  # a bias that is not zero
    kernel, bias = params["params"]["kernel"], params["params"]["bias"]
    assert kernel.shape == (k, k, 12, 4) and bias.shape == (4,)

    def by_parts(p, a, b):
        return split.apply(p, a, method=split.observation) + split.apply(p, b, method=split.target)[index]

    def concatenated(p, a, b):
        x = jnp.concatenate([a, b[index]], -1)
        pads = layers.conv_padding(x.shape[1:3], k, s, padding)
        y = jax.lax.conv_general_dilated(x, p["params"]["kernel"], (s, s), pads, dimension_numbers=("NHWC", "HWIO", "NHWC"))
        return y + p["params"]["bias"]

    np.testing.assert_allclose(by_parts(params, a, b), concatenated(params, a, b), rtol=1e-5, atol=1e-5)
    loss = lambda f: lambda p, a, b: jnp.sum(jnp.sin(f(p, a, b)))  # noqa: E731
    for g1, g2 in zip(jax.tree_util.tree_leaves(jax.grad(loss(by_parts), argnums=(0, 1, 2))(params, a, b)),
                      jax.tree_util.tree_leaves(jax.grad(loss(concatenated), argnums=(0, 1, 2))(params, a, b))):
        np.testing.assert_allclose(g1, g2, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("k,s,padding,size,cin,cout,form", CONV_CASES)
def test_conv2d_by_matrix_products_is_xla_convolution(k, s, padding, size, cin, cout, form):
    """`conv2d`'s matrix products give `lax.conv_general_dilated`'s outputs and gradients."""
    rng = np.random.default_rng(k * 1000 + size * 10 + cout)
    x = jnp.asarray(rng.normal(size=(3, size, size, cin)).astype(np.float32))
    kernel = jnp.asarray(rng.normal(size=(k, k, cin, cout)).astype(np.float32))
    pads = layers.conv_padding((size, size), k, s, padding)
    lax_pads = padding if isinstance(padding, str) else pads

    def ref(x, kernel):
        return jax.lax.conv_general_dilated(x, kernel, (s, s), lax_pads, dimension_numbers=("NHWC", "HWIO", "NHWC"))

    def mine(x, kernel):
        return layers.conv2d(x, kernel, s, padding, "matmul", form)

    want, got = ref(x, kernel), mine(x, kernel)
    assert got.shape == want.shape
    scale = float(jnp.max(jnp.abs(want)))
    assert float(jnp.max(jnp.abs(got - want))) < 1e-5 * scale
    probe = jnp.asarray(rng.normal(size=want.shape).astype(np.float32))
    g_want = jax.grad(lambda x, w: jnp.sum(ref(x, w) * probe), (0, 1))(x, kernel)
    g_got = jax.grad(lambda x, w: jnp.sum(mine(x, w) * probe), (0, 1))(x, kernel)
    for a, b in zip(g_got, g_want):
        assert float(jnp.max(jnp.abs(a - b))) < 1e-5 * float(jnp.max(jnp.abs(b)))
    auto = layers.conv2d(x, kernel, s, padding, "auto")
    assert float(jnp.max(jnp.abs(auto - want))) < 1e-5 * scale
    with pytest.raises(ValueError, match="conv impl"):
        layers.conv2d(x, kernel, s, padding, "fast")
    with pytest.raises(ValueError, match="conv form"):
        layers.conv2d(x, kernel, s, padding, "matmul", "im2col")


@pytest.mark.parametrize("impl,form", [("xla", None), ("matmul", "patches"), ("matmul", "shift")])
@pytest.mark.parametrize("k,s,padding,size", [(8, 4, "SAME", 21), (7, 4, "VALID", 23), (3, 1, "SAME", 7)])
def test_conv2d_of_uint8_images_is_that_of_the_same_values_as_floats(k, s, padding, size, impl, form):
    """`conv2d` on uint8 input (conv1 keeps images uint8 up to the product) gives the
    outputs and kernel gradient of the same values as float32, each way it computes."""
    rng = np.random.default_rng(k * 100 + size)
    image = jnp.asarray(rng.integers(0, 256, (2, size, size, 3), dtype=np.uint8))
    kernel = jnp.asarray(rng.normal(size=(k, k, 3, 6)).astype(np.float32)) / 255.0

    def out(kernel, x):
        return layers.conv2d(x, kernel, s, padding, impl, form)

    want, got = out(kernel, image.astype(jnp.float32)), out(kernel, image)
    assert got.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-5, atol=1e-5)
    probe = jnp.asarray(rng.normal(size=want.shape).astype(np.float32))
    grad = lambda x: jax.grad(lambda w: jnp.sum(out(w, x) * probe))(kernel)  # noqa: E731
    np.testing.assert_allclose(np.asarray(grad(image)), np.asarray(grad(image.astype(jnp.float32))), rtol=1e-5,
                               atol=1e-3)


@pytest.mark.parametrize("impl,s2d", [("xla", False), ("matmul", False), ("matmul", True)])
def test_conv1_keeps_the_image_uint8_up_to_the_product(impl, s2d):
    """`Conv1` pads and rearranges the uint8 image as uint8 (a quarter of float32's
    bytes), and its outputs and kernel gradient are those of the image scaled to [0, 1]
    first and convolved by XLA (how conv1 was computed before)."""
    rng = np.random.default_rng(5)
    image = jnp.asarray(rng.integers(0, 256, (2, 32, 32, 3), dtype=np.uint8))
    layer = networks.Conv1(6, s2d, 8, 4, "same", impl=impl)
    params = layer.init(jax.random.PRNGKey(0), image)

    def eqns(jaxpr):  # every equation, those of nested programs (jit, custom rules) included
        for e in jaxpr.eqns:
            yield e
            for v in e.params.values():
                for sub in v if isinstance(v, (tuple, list)) else (v,):
                    if hasattr(sub, "eqns") or hasattr(sub, "jaxpr"):
                        yield from eqns(getattr(sub, "jaxpr", sub))

    # the image-sized rearrangements (the kernel's are smaller)
    moved = [e for e in eqns(jax.make_jaxpr(layer.apply)(params, image).jaxpr)
             if e.primitive.name in ("pad", "transpose", "concatenate") and e.outvars[0].aval.size >= image.size]
    assert moved and all(e.outvars[0].aval.dtype == jnp.uint8 for e in moved), [
        (e.primitive.name, e.outvars[0].aval.dtype) for e in moved]

    def before(p):
        x = jnp.pad(image.astype(jnp.float32) / 255.0, ((0, 0), (4, 0), (4, 0), (0, 0)))
        y = jax.lax.conv_general_dilated(x, p["params"]["kernel"], (4, 4), "VALID",
                                         dimension_numbers=("NHWC", "HWIO", "NHWC"))
        return y + p["params"]["bias"]

    probe = jnp.asarray(rng.normal(size=(2, 8, 8, 6)).astype(np.float32))
    np.testing.assert_allclose(np.asarray(layer.apply(params, image)), np.asarray(before(params)), rtol=1e-5, atol=1e-6)
    g_now = jax.grad(lambda p: jnp.sum(layer.apply(p, image) * probe))(params)["params"]["kernel"]
    g_before = jax.grad(lambda p: jnp.sum(before(p) * probe))(params)["params"]["kernel"]
    np.testing.assert_allclose(np.asarray(g_now), np.asarray(g_before), rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("preset", [False, True])
def test_conv_impls_are_the_same_network(preset):
    """agent.conv_impl changes how the convolutions are computed, not the network: the
    same parameters, and the same outputs and gradients up to float rounding."""
    def config(impl):
        return _preset(48, f"agent.conv_impl={impl}") if preset else load_config(None, [*TINY_LEARNER, f"agent.conv_impl={impl}"])

    size = config("xla").env.render.image_size
    rng = np.random.default_rng(1)
    img = jnp.asarray(rng.integers(0, 256, (2, size, size, 3), dtype=np.uint8))
    target = jnp.asarray(rng.integers(0, 256, (2, size, size, 3), dtype=np.uint8))
    results = {}
    for impl in ("xla", "matmul", "auto"):
        net = networks.make_networks(config(impl), ACTIONS)
        params = net.init(jax.random.PRNGKey(2))

        def total(params, net=net):
            out = net.module.apply(params, img, target, jnp.array([1, 2]), jnp.array([0.5, -2.0]))
            return sum(jnp.sum(jnp.sin(v)) for v in jax.tree_util.tree_leaves(out)), out

        (_, out), grads = jax.jit(jax.value_and_grad(total, has_aux=True))(params)
        results[impl] = (params, out, grads)
    params, out, grads = results["xla"]

    def close(a, b, rtol):
        return float(jnp.max(jnp.abs(a - b))) <= rtol * max(float(jnp.max(jnp.abs(b))), 1e-3)

    for impl in ("matmul", "auto"):
        p, o, g = results[impl]
        assert jax.tree_util.tree_all(jax.tree_util.tree_map(np.array_equal, p, params))
        assert all(close(a, b, 1e-4) for a, b in zip(jax.tree_util.tree_leaves(o), jax.tree_util.tree_leaves(out))), impl
        # Gradients of the first layers sum over every pixel of every later layer, where a
        # rounding difference can move a ReLU input across 0: looser, but far below the
        # error of a wrong tap or a transposed kernel (the layer tests above are exact to 1e-5).
        assert all(close(a, b, 2e-2) for a, b in zip(jax.tree_util.tree_leaves(g), jax.tree_util.tree_leaves(grads))), impl
    with pytest.raises(ConfigError, match="agent.conv_impl"):
        load_config(None, ["agent.conv_impl=fast"])


@pytest.mark.parametrize("k,s", [(4, 2), (6, 2), (8, 4), (3, 1)])
def test_conv_transpose_against_numpy(k, s):
    rng = np.random.default_rng(k)
    x = rng.normal(size=(2, 3, 4, 5)).astype(np.float32)
    kernel = rng.normal(size=(k, k, 5, 6)).astype(np.float32)
    y = np.asarray(layers.conv_transpose(jnp.asarray(x), jnp.asarray(kernel), s))
    ref = np.zeros((2, 2 * s + k, 3 * s + k, 6))
    for i in range(3):
        for j in range(4):
            ref[:, s * i : s * i + k, s * j : s * j + k] += np.einsum("nc,uvcf->nuvf", x[:, i, j], kernel)
    assert y.shape == ref.shape
    np.testing.assert_allclose(y, ref, atol=1e-4)


@pytest.mark.parametrize("offset,size", [(0, 21), (3, 8), (-2, 14), (2, 6)])
def test_transposed_heads_window(offset, size):
    """The window of the 4n + 6 map: cropped where it fits, the nearest edge pixel repeated where it does not."""
    heads = networks.TransposedVNHeads({"depth": 1, "segmentation": 3, "target_segmentation": 3}, size, offset)
    x = jnp.asarray(np.random.default_rng(1).normal(size=(2, 3, 3, 8)).astype(np.float32))
    params = heads.init(jax.random.PRNGKey(0), x, ("depth",))
    out = np.asarray(heads.apply(params, x, ("depth", "segmentation"))["segmentation"])
    p = params["params"]
    hidden = jax.nn.relu(layers.conv_transpose(x, p["segmentation_deconv1_kernel"], 2) + p["segmentation_deconv1_bias"])
    full = np.asarray(layers.conv_transpose(hidden, p["segmentation_deconv2_kernel"], 2) + p["segmentation_deconv2_bias"])
    assert full.shape[1] == 18
    rows = np.clip(np.arange(offset, offset + size), 0, 17)
    np.testing.assert_allclose(out, full[:, rows][:, :, rows], atol=1e-6)


def _geometric_params(params):
    """Parameters of the shapes `params` gives: every conv kernel an average over its window
    and input channels, every transposed conv kernel the bilinear x2 interpolation kernel
    (1/4, 3/4, 3/4, 1/4 along each axis), biases 0: each layer then passes on where in the
    image its input pixels lie."""
    bilinear = np.array([0.25, 0.75, 0.75, 0.25])

    def one(path, x):  # x: a parameter's shape and dtype
        if len(x.shape) == 1:
            return jnp.zeros(x.shape, x.dtype)
        if "deconv" in jax.tree_util.keystr(path):
            kernel = np.outer(bilinear, bilinear)[:, :, None, None] / x.shape[2]
            return jnp.asarray(np.broadcast_to(kernel, x.shape), x.dtype)
        return jnp.full(x.shape, 1 / math.prod(x.shape[:-1]), x.dtype)

    return jax.tree_util.tree_map_with_path(one, params)


@pytest.mark.parametrize("size,padding", [(84, "valid"), (172, "valid"), (84, "same"), (172, "same")])
def test_transposed_heads_are_aligned_with_their_targets(size, padding):
    """With averaging conv kernels and bilinear transposed-conv kernels, the gradient of a
    depth cell with respect to the observation is centred where the cell's output pixel
    lies in the image; for cells away from the maps' borders (no padding or missing
    input in their receptive field) that centre must be within half a cell of the target
    cell's centre."""
    cfg = _preset(size, f"agent.conv_padding={padding}", "agent.conv_channels=[4,4,4,4]", "agent.dense_size=8",
                  "agent.core_size=8")
    net = networks.make_networks(cfg, ACTIONS)
    params = _geometric_params(jax.eval_shape(net.init, jax.random.PRNGKey(0)))
    f, cells = cfg.train.aux_downsize, size // cfg.train.aux_downsize
    target = net.target_stream(params, jnp.ones((1, size, size, 3), jnp.uint8))

    @jax.jit
    def grad(t):
        def cell(image):
            conv4, _ = net.encode(params, image, target)
            return net.vn_heads(params, conv4, ("depth",))["depth"][0, t, t]

        return jax.grad(cell)(jnp.ones((1, size, size, 3)))

    for t in (cells // 2 - 2, cells // 2, cells // 2 + 2):
        g = np.asarray(grad(t))[0].sum(axis=(1, 2))
        centroid = (g * (np.arange(size) + 0.5)).sum() / g.sum()
        assert abs(centroid - (t * f + f / 2)) <= f / 2, (t, centroid)


def test_transposed_heads_offsets():
    """Worked out by hand from the layers' padding (docs: `transposed_heads_offset`).

    valid, any size: conv1 pixel i is centred on image position 4i + 3.5, conv2 on 8i + 9.5,
    conv3 and conv4 on 16i + 21.5; the transposed convs' output pixel q on 4q + 3.5: cell t
    (centre 4t + 2) takes q = t. same at 32 px: conv1 (3 pixels of padding before) 4i + 0.5,
    conv2 (1 before) 8i + 2.5, conv3 (1 before) 16i + 6.5, output 4q - 11.5: cell t takes q = t + 3."""
    for size in (43, 84, 172):
        assert networks.transposed_heads_offset(_preset(size).agent, size, 4) == 0
    assert networks.transposed_heads_offset(_preset(32, "agent.conv_padding=same").agent, 32, 4) == 3


# -- configuration errors -----------------------------------------------------------------------


@pytest.mark.parametrize("overrides,fragment", [
    (["agent.conv_kernels=[3,4,3,3]"], "agent.conv_kernels: conv1's kernel 3 is smaller than its stride 4"),
    (["agent.conv_strides=[4,2,4,1]"], "agent.conv_kernels: conv3's kernel 3 is smaller than its stride 4"),
    (["agent.space_to_depth=true", "agent.conv_kernels=[7,4,3,3]"],
     "agent.space_to_depth: needs conv1's kernel to be a multiple of its stride, got kernel 7"),
    (["agent.conv_padding=valid", "env.render.image_size=40"],
     "env.render.image_size: 40 is too small for the conv stack with agent.conv_padding=valid: conv4 (3x3/1) gets 1x1"),
    (["agent.vision_heads=transposed"], "agent.vision_heads: 'transposed' (two stride-2 transposed convs) brings "
                                        "conv4's maps from stride 8"),
    (["agent.conv_kernels=[0,4,3,3]"], "agent.conv_kernels[0]: must be >= 1"),
    (["agent.conv_padding=full"], "agent.conv_padding: invalid value 'full'"),
    (["agent.init=xavier"], "agent.init: invalid value 'xavier'"),
])
def test_bad_conv_stacks_are_config_errors(overrides, fragment):
    with pytest.raises(ConfigError) as ei:
        load_config(None, overrides)
    assert str(ei.value).startswith(fragment), str(ei.value)
    assert "\n" not in str(ei.value)


def test_transposed_heads_need_matching_aux_downsize():
    with pytest.raises(ConfigError, match=r"to stride 4, which must equal train.aux_downsize \(2\)"):
        _preset(84, "train.aux_downsize=2")
    load_config(None, ["agent.vision_heads=transposed", "agent.conv_strides=[4,2,2,1]", "agent.conv_kernels=[8,4,3,3]"])


@pytest.mark.parametrize("preset", [False, True], ids=["default", "authors"])
def test_the_pytorch_reference_has_the_networks_layers(preset):
    """`benchmark network`'s PyTorch model of a configuration (`bench.torch_reference`)
    has the JAX network's conv base, dense layer and vision heads: as many parameters,
    but for the default heads' upsampling biases (one per channel in PyTorch's
    transposed convolution, one per channel and sub-pixel in the sub-pixel convolution),
    and outputs of the same shapes (also with class-id segmentation)."""
    torch_reference = pytest.importorskip("a2catvn_jax.bench.torch_reference", reason="PyTorch: the bench extra")
    import torch

    for extra in ([], ["agent.segmentation_loss=cross_entropy"]):
        cfg = _preset(84, *extra) if preset else load_config(None, ["env.render.image_size=84", *extra])
        model = torch_reference.TorchNetwork(cfg)
        net = networks.make_networks(cfg, ACTIONS)
        params = jax.eval_shape(net.init, jax.random.PRNGKey(0))
        names = ("conv1", "conv2", "conv3", "conv4", "dense", "vn")
        bias_difference = 0 if preset else 3 * sum(networks.VNHeads.HIDDEN.values())
        assert sum(p.numel() for p in model.parameters()) + bias_difference == sum(
            networks.num_params(params["params"][k]) for k in names)
        feats, heads = model(*(torch.zeros((2, 3, 84, 84), dtype=torch.uint8),) * 2)
        want = _shapes(net, 84)
        assert tuple(feats.shape) == want["features"]
        for name, out in heads.items():  # NCHW against NHWC (depth without a channel axis)
            n, ch, h, w = out.shape
            assert (n, h, w) + ((ch,) if name != "depth" else ()) == want[name], name


def test_blind_controls_zero_what_they_name():
    """`agent.blind`: "both" sees observation and target images as zeros, "target" only the
    targets, "observation" only the observations; "none" sees both; true is "both"."""
    rng = np.random.default_rng(0)
    images = jnp.asarray(rng.integers(0, 256, (2, 16, 16, 3)), jnp.uint8)
    zeros = jnp.zeros_like(images)
    assert load_config(None, ["agent.blind=true"]).agent.blind == "both"
    for mode, target_zeroed, observation_zeroed in (("none", False, False), ("both", True, True),
                                                    ("target", True, False), ("observation", False, True)):
        cfg = load_config(None, TINY_LEARNER + [f"agent.blind={mode}"])
        net = networks.make_networks(cfg, 8)
        params = net.init(jax.random.PRNGKey(0))
        feats = net.target_stream(params, images)
        same_target = bool(jnp.allclose(feats, net.target_stream(params, zeros)))
        assert same_target == target_zeroed, mode
        conv4, _ = net.encode(params, images, feats)
        conv4_zero, _ = net.encode(params, zeros, feats)
        assert bool(jnp.allclose(conv4, conv4_zero)) == observation_zeroed, mode
