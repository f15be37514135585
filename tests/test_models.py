"""Keypoint networks: shapes, value ranges, cell order, sizes, configs, input checks, ONNX export."""

from __future__ import annotations

import inspect
import io
import json
import warnings

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from omegaconf import OmegaConf

from aerovis_slam.mcts import CHANNEL_ORDER, MCTS_DT_WINDOWS_MS, MCTS_NE_EVENTS_PER_PX
from aerovis_train.models import (
    CONF_DIR,
    ENCODERS,
    ExportWrapper,
    KeypointNet,
    build_model,
    count_flops,
    count_parameters,
    depth_to_space,
    encoder_defaults,
    space_to_depth,
)
from aerovis_train.models.encoders import grid_partition, grid_reverse, window_partition, window_reverse

from conftest import randomise_batchnorm


def _model_cfg(name: str):
    return OmegaConf.load(CONF_DIR / "model" / f"{name}.yaml")


def _tiny(encoder: str, in_channels: int = 8, descriptor_dim: int = 32, **encoder_conf) -> KeypointNet:
    return build_model({"name": f"tiny_{encoder}", "encoder": encoder, "encoder_conf": encoder_conf,
                        "in_channels": in_channels, "descriptor_dim": descriptor_dim, "head_width": 32})


# ---------------------------------------------------------------------------------------------
# Outputs
# ---------------------------------------------------------------------------------------------


def test_outputs_shapes_and_ranges():
    torch.manual_seed(0)
    net = build_model(_model_cfg("superlite")).eval()
    randomise_batchnorm(net)
    x = torch.rand(2, 8, 32, 48)
    with torch.no_grad():
        out = net(x)
    assert out["logits"].shape == (2, 65, 4, 6)
    assert out["scores"].shape == (2, 32, 48) and out["scores"].dtype == torch.float32
    assert out["descriptors"].shape == (2, 64, 4, 6) and out["descriptors"].dtype == torch.float32
    scores = out["scores"]
    assert float(scores.min()) >= 0.0 and float(scores.max()) <= 1.0
    # Each cell's 64 position probabilities plus its dustbin probability sum to 1.
    dustbin = out["logits"].softmax(1)[:, 64]
    cell_sums = space_to_depth(scores).sum(1) + dustbin
    torch.testing.assert_close(cell_sums, torch.ones_like(cell_sums), atol=1e-5, rtol=0)
    norms = out["descriptors"].norm(dim=1)
    torch.testing.assert_close(norms, torch.ones_like(norms), atol=1e-5, rtol=0)


def test_depth_to_space_order_matches_loop_and_pixel_shuffle():
    x = torch.randn(2, 64, 3, 5)
    expected = torch.zeros(2, 24, 40)
    for b in range(2):
        for y in range(3):
            for xx in range(5):
                for dy in range(8):
                    for dx in range(8):
                        expected[b, y * 8 + dy, xx * 8 + dx] = x[b, 8 * dy + dx, y, xx]
    out = depth_to_space(x)
    assert torch.equal(out, expected)
    # Same arrangement as pixel_shuffle, i.e. ONNX DepthToSpace in CRD mode.
    assert torch.equal(out, F.pixel_shuffle(x, 8)[:, 0])
    assert torch.equal(space_to_depth(out), x)


def test_scores_follow_the_cell_convention():
    # Force one position logit high in one cell: the score peak must land at (y*8+dy, x*8+dx).
    net = _tiny("vgg_lite").eval()
    with torch.no_grad():
        net.detector.out.weight.zero_()
        net.detector.out.bias.fill_(-20.0)
        net.detector.out.bias[8 * 3 + 5] = 20.0  # dy = 3, dx = 5 in every cell
        scores = net(torch.rand(1, 8, 16, 24))["scores"][0]
    peaks = torch.nonzero(scores > 0.5).tolist()
    assert peaks == [[y * 8 + 3, x * 8 + 5] for y in range(2) for x in range(3)]


