"""UniqueSplat: zero-init equivalence with a loaded primary network, per-target
specialisation, gradients through every part, the cached W, rendering per target, the
parameter count of the paper configuration, and input errors."""

import dataclasses
import logging
import math

import pytest
import torch

from tests.model.conftest import two_view_cameras
from usplat_dr.data.types import SceneInputs
from usplat_dr.geometry.cameras import Cameras
from usplat_dr.model import CheckpointMismatchError, PrimaryNetwork, UniqueSplat
from usplat_dr.model.hypernet.hypernetwork import LayerDelta
from usplat_dr.model.hypernet.resnet import ResNet18
from usplat_dr.model.uniquesplat import PAPER_PARAMETERS, StudyHooks, UniqueSplatCfg
from usplat_dr.render import RasterSettings, rasterize
from usplat_dr.render.prune import PruneSettings


@pytest.fixture(autouse=True)
def _quiet_resnet(caplog):
    caplog.set_level(logging.ERROR, logger="usplat_dr.model.hypernet.resnet")


def scene(size: int = 64, n: int = 3, seed: int = 0, b: int = 1):
    """Two context cameras 0.1 apart along x; targets between and beyond them."""
    g = torch.Generator().manual_seed(seed)
    e, k = two_view_cameras(b, 2)
    te = torch.eye(4).repeat(b, n, 1, 1)
    te[:, :, 0, 3] = torch.linspace(-0.05, 0.15, n)
    te[:, :, 1, 3] = 0.02 * torch.arange(n)
    tk = k[:, :1].expand(b, n, 3, 3).clone()
    images = torch.rand(b, 2, 3, size, size, generator=g)
    return SceneInputs.of(images=images, extrinsics=e, intrinsics=k, near=torch.ones(b, 2),
                       far=100 * torch.ones(b, 2), target_extrinsics=te, target_intrinsics=tk,
                       target_near=torch.ones(b, n), target_far=100 * torch.ones(b, n))


def context(args: SceneInputs) -> dict:
    """The context views' half of ``args``, by name: ``encode``'s arguments."""
    return dict(images=args.images, extrinsics=args.extrinsics, intrinsics=args.intrinsics,
                near=args.near, far=args.far)


FIELDS = ("means", "covariances", "harmonics", "opacities")


def test_zero_init_equals_the_loaded_primary_network(net, weights):
    # The deterministic MVSplat weights (tests/fixtures) loaded into every variant: at
    # initialisation W is the checkpoint's head and Delta W = 0, so (b) and (c) give the
    # Gaussians of (a), and (a) gives the primary network's.
    args = scene()
    ckpt = {"state_dict": {"encoder." + k: v for k, v in weights.items()}}  # Lightning-style
    with torch.no_grad():
        ref = net(**context(args))
        outs = {}
        for variant in ("baseline", "agnostic", "full"):
            model = UniqueSplat.from_preset("paper", variant=variant).load_mvsplat(ckpt).eval()
            outs[variant] = model(*args, render=False)
    n = 3
    for name in FIELDS:
        a = getattr(outs["baseline"].gaussians, name)
        r = getattr(ref, name)
        # (a) runs the primary network's own operations in the same order: bit-identical.
        assert torch.equal(a, r.repeat_interleave(n, 0)), name
        for variant in ("agnostic", "full"):
            x = getattr(outs[variant].gaussians, name)
            # (b) convolves with the same weights, reshaped through H_a's bias; (c) adds the
            # rank-r channels to the last convolution and U z = 0. Bit-identical here (oneDNN
            # computes the first output channels the same way); another convolution backend
            # may block differently: float32 rounding ~1e-7 of the raw outputs, scaled by
            # depths up to 100 for the means, hence an absolute 1e-4 and relative 1e-5.
            tol = dict(rtol=1e-5, atol=1e-4 if name == "means" else 1e-5)
            assert torch.allclose(x, a, **tol), (variant, name, (x - a).abs().max())
    assert not outs["baseline"].per_target and outs["full"].per_target