def test_pixel_detector_branch_starts_at_zero_and_follows_the_cell_convention():
    # model.detector_pixel: full-resolution logits added to the cell head's 64 positions
    torch.manual_seed(0)
    plain = _tiny("vgg_lite").eval()
    randomise_batchnorm(plain)
    cfg = {"name": "tiny_vgg_lite", "encoder": "vgg_lite", "in_channels": 8, "descriptor_dim": 32, "head_width": 32}
    branch = build_model({**cfg, "detector_pixel": {"width": 8, "depth": 1}}).eval()
    state = plain.state_dict()
    state.update({f"detector_pixel.{k}": v for k, v in branch.detector_pixel.state_dict().items()})
    branch.load_state_dict(state)
    x = torch.rand(2, 8, 16, 24)
    with torch.no_grad():
        # its last conv starts at zero: the network is exactly the one without the branch
        a, b = plain(x), branch(x)
        assert all(torch.equal(a[k], b[k]) for k in a)
        # a logit of 40 where input channel 0 is 1 (depth 1: one 3x3 conv, centre tap), none from the
        # cell head: the score peaks at those pixels, wherever they sit in their cells
        branch.detector.out.weight.zero_()
        branch.detector.out.bias.zero_()
        branch.detector_pixel.out.weight[0, 0, 1, 1] = 40.0
        pixels = [(0, 0), (3, 13), (7, 23), (9, 2), (14, 10)]  # one per cell, at varied (dy, dx)
        x = torch.zeros(1, 8, 16, 24)
        for y, xx in pixels:
            x[0, 0, y, xx] = 1.0
        scores = branch(x)["scores"][0]
    assert sorted(map(tuple, torch.nonzero(scores > 0.99).tolist())) == sorted(pixels)
    assert branch.metadata()["detector_pixel"] == {"width": 8, "depth": 1, "within_cell": False}
    assert plain.metadata()["detector_pixel"] is None


def test_pixel_detector_within_cell_moves_keypoints_but_keeps_each_cells_mass():
    # detector_pixel.within_cell: the branch chooses the pixel, the cell head how likely the cell holds one
    torch.manual_seed(0)
    cfg = {"name": "tiny_vgg_lite", "encoder": "vgg_lite", "in_channels": 8, "descriptor_dim": 32, "head_width": 32}
    net = build_model({**cfg, "detector_pixel": {"width": 8, "depth": 1, "within_cell": True}}).eval()
    randomise_batchnorm(net)
    x = torch.rand(2, 8, 16, 24)
    with torch.no_grad():
        before = net(x)["scores"]
        net.detector_pixel.out.weight.normal_(0.0, 2.0)  # a branch that contributes everywhere
        after = net(x)["scores"]
        # each cell's keypoint probability (sum over its 64 pixels) is the cell head's, to float32
        # rounding of the log-sum-exp shift (~1e-7 relative per term); the distribution inside moves
        mass = lambda s: s.reshape(2, 2, 8, 3, 8).sum((2, 4))  # noqa: E731
        torch.testing.assert_close(mass(after), mass(before), rtol=1e-5, atol=1e-7)
        assert (after - before).abs().max() > 1e-2
        # cell head silent (all 65 logits 0: each cell 64/65 keypoint) and a logit of 40 at one pixel per
        # cell: that pixel takes the cell's whole mass 64/65, the dustbin keeps 1/65
        net.detector.out.weight.zero_()
        net.detector.out.bias.zero_()
        net.detector_pixel.out.weight.zero_()
        net.detector_pixel.out.weight[0, 0, 1, 1] = 40.0
        pixels = [(0, 0), (3, 13), (7, 23), (9, 2), (14, 10), (12, 20)]  # one per cell, at varied (dy, dx)
        x = torch.zeros(1, 8, 16, 24)
        for y, xx in pixels:
            x[0, 0, y, xx] = 1.0
        scores = net(x)["scores"][0]
    peak = scores[tuple(torch.tensor(pixels).T)]
    torch.testing.assert_close(peak, torch.full_like(peak, 64 / 65), rtol=1e-6, atol=1e-6)
    assert net.metadata()["detector_pixel"] == {"width": 8, "depth": 1, "within_cell": True}