def test_load_mvsplat_reports_mismatches(weights):
    model = UniqueSplat.from_preset("paper", variant="full")
    bad = {k: v for k, v in weights.items() if k != "depth_predictor.to_gaussians.2.bias"}
    with pytest.raises(CheckpointMismatchError, match="to_gaussians.2.bias"):
        model.load_mvsplat(bad)
    bad = dict(weights)
    bad["depth_predictor.to_gaussians.0.weight"] = torch.zeros(3, 3, 3, 3)
    with pytest.raises(CheckpointMismatchError, match="shape mismatches"):
        model.load_mvsplat(bad)
    bad = {k: v for k, v in weights.items() if "upsampler" not in k}
    with pytest.raises(CheckpointMismatchError, match="upsampler"):
        model.load_mvsplat(bad)


def test_paper_configuration_has_the_papers_parameter_count():
    model = UniqueSplat.from_preset("paper", variant="full")
    total = sum(p.numel() for p in model.parameters())
    assert abs(total / PAPER_PARAMETERS - 1) < 0.05, total
    assert model.parameter_table()[-1] == ("total", total)
    # the primary network keeps MVSplat's 11,955,734 parameters minus the generated layers
    specs = model.specs
    head = sum(math.prod(s.weight_shape) + s.out_channels for s in specs)
    primary = sum(p.numel() for p in model.primary.parameters())
    assert primary + head == sum(p.numel() for p in PrimaryNetwork().parameters())


def train_steps(model, args, steps: int, seed: int = 0, lr: float = 1e-3):
    """A few Adam steps on one scene: renders of the targets against fixed random images."""
    gen = torch.Generator().manual_seed(seed)
    n = args.target_intrinsics.shape[1]
    gt = torch.rand(1, n, 3, 64, 64, generator=gen).to(args.images.device)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    model.train()
    for _ in range(steps):
        opt.zero_grad()
        out = model(*args)
        loss = (out.color - gt).square().mean()
        loss.backward()
        opt.step()
    return out


def test_per_target_specialisation_and_gradients_reach_every_part():
    torch.manual_seed(0)
    model = UniqueSplat.from_preset("tiny", variant="full")
    args = scene()
    train_steps(model, args, 3, lr=1e-2)
    # After a step the zero-initialised last layers are non-zero, so every part's gradient
    # is non-zero from the second step on (checked on the last step's gradients).
    parts = {"e_a": [model.agnostic.embedding], "H_a": list(model.agnostic.hyper.parameters()),
             "H_s": list(model.specific.parameters()),
             "phi": list(model.view_embedding.phi.parameters()),
             "ResNet18": list(model.view_embedding.features.resnet.parameters()),
             "Proj": list(model.view_embedding.proj.parameters()),
             "primary": list(model.primary.parameters())}
    for name, params in parts.items():
        norm = sum(p.grad.norm() ** 2 for p in params if p.grad is not None)
        assert norm > 0, name
    # every parameter of the hypernetwork branches and of the primary network is used
    unused = [n for n, p in model.named_parameters() if p.grad is None]
    assert not unused, unused

    model.eval()
    te = args.target_extrinsics
    te2 = torch.cat([te[:, :2], te[:, :1]], 1)  # targets 0 and 2 are the same camera
    with torch.no_grad():
        out = model(*args.replaced(target_extrinsics=te2), render=False)
    g0, g1, g2 = (out.target(0, i) for i in range(3))
    for name in FIELDS:
        # identical cameras: the same arithmetic on the same inputs in one batch
        assert torch.allclose(getattr(g0, name), getattr(g2, name), atol=1e-6), name
    # different cameras: different Gaussians (colour, shape, depth and opacity are generated
    # per target: Delta W on both heads). Measured after these 3 steps: 6e-3 (harmonics),
    # 1e-2 (covariances), 7e-3 (means, of magnitude <= 100) and 2.8e-5 (opacities, <= 1),
    # each >= 7x above its threshold; the thresholds are >= 25x float32 rounding of the
    # values' magnitude (6e-6 for 100, 6e-8 for 1).
    assert (g0.harmonics - g1.harmonics).abs().max() > 1e-4
    assert (g0.covariances - g1.covariances).abs().max() > 1e-5
    assert (g0.means - g1.means).abs().max() > 1e-3
    assert (g0.opacities - g1.opacities).abs().max() > 3e-6


@pytest.mark.parametrize("init_std", [0.0, 1e-2])
def test_delta_init_std_opens_the_view_specific_gradient_path(init_std):
    # With Delta W = U V and U = 0 exactly, the gradient that reaches e_s (and the ResNet,
    # Proj and phi behind it) is proportional to U: exactly zero on the first step. A small
    # random U (delta_init_std) gives it a non-zero gradient at once, at the price of
    # starting near (not at) the primary network's output.
    torch.manual_seed(0)
    model = UniqueSplat.from_preset("tiny", variant="full", delta_init_std=init_std)
    args = scene()
    train_steps(model, args, 1, lr=0.0)  # one backward; lr 0 keeps the initial weights
    resnet = sum(p.grad.norm() ** 2 for p in model.view_embedding.parameters()
                 if p.grad is not None)
    deltas = model.specific(torch.randn(3, model.cfg.embed_dim))
    largest_u = max(d.u.abs().max() for d in deltas)
    if init_std == 0:
        assert resnet == 0 and largest_u == 0
    else:
        assert resnet > 0 and largest_u > 0


def test_each_target_renders_its_own_gaussians(device):
    # On every available device (conftest: CPU always, CUDA where present): a training step,
    # the per-target forward and the rasteriser on that device's Dr.Jit backend.
    torch.manual_seed(1)
    model = UniqueSplat.from_preset("tiny", variant="full").to(device)
    args = scene(n=2).to(device)
    train_steps(model, args, 2)
    model.eval()
    with torch.no_grad():
        out = model(*args, prune=None)  # every Gaussian (the inference default merges some)
    assert out.color.shape == (1, 2, 3, 64, 64) and out.depth.shape == (1, 2, 64, 64)
    te, tk = args.target_extrinsics, args.target_intrinsics
    tn, tf = args.target_near, args.target_far
    for i in range(2):
        g = out.target(0, i)
        r = rasterize(te[:, i], tk[:, i], tn[:, i], tf[:, i], (64, 64),
                      torch.zeros(1, 3, device=device),
                      g.means, g.covariances, g.harmonics, g.opacities,
                      RasterSettings(sh_basis="mvsplat"))
        # the same rasteriser on the same inputs, batched or not: bit-identical images
        assert torch.equal(r.color[0], out.color[0, i])
    assert out.alpha.mean() > 0.1


def test_agnostic_weights_are_cached_and_refreshed(monkeypatch):
    model = UniqueSplat.from_preset("tiny", variant="agnostic").eval()
    calls = []
    original = model.agnostic.forward
    monkeypatch.setattr(model.agnostic, "forward", lambda: calls.append(1) or original())
    args = scene(n=2)
    with torch.no_grad():
        first = model(*args, render=False)
        model(*args, render=False)
    assert len(calls) == 1  # one H_a evaluation for two scenes
    # (b) has one set of Gaussians for all targets
    assert torch.equal(first.target(0, 0).means, first.target(0, 1).means)
    with torch.no_grad():
        model.agnostic.embedding.add_(0.5)  # an in-place update, as an optimiser step does
        model(*args, render=False)
    assert len(calls) == 2
    model.train()
    model(*args, render=False)
    assert len(calls) == 3  # training: computed every forward, with gradients


@pytest.mark.parametrize("overrides", [
    {"delta_rank": None},
    {"specific_layers": ("to_gaussians.0", "to_gaussians.2")},
    {"target_layers": ("to_gaussians.0", "to_gaussians.2"), "specific_layers": ("to_gaussians.2",)},
    {"target_layers": ("to_gaussians.2", "to_disparity.0"),
     "specific_layers": ("to_disparity.0",)},
])
def test_other_injection_settings_start_at_the_primary_network(overrides):
    # Any choice of layers or Delta W form: at initialisation the full variant's Gaussians
    # are the baseline's (same primary weights copied into W); tolerance as above, except
    # for the means where the disparity head takes Delta W: depth = 1 / disparity turns the
    # head's float32 rounding (its convolution is summed in another order: grouped by target)
    # into depth^2 times it, up to 1e4 x at the far plane (100). So |d means| <= 1e-4 +
    # 5e-7 |means|^2 (5e-7: a few ulps of a disparity of order 1); measured up to 3.7e-4 at
    # |means| = 99 (7 % of the bound); a wrong path is off by order 1 everywhere.
    torch.manual_seed(2)
    base = UniqueSplat.from_preset("tiny", variant="baseline").eval()
    model = UniqueSplat.from_preset("tiny", variant="full", **overrides)
    sd = base.primary.state_dict()
    model.load_mvsplat(sd).eval()
    args = scene(b=2, seed=3)
    with torch.no_grad():
        a = base(*args, render=False).gaussians
        c = model(*args, render=False).gaussians
    for name in FIELDS:
        x, y = getattr(a, name), getattr(c, name)
        if name == "means":
            assert ((x - y).abs() <= 1e-4 + 5e-7 * x.square()).all(), name
        else:
            assert torch.allclose(x, y, rtol=1e-5, atol=1e-4), name