def test_partitions_round_trip_and_grid_is_dilated():
    p, h, w = 5, 10, 15
    x = torch.arange(2 * h * w * 3, dtype=torch.float32).reshape(2, h, w, 3)
    assert torch.equal(window_reverse(window_partition(x, p), p, h, w), x)
    assert torch.equal(grid_reverse(grid_partition(x, p), p, h, w), x)
    pix = torch.stack(torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij"), -1).float()[None]  # (1, h, w, 2)
    window0 = window_partition(pix, p)[0]  # first window: a contiguous 5x5 block
    assert window0[:, 0].unique().tolist() == list(range(5)) and window0[:, 1].unique().tolist() == list(range(5))
    grid0 = grid_partition(pix, p)[0]  # first grid: pixels h/p = 2 rows and w/p = 3 columns apart
    assert grid0[:, 0].unique().tolist() == list(range(0, h, h // p))
    assert grid0[:, 1].unique().tolist() == list(range(0, w, w // p))


# ---------------------------------------------------------------------------------------------
# Sizes and costs
# ---------------------------------------------------------------------------------------------


def test_superlite_parameter_count():
    paper = build_model({**OmegaConf.to_container(_model_cfg("superlite")), "detector_pixel": None})
    conv = lambda ci, co, k: ci * co * k * k  # noqa: E731 - convs before BatchNorm have no bias
    bn = lambda c: 2 * c  # noqa: E731 - affine weight and bias
    encoder = conv(8, 64, 3) + bn(64) + conv(64, 64, 3) + bn(64) + conv(64, 128, 3) + bn(128) + conv(128, 128, 3) + bn(128)
    detector = conv(128, 256, 3) + bn(256) + 256 * 65 + 65
    descriptor = conv(128, 256, 3) + bn(256) + 256 * 64 + 64
    assert count_parameters(paper) == encoder + detector + descriptor == 887_425
    # The paper says "about 0.9 M"; our count of its layer list is 0.887 M. 2 % tolerance covers
    # bias/BatchNorm bookkeeping conventions (conv biases before BN would add 0.1 %), while a
    # wrong width or layer (e.g. one more 128x128 conv: +17 %) fails.
    assert abs(count_parameters(paper) - 0.9e6) / 0.9e6 < 0.02
    # model=superlite (the shipped network) adds the full-resolution detector branch, 16 wide, 3 deep:
    # two conv+BN layers and a biased conv to one channel
    branch = conv(8, 16, 3) + bn(16) + conv(16, 16, 3) + bn(16) + conv(16, 1, 3) + 1
    assert count_parameters(build_model(_model_cfg("superlite"))) == 887_425 + branch == 891_090


def test_superlite_flops_match_closed_form():
    h, w = 240, 320
    macs = (h * w * 8 * 64 * 9 + (h // 2) * (w // 2) * 64 * 64 * 9 + (h // 4) * (w // 4) * 64 * 128 * 9
            + (h // 8) * (w // 8) * (128 * 128 * 9 + 2 * 128 * 256 * 9 + 256 * 65 + 256 * 64))
    paper = build_model({**OmegaConf.to_container(_model_cfg("superlite")), "detector_pixel": None})
    assert count_flops(paper, (1, 8, h, w)) == 2 * macs
    branch_macs = h * w * (8 * 16 * 9 + 16 * 16 * 9 + 16 * 1 * 9)  # three 3x3 convs at full resolution
    assert count_flops(build_model(_model_cfg("superlite")), (1, 8, h, w)) == 2 * (macs + branch_macs)


def test_superevent_models_have_about_the_published_size():
    # REFERENCE: SuperEvent+ ~1.7 M parameters; the 10-channel SuperEvent differs only in the stem.
    plus = count_parameters(build_model(_model_cfg("superevent_plus")))
    dt = count_parameters(build_model(_model_cfg("superevent")))
    assert abs(plus - 1.7e6) / 1.7e6 < 0.05
    assert dt - plus == 2 * 32 * 9  # two more input channels into the 3x3 patch embedding


# ---------------------------------------------------------------------------------------------
# Configs and registry
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(ENCODERS))
def test_encoder_yaml_is_complete_and_matches_class_defaults(name):
    defaults = encoder_defaults(name)
    sig = inspect.signature(ENCODERS[name].__init__)
    options = {k: v.default for k, v in sig.parameters.items() if k not in ("self", "in_channels")}
    assert set(defaults) == set(options), f"conf/encoder/{name}.yaml keys differ from {ENCODERS[name].__name__}"
    for key, value in options.items():
        if name == "vgg" and key == "depth":
            continue  # the class's standalone default is SuperLitE's; vgg.yaml sets depth 2
        expected = list(value) if isinstance(value, tuple) else value
        assert defaults[key] == expected, f"{name}.{key}: yaml {defaults[key]!r} != class default {expected!r}"


@pytest.mark.parametrize(("name", "encoder", "channels", "dim", "kind", "params"), [
    ("superevent", "maxvit", 10, 256, "dt", list(MCTS_DT_WINDOWS_MS)),
    ("superevent_plus", "maxvit", 8, 256, "ne", list(MCTS_NE_EVENTS_PER_PX)),
    ("superlite", "vgg_lite", 8, 64, "ne", list(MCTS_NE_EVENTS_PER_PX)),
])
def test_model_configs(name, encoder, channels, dim, kind, params):
    cfg = _model_cfg(name)
    assert (cfg.name, cfg.encoder, cfg.in_channels, cfg.descriptor_dim, cfg.mcts.kind) == (name, encoder, channels, dim, kind)
    assert [float(v) for v in cfg.mcts.params] == params
    net = build_model(cfg)
    meta = net.metadata()
    assert json.loads(json.dumps(meta)) == meta
    assert meta["mcts"]["channel_order"] == CHANNEL_ORDER and meta["size_multiple"] == (40 if encoder == "maxvit" else 8)


def test_command_line_style_override_gives_a_valid_model():
    cfg = OmegaConf.merge(_model_cfg("superlite"), OmegaConf.from_dotlist(["encoder=vgg", "descriptor_dim=128"]))
    net = build_model(cfg)
    assert net.encoder.depths == [2, 2, 2, 2]
    assert net(torch.rand(1, 8, 16, 16))["descriptors"].shape == (1, 128, 2, 2)


def test_hydra_compose_with_overrides():
    hydra = pytest.importorskip("hydra", reason="hydra-core is not installed")
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = hydra.compose(overrides=["+model=superevent_plus", "model.encoder=vgg", "model.descriptor_dim=128",
                                       "+model.encoder_conf.width_mult=0.5"])
    net = build_model(cfg.model)
    assert (net.name, net.encoder_name, net.descriptor_dim, net.encoder.widths) == ("superevent_plus", "vgg", 128, [32, 32, 64, 128])
    assert net(torch.rand(1, 8, 16, 16))["descriptors"].shape == (1, 128, 2, 2)


def test_encoder_conf_overrides_width_and_depth():
    net = _tiny("maxvit", width_mult=0.5, depth=[1, 2, 1], out_channels=64)
    assert net.encoder.widths == [16, 32, 64] and net.encoder.depths == [1, 2, 1] and net.encoder.out_channels == 64
    assert net(torch.rand(1, 8, 40, 40))["logits"].shape == (1, 65, 5, 5)
    # Attention-only blocks (no MBConv) as in RVT; fewer parameters, same contract.
    plain = _tiny("maxvit", mbconv=False)
    assert count_parameters(plain) < count_parameters(_tiny("maxvit"))
    assert plain(torch.rand(1, 8, 40, 80))["scores"].shape == (1, 40, 80)


@pytest.mark.parametrize("encoder", sorted(ENCODERS))
@pytest.mark.parametrize("dim", [32, 128])
def test_every_encoder_builds_runs_and_trains(encoder, dim):
    torch.manual_seed(0)
    net = _tiny(encoder, in_channels=10 if dim == 128 else 8, descriptor_dim=dim)
    side = net.size_multiple
    x = torch.rand(2, net.in_channels, side, 2 * side)
    out = net(x)  # training mode: BatchNorm uses batch statistics
    h, w = side // 8, 2 * side // 8
    assert out["logits"].shape == (2, 65, h, w)
    assert out["scores"].shape == (2, side, 2 * side)
    assert out["descriptors"].shape == (2, dim, h, w)
    (out["logits"].square().mean() + out["descriptors"].sum()).backward()
    dead = [n for n, p in net.named_parameters() if p.grad is None]
    assert not dead, f"parameters without gradient: {dead}"


# ---------------------------------------------------------------------------------------------
# Errors
# ---------------------------------------------------------------------------------------------


def test_invalid_inputs_raise_clear_errors():
    lite = build_model(_model_cfg("superlite"))
    with pytest.raises(ValueError, match=r"expects 8 input channels, got 10"):
        lite(torch.rand(1, 10, 16, 16))
    with pytest.raises(ValueError, match=r"multiples of 8 .*got 20x16"):
        lite(torch.rand(1, 8, 20, 16))
    with pytest.raises(ValueError, match=r"expects input \(B, 8, H, W\)"):
        lite(torch.rand(8, 16, 16))
    plus = build_model(_model_cfg("superevent_plus"))
    with pytest.raises(ValueError, match=r"multiples of 40 \(8 x partition size 5\), got 240x424; crop to 240x400"):
        plus(torch.rand(1, 8, 240, 424))


def test_invalid_configs_raise_clear_errors():
    base = {"name": "x", "encoder": "vgg_lite", "in_channels": 8, "descriptor_dim": 64}
    with pytest.raises(ValueError, match=r"unknown encoder 'resnet'; known encoders: \['maxvit', 'mobilenetv3', 'vgg', 'vgg_lite'\]"):
        build_model({**base, "encoder": "resnet"})
    with pytest.raises(ValueError, match=r"encoder_conf keys \['widht_mult'\] are not options of encoder 'vgg_lite'"):
        build_model({**base, "encoder_conf": {"widht_mult": 0.5}})
    with pytest.raises(ValueError, match=r"2 x 4 = 8 channels, but in_channels is 10"):
        build_model({**base, "in_channels": 10, "mcts": {"kind": "ne", "params": [0.03, 0.1, 0.3, 1.0]}})
    with pytest.raises(ValueError, match=r"lacks \['descriptor_dim'\]"):
        build_model({k: v for k, v in base.items() if k != "descriptor_dim"})
    with pytest.raises(ValueError, match=r"partition_size and head_dim must be positive, got 0, 8"):
        build_model({**base, "encoder": "maxvit", "encoder_conf": {"partition_size": 0}})
    with pytest.raises(ValueError, match=r"depth must be >= 1 per scale, got \[1, 0, 1, 1\]"):
        build_model({**base, "encoder_conf": {"depth": [1, 0, 1, 1]}})
    with pytest.raises(ValueError, match=r"channels needs one value per stage \(3\), got 2"):
        build_model({**base, "encoder_conf": {"channels": [64, 64]}})
    with pytest.raises(ValueError, match=r"detector_pixel needs width >= 1 and depth >= 1, got width=0, depth=3"):
        build_model({**base, "detector_pixel": {"width": 0, "depth": 3}})
    with pytest.raises(ValueError, match=r"detector_pixel takes width, depth and within_cell, got \['widht'\]"):
        build_model({**base, "detector_pixel": {"widht": 16}})
    with pytest.raises(ValueError, match=r"detector_pixel.within_cell must be true or false, got 'yes'"):
        build_model({**base, "detector_pixel": {"width": 16, "within_cell": "yes"}})
    # Stage widths round to whole attention heads instead of failing.
    assert build_model({**base, "encoder": "maxvit", "encoder_conf": {"head_dim": 12}}).encoder.widths == [36, 60, 132]


# ---------------------------------------------------------------------------------------------
# ONNX export
# ---------------------------------------------------------------------------------------------


def _export_and_compare(net: KeypointNet, shape: tuple[int, int, int, int]) -> None:
    onnx = pytest.importorskip("onnx", reason="onnx is not installed (pip install onnx)")
    ort = pytest.importorskip("onnxruntime", reason="onnxruntime is not installed")
    net.eval()
    randomise_batchnorm(net)
    x = torch.rand(shape)
    net.check_input(x)
    wrapper = ExportWrapper(net)
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the legacy TorchScript exporter's deprecation notice
        torch.onnx.export(
            wrapper, (x,), buf, opset_version=18, dynamo=False,
            input_names=list(ExportWrapper.input_names), output_names=list(ExportWrapper.output_names),
            dynamic_axes={name: {0: "batch"} for name in (*ExportWrapper.input_names, *ExportWrapper.output_names)},
        )
    assert not net.training, "export must leave an eval() net in eval mode"
    model = onnx.load_from_string(buf.getvalue())
    onnx.checker.check_model(model)
    assert model.opset_import[0].version == 18
    ops = {node.op_type for node in model.graph.node}
    assert "SpaceToDepth" not in ops  # pixel_unshuffle's wrongly ordered export must not appear
    session = ort.InferenceSession(buf.getvalue(), providers=["CPUExecutionProvider"])
    # A different batch than the traced one proves the batch axis is dynamic.
    for batch in (x, torch.rand(shape[0] + 1, *shape[1:])):
        with torch.no_grad():
            ref = wrapper(batch)
        got = session.run(None, {ExportWrapper.input_names[0]: batch.numpy()})
        for name, r, g in zip(ExportWrapper.output_names, ref, got):
            assert g.shape == tuple(r.shape), name
            # float32 with different kernel summation orders: ~1e-7 observed; 1e-5 absolute on
            # probabilities and unit-norm descriptors (entries <= 1) is far below any effect.
            np.testing.assert_allclose(g, r.numpy(), atol=1e-5, rtol=0, err_msg=name)


def test_onnx_export_superlite_matches_torch():
    torch.manual_seed(1)
    _export_and_compare(build_model(_model_cfg("superlite")), (2, 8, 48, 64))


@pytest.mark.parametrize("within_cell", [False, True])
def test_onnx_export_with_pixel_detector_matches_torch(within_cell):
    torch.manual_seed(3)
    net = build_model({**OmegaConf.to_container(_model_cfg("superlite")),
                       "detector_pixel": {"width": 8, "depth": 2, "within_cell": within_cell}})
    with torch.no_grad():  # a branch that contributes (it starts at zero)
        net.detector_pixel.out.weight.normal_(0.0, 1.0)
    _export_and_compare(net, (2, 8, 48, 64))


def test_onnx_export_maxvit_matches_torch():
    torch.manual_seed(2)
    _export_and_compare(build_model(_model_cfg("superevent")), (1, 10, 40, 80))