def test_resnet_weights_load_from_a_torchvision_file(tmp_path, caplog):
    path = tmp_path / "resnet18.pth"
    ref = ResNet18()
    torch.save(ref.state_dict(), path)
    model = UniqueSplat.from_preset("tiny", variant="full", resnet_weights=str(path))
    got = model.view_embedding.features.resnet
    assert torch.equal(got.layer2[0].conv1.weight, ref.layer2[0].conv1.weight)
    with caplog.at_level(logging.WARNING, logger="usplat_dr.model.hypernet.resnet"):
        UniqueSplat.from_preset("tiny", variant="full",
                                resnet_weights=str(tmp_path / "missing.pth"))
    assert "random initialisation" in caplog.text


def test_bad_configuration_and_inputs_name_the_argument():
    with pytest.raises(ValueError, match="variant must be one of"):
        UniqueSplat.from_preset("tiny", variant="both")
    with pytest.raises(ValueError, match="preset must be one of"):
        UniqueSplat.from_preset("huge")
    with pytest.raises(ValueError, match="target_layers"):
        UniqueSplatCfg(target_layers=("backbone.conv1",))
    with pytest.raises(ValueError, match="specific_layers"):
        UniqueSplatCfg(target_layers=("to_gaussians.2",), specific_layers=("to_disparity.0",))
    with pytest.raises(ValueError, match="unknown UniqueSplatCfg keys"):
        UniqueSplatCfg.from_dict({"rank": 4})
    cfg = UniqueSplatCfg.from_dict({"primary": {"d_feature": 64}, "phi_channels": [8, 8, 8, 8]})
    assert cfg.primary.d_feature == 64 and cfg.phi_channels == (8, 8, 8, 8)
    model = UniqueSplat.from_preset("tiny", variant="baseline")
    args = scene(n=2)
    te, tk = args.target_extrinsics, args.target_intrinsics
    tn, tf = args.target_near, args.target_far

    def unchecked(*fields) -> Cameras:
        # cameras whose fields disagree, built past the dataclass's own shape check (which the
        # suite's jaxtyping hook runs): what check_targets must catch on its own
        cams = object.__new__(Cameras)
        for name, value in zip(("extrinsics", "intrinsics", "near", "far"), fields,
                               strict=True):
            object.__setattr__(cams, name, value)
        return cams

    with pytest.raises(ValueError, match="target_extrinsics must have shape"):
        model.check_targets(1, unchecked(te[:, :, :3], tk, tn, tf))
    with pytest.raises(ValueError, match="target_near must have shape"):
        model.check_targets(1, unchecked(te, tk, tn[:, :1], tf))
    with pytest.raises(ValueError, match=r"target_intrinsics must have shape \[B=2, N, 3, 3\]"):
        model.check_targets(2, args.targets)


def test_inference_culling_keeps_the_renders():
    """Culling per target keeps the images of rendering every Gaussian, merging stays close;
    eval mode renders every Gaussian by default (``inference_prune``: pruning does not pay on
    CPU, train/bench/prune.py); training renders every Gaussian; pruning refuses to run
    under autograd."""
    torch.manual_seed(2)
    model = UniqueSplat.from_preset("tiny", variant="full")
    args = scene(n=3)
    # targets turned away from the contexts' content so that culling has work to do
    args.target_extrinsics[:, 2, :3, :3] = torch.tensor([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    model.eval()
    with torch.no_grad():
        culled = model(*args, prune=PruneSettings())
        everything = model(*args, prune=None)
        merged = model(*args, prune=PruneSettings(merge=True))
        default = model(*args)
    total = len(culled.gaussians)
    assert model.inference_prune is None
    assert (everything.aux["rendered"] == total).all()
    assert torch.equal(default.aux["rendered"], everything.aux["rendered"])
    assert torch.equal(default.color, everything.color)
    assert (culled.aux["rendered"] <= total).all()
    assert culled.aux["rendered"][0, 2] < total // 2
    assert (merged.aux["rendered"] <= culled.aux["rendered"]).all()
    # the same Gaussians in the same depth order; only float32 summation order may differ
    for a, b in ((culled.color, everything.color), (culled.alpha, everything.alpha)):
        assert (a - b).abs().max() <= 1e-6
    # merging approximates (bench: <= 0.005 dB on trained models); a random-weight model's
    # image stays above 40 dB of the full render
    mse = (merged.color - everything.color).square().mean().item()
    assert mse == 0 or -10 * math.log10(mse) > 40
    model.train()
    out = model(*args)
    assert (out.aux["rendered"] == total).all()
    with pytest.raises(ValueError, match="inference only"):
        model(*args, prune=PruneSettings())
    with pytest.raises(ValueError, match="prune must be"):
        model(*args, prune="yes")


def test_encoder_and_agnostic_weights_run_once_per_scene_whatever_the_targets():
    """No per-target recomputation (README, "UniqueSplat: Gaussians per target view"): the
    backbone, the cost-volume U-Net and H_a run once per forward pass for 1 or 5 targets
    (counted with forward hooks)."""
    model = UniqueSplat.from_preset("tiny", variant="full").eval()
    calls = {"backbone": 0, "agnostic": 0, "depth_unet": 0}
    model.primary.backbone.register_forward_hook(
        lambda *a: calls.__setitem__("backbone", calls["backbone"] + 1))
    model.agnostic.register_forward_hook(
        lambda *a: calls.__setitem__("agnostic", calls["agnostic"] + 1))
    model.primary.depth_predictor.refine_unet.register_forward_hook(
        lambda *a: calls.__setitem__("depth_unet", calls["depth_unet"] + 1))
    for n in (1, 5):
        calls.update(backbone=0, agnostic=0, depth_unet=0)
        model._cached_weights = None  # count H_a too (it is cached across calls)
        with torch.no_grad():
            model(*scene(n=n), render=False)
        assert calls == {"backbone": 1, "agnostic": 1, "depth_unet": 1}, (n, calls)


@pytest.mark.parametrize("variant", ["baseline", "full"])
def test_three_context_views_render_and_every_view_counts(variant):
    # MVSplat evaluates DTU with 3 context views. With V = 3 the model must treat the views
    # symmetrically (its cost volume, transformer and Proj reduce over all of them), so the
    # order of the context views must not change the render, while each view must matter.
    # (The view-specific branch expresses target rays in the first context camera's frame,
    # so only views 1 and 2 are swapped.)
    from usplat_dr.render.scenes import orbit_cameras

    torch.manual_seed(0)
    model = UniqueSplat.from_preset("tiny", variant=variant).eval()
    if variant == "full":  # non-zero Delta W, so the view-specific branch shapes the render
        for p in model.specific.parameters():
            torch.nn.init.normal_(p, std=0.02)
    c2w = orbit_cameras(5, radius=4.0, height=0.5, arc_degrees=40.0).float()
    k = torch.tensor([[1.0, 0, 0.5], [0, 1.0, 0.5], [0, 0, 1]])
    images = torch.rand(1, 3, 3, 32, 32, generator=torch.Generator().manual_seed(1))

    def render(images, order):
        with torch.no_grad():
            return model(images[:, order],
                         Cameras(c2w[None, [0, 2, 4]][:, order], k.expand(1, 3, 3, 3),
                                 torch.ones(1, 3), 10 * torch.ones(1, 3)),
                         Cameras(c2w[None, [1, 3]], k.expand(1, 2, 3, 3), torch.ones(1, 2),
                                 10 * torch.ones(1, 2)), prune=None)

    out = render(images, [0, 1, 2])
    assert out.color.shape == (1, 2, 3, 32, 32) and torch.isfinite(out.color).all()
    assert out.gaussians.means.shape == (2, 3 * 32 * 32, 3)  # one Gaussian per context pixel
    # float32 sums over views and view pairs in another order: ~1e-7 per pixel on average;
    # a rounding difference can flip one of the rasteriser's thresholds (the alpha < 1/255
    # skip) and so change a pixel by up to 1/255 = 3.9e-3 (observed max 3e-4). A view dropped
    # or paired wrongly changes pixels by >= 1e-2.
    swapped = render(images, [0, 2, 1]).color
    assert (swapped - out.color).abs().mean() < 1e-5
    assert (swapped - out.color).abs().max() < 1 / 255
    changed = images.clone()
    changed[:, 2] = torch.rand(1, 3, 32, 32, generator=torch.Generator().manual_seed(2))
    assert (render(changed, [0, 1, 2]).color - out.color).abs().max() > 1e-2


def test_colour_sh_degree_zero_makes_colour_view_independent():
    # The control for view-dependent colour: the same weights, the coefficients above the
    # chosen degree masked to exactly zero, everything else unchanged (bit for bit: the mask
    # multiplies, and 0.1 * 0.25^l or 1 are the same factors in both models).
    torch.manual_seed(4)
    model = UniqueSplat.from_preset("tiny", variant="baseline").eval()
    cfg = dataclasses.replace(model.cfg, primary=dataclasses.replace(model.cfg.primary,
                                                                     colour_sh_degree=0))
    flat = UniqueSplat(cfg).eval()
    flat.load_state_dict(model.state_dict())
    args = scene(seed=5)
    with torch.no_grad():
        g, f = model(*args, render=False).gaussians, flat(*args, render=False).gaussians
    assert torch.equal(f.harmonics[..., 0], g.harmonics[..., 0])
    assert (f.harmonics[..., 1:] == 0).all() and (g.harmonics[..., 1:] != 0).any()
    assert torch.equal(f.means, g.means) and torch.equal(f.opacities, g.opacities)
    with pytest.raises(ValueError, match="colour_sh_degree"):
        dataclasses.replace(model.cfg.primary, colour_sh_degree=3)


def test_a_reused_encoding_and_given_delta_w_render_what_forward_renders():
    """``encoding=`` (the encoder's output, computed once) and ``delta_w=`` (Delta W given,
    for studies with the primary network fixed) change nothing when they hold what forward
    would compute itself: (c) with its own branch's Delta W, and (a) with a zero Delta W."""
    torch.manual_seed(0)
    model = UniqueSplat.from_preset("tiny", variant="full", delta_init_std=1e-2).eval()
    args = scene(n=3)
    with torch.no_grad():
        ref = model(*args)
        encoding = model.encode(**context(args))
        again = model(*args, hooks=StudyHooks(encoding=encoding))
        _, deltas, _ = model._target_weights(args.images, args.context, args.targets)
        given = model(*args, hooks=StudyHooks(encoding=encoding, delta_w=deltas))
    # the same arithmetic on the same tensors: bit-for-bit
    assert torch.equal(again.color, ref.color) and torch.equal(given.color, ref.color)
    assert given.per_target

    base = UniqueSplat.from_preset("tiny", variant="baseline").eval()
    spec = base.conv_spec("to_disparity.2")
    zero = LayerDelta(bias=torch.zeros(3, spec.out_channels),
                      u=torch.zeros(3, spec.out_channels, 2),
                      v=torch.randn(3, 2, spec.in_channels, spec.kernel_size, spec.kernel_size))
    with torch.no_grad():
        plain = base(*args)
        zeroed = base(*args, hooks=StudyHooks(delta_w={"to_disparity.2": zero}))
    # Delta W = U V = 0 through the per-target path: the same Gaussians up to the float
    # rounding of a convolution batched differently, which the depth (up to far = 100)
    # amplifies: measured at 1 and 2 threads, means differ by <= 1.2e-4 on values up to ~100
    # (elementwise <= 3e-6 relative), covariances <= 2.2e-5 relative, opacities 1.2e-7,
    # colour coefficients 0. Bounds on the norm of the difference relative to the values
    # (5x-100x above those) hold on every thread count and CPU; a wrong layer moves them by
    # 65x (means) and 0.12 (opacities), below. Compared before rendering: near-equal depths
    # can swap places in the depth sort under such rounding and move a pixel by far more.
    assert zeroed.per_target and not plain.per_target
    g, h = zeroed.gaussians, plain.gaussians

    def rel(a, b):
        return ((a - b).norm() / b.norm()).item()

    assert rel(g.means, h.means) < 1e-5 and rel(g.covariances, h.covariances) < 1e-4
    assert (g.opacities - h.opacities).abs().max() < 1e-5
    assert (g.harmonics - h.harmonics).abs().max() < 1e-5  # no Delta W on to_gaussians
    # and a Delta W that is not zero moves them far beyond that
    with torch.no_grad():
        half = dataclasses.replace(zero, bias=torch.full((3, spec.out_channels), 0.5))
        moved = base(*args, render=False,
                     hooks=StudyHooks(delta_w={"to_disparity.2": half})).gaussians
    assert rel(moved.means, h.means) > 1e-2 and (moved.opacities - h.opacities).abs().max() > 1e-2


def test_a_wrong_encoding_or_delta_w_names_the_argument():
    model = UniqueSplat.from_preset("tiny", variant="baseline").eval()
    args = scene(n=2)
    spec = model.conv_spec("to_gaussians.2")
    good = LayerDelta(bias=torch.zeros(2, spec.out_channels))
    with pytest.raises(ValueError, match="delta_w must map layer names"):
        model(*args, render=False, hooks=StudyHooks(delta_w={"primary.backbone": good}))
    with pytest.raises(ValueError, match=r"delta_w\['to_gaussians.2'\] must be a LayerDelta "
                                         r"for B\*N = 2"):
        wrong = LayerDelta(bias=torch.zeros(3, 1))
        model(*args, render=False, hooks=StudyHooks(delta_w={"to_gaussians.2": wrong}))
    with torch.no_grad():
        small = model.encode(**context(scene(size=32, n=2)))
    with pytest.raises(ValueError, match="encoding is for other context views"):
        model(*args, render=False, hooks=StudyHooks(encoding=small))
    with torch.no_grad():
        dropped = model.encode(**context(args))
    dropped.drop_intermediates()  # what PrimaryNetwork.forward leaves: no head inputs
    with pytest.raises(ValueError, match="encoding must be what UniqueSplat.encode returned"):
        model(*args, render=False, hooks=StudyHooks(encoding=dropped))
    grad = model.encode(**context(args))  # parameters require grad: so does the encoding
    with pytest.raises(ValueError, match="encoding needs a gradient"):
        model(*args, render=False, hooks=StudyHooks(encoding=grad))
    with pytest.raises(ValueError, match="name must be one of"):
        model.conv_spec("to_gaussians.1")


def test_view_features_from_the_primary_network_read_it_without_training_it():
    # E_H as the primary network's backbone features (view_features="primary"): Delta W
    # depends on the images through them, and no gradient flows back into the encoder
    torch.manual_seed(0)
    model = UniqueSplat.from_preset("tiny", variant="full", view_features="primary",
                                    delta_init_std=0.5)
    assert not hasattr(model.view_embedding.features, "resnet")
    args = scene(n=2)
    cams = dict(target_extrinsics=args.target_extrinsics,
                target_intrinsics=args.target_intrinsics, target_near=args.target_near,
                target_far=args.target_far, near=args.near, far=args.far)
    deltas = model.view_delta_w(args.images, args.extrinsics, args.intrinsics, **cams)
    sum(d.u.square().sum() + d.v.square().sum() for d in deltas.values()).backward()
    assert model.view_embedding.features.lateral.weight.grad.norm() > 0
    assert all(p.grad is None for p in model.primary.parameters())  # detached
    with torch.no_grad():
        other = model.view_delta_w(args.images.flip(-1), args.extrinsics, args.intrinsics,
                                   **cams)
    assert any(not torch.allclose(other[k].u, deltas[k].u) for k in deltas)
    # two scenes in a batch ((v b) order inside the encoder): each gets its own Delta W
    two = scene(n=2, b=2, seed=3)
    cams2 = dict(target_extrinsics=two.target_extrinsics,
                 target_intrinsics=two.target_intrinsics, target_near=two.target_near,
                 target_far=two.target_far)
    with torch.no_grad():
        both = model.view_delta_w(two.images, two.extrinsics, two.intrinsics, **cams2,
                                  near=two.near, far=two.far)
        for b in range(2):
            one = model.view_delta_w(two.images[b:b + 1], two.extrinsics[b:b + 1],
                                     two.intrinsics[b:b + 1],
                                     **{k: v[b:b + 1] for k, v in cams2.items()},
                                     near=two.near[b:b + 1], far=two.far[b:b + 1])
            for k in both:  # float32 batched against single convolutions
                torch.testing.assert_close(both[k].u[2 * b:2 * b + 2], one[k].u,
                                           rtol=1e-4, atol=1e-6)
    assert all(not torch.allclose(both[k].u[:2], both[k].u[2:]) for k in both)  # other images
    with pytest.raises(ValueError, match="near and far"):
        model.view_delta_w(args.images, args.extrinsics, args.intrinsics,
                           args.target_extrinsics, args.target_intrinsics, args.target_near,
                           args.target_far)
    with pytest.raises(ValueError, match="view_features"):
        UniqueSplat.from_preset("tiny", variant="full", view_features="vgg")
