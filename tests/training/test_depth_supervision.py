"""Depth supervision and the fine-tuning protocol: the depth loss against a float64
reference written from its definition, the context depths the model exposes against the
Gaussians it places, a depth-supervised run that learns depth, and ``model.init_from``
starting (b) and (c) exactly at a trained (a)."""

import math
from pathlib import Path

import pytest
import torch
from torch.utils.data import default_collate

from tests.synth_sets import tiny_training_config
from usplat_dr.config import ConfigError
from usplat_dr.data.dataset import dataset_from_section
from usplat_dr.data.synth import synthesize
from usplat_dr.data.types import model_inputs
from usplat_dr.model import UniqueSplat
from usplat_dr.training import Trainer
from usplat_dr.training.config import model_from_config
from usplat_dr.training.losses import depth_loss, mse_loss, target_depth_loss, training_loss

CONFIGS = Path(__file__).parents[2] / "usplat_dr" / "configs"
pytestmark = pytest.mark.usefixtures("restore_threads")


@pytest.fixture(scope="module")
def synth_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("synth_depth")
    synthesize(root, scenes=2, frames=10, resolution=(32, 32), seed=3, spp=4, stage="train",
               previews=0, progress=False, kinds=("indoor",))
    return root


def config(root: Path, out: Path, steps: int, *overrides: str) -> dict:
    return tiny_training_config(CONFIGS / "synthetic_tiny_depth.yaml", root, out, steps,
                                "threads=1", *overrides)


def test_depth_loss_matches_a_float64_reference():
    g = torch.Generator().manual_seed(0)
    b, v, h, w = 2, 2, 5, 7
    k = torch.tensor([[0.9, 0.0, 0.45], [0.0, 1.1, 0.55], [0.0, 0.0, 1.0]])  # off-centre
    intrinsics = k.expand(b, v, 3, 3).clone()
    intrinsics[1, 1, 0, 0] = 1.3
    z = 0.5 + 3 * torch.rand(b, v, h, w, generator=g)
    z[0, 0, 1, 2] = math.inf  # a miss
    z[1, 1, 3, 0] = math.inf
    aux = {"context_depths": 0.5 + 3 * torch.rand(b, v, h, w, generator=g),
           "context_coarse_depths": 0.5 + 3 * torch.rand(b, v, h, w, generator=g)}
    terms = {key: [] for key in aux}
    for bi in range(b):
        for vi in range(v):
            kinv = torch.linalg.inv(intrinsics[bi, vi].double())
            for y in range(h):
                for x in range(w):
                    if not math.isfinite(z[bi, vi, y, x]):
                        continue
                    ray = kinv @ torch.tensor([(x + 0.5) / w, (y + 0.5) / h, 1.0],
                                              dtype=torch.float64)
                    true = z[bi, vi, y, x].double() * ray.norm()  # distance along the ray
                    for key, pred in aux.items():
                        terms[key].append(abs(math.log(pred[bi, vi, y, x].double() / true)))
    ref = sum(sum(t) / len(t) for t in terms.values())
    # float32 logs of values in [0.5, 3.5], averaged over 68 pixels: ~1e-7 relative
    assert depth_loss(aux, z, intrinsics).item() == pytest.approx(ref, rel=1e-5)
    # no valid pixel: zero, not NaN
    none = depth_loss(aux, torch.full_like(z, math.inf), intrinsics)
    assert none.item() == 0.0


def test_target_depth_loss_matches_a_float64_reference():
    g = torch.Generator().manual_seed(1)
    b, n, h, w = 2, 3, 4, 5
    alpha = torch.rand(b, n, h, w, generator=g)  # about half the pixels under 0.5
    depth = alpha * (0.5 + 3 * torch.rand(b, n, h, w, generator=g))  # alpha-weighted z
    z = 0.5 + 3 * torch.rand(b, n, h, w, generator=g)
    z[0, 1, 2, 3] = math.inf  # a miss
    z[1, 0, 0, 0] = 0.0  # no depth
    terms = []
    for i in range(b):
        for j in range(n):
            for y in range(h):
                for x in range(w):
                    a, t = alpha[i, j, y, x].double(), z[i, j, y, x].double()
                    if math.isfinite(t) and t > 0 and a > 0.5:
                        terms.append(abs(math.log(depth[i, j, y, x].double() / a / t)))
    assert 10 < len(terms) < b * n * h * w  # the mask both keeps and drops pixels
    depth.requires_grad_(True)
    alpha.requires_grad_(True)
    loss = target_depth_loss(depth, alpha, z)
    # float32 logs of ratios in [0.15, 7], averaged over ~60 pixels: ~1e-7 relative
    assert loss.item() == pytest.approx(sum(terms) / len(terms), rel=1e-5)
    loss.backward()  # gradients reach both the depth and the opacity of the kept pixels
    kept = torch.isfinite(z) & (z > 0) & (alpha.detach() > 0.5)
    assert (depth.grad[kept] != 0).all() and (depth.grad[~kept] == 0).all()
    assert (alpha.grad[kept] != 0).all()
    assert target_depth_loss(depth, alpha, torch.full_like(z, math.inf)).item() == 0.0


def test_training_loss_weighs_its_terms_until_depth_until_step(synth_root, tmp_path):
    trainer = Trainer(config(synth_root, tmp_path, 4, "model.variant=baseline", "loss.mse=2",
                             "loss.depth=0.5", "loss.target_depth=0.25",
                             "loss.depth_until_step=3"))
    batch = trainer.batches.next()
    with torch.no_grad():
        out = trainer.model(*model_inputs(batch, trainer.device))
    cfg, context = trainer.config.loss, batch["context"]
    mse = mse_loss(out.color, batch["target"]["image"])
    d = depth_loss(out.aux, context["depth"], context["intrinsics"])
    t = target_depth_loss(out.depth, out.alpha, batch["target"]["depth"])
    loss, parts = training_loss(out, batch, cfg, 2, trainer.device)
    # the terms added in this order: the same float32 sums, so equal bit for bit
    assert torch.equal(loss, 2 * mse + 0.5 * d + 0.25 * t)
    assert parts == {"mse": mse.item(), "depth": d.item(), "target_depth": t.item()}
    assert torch.equal(trainer.loss(out, batch)[0], training_loss(out, batch, cfg, 0,
                                                                  trainer.device)[0])
    loss, parts = training_loss(out, batch, cfg, 3, trainer.device)  # the depth terms end
    assert torch.equal(loss, 2 * mse) and set(parts) == {"mse"}


def test_context_depths_are_where_the_gaussians_sit(synth_root):
    torch.manual_seed(0)
    model = UniqueSplat.from_preset("tiny", variant="full").eval()
    example = next(iter(dataset_from_section(
        {"name": "synth", "roots": [str(synth_root)], "image_shape": [32, 32],
         "view_sampler": {"name": "bounded", "num_target_views": 2,
                          "min_distance_between_context_views": 3,
                          "max_distance_between_context_views": 6,
                          "initial_min_distance_between_context_views": 3,
                          "initial_max_distance_between_context_views": 6}}, "train")))
    batch = default_collate([example])
    with torch.no_grad():
        out = model(*model_inputs(batch, torch.device("cpu")), render=False)
    d = out.aux["context_depths"]  # [1, 2, 32, 32]
    assert d.shape == (1, 2, 32, 32)
    # Target 0's Gaussians, context view by context view, raster order (one per pixel):
    # each sits at its context depth along a unit ray from its camera's centre.
    means = out.gaussians.means[0].view(2, 32 * 32, 3)
    centres = batch["context"]["extrinsics"][0, :, :3, 3]
    dist = (means - centres[:, None]).norm(dim=-1).view(1, 2, 32, 32)
    # float32 over distances of a few metres: ~1e-6 relative
    torch.testing.assert_close(dist, d, rtol=1e-5, atol=1e-6)
    near, far = batch["context"]["near"][0, 0].item(), batch["context"]["far"][0, 0].item()
    coarse = out.aux["context_coarse_depths"]
    assert coarse.shape == d.shape
    # the coarse depth is a softmax average of disparities in [1/far, 1/near]
    assert (coarse >= near * (1 - 1e-5)).all() and (coarse <= far * (1 + 1e-5)).all()


def test_depth_supervision_learns_depth(synth_root, tmp_path):
    torch.manual_seed(0)
    trainer = Trainer(config(synth_root, tmp_path, 60, "model.variant=baseline",
                             "loss.depth=1.0", "optimizer.warm_up_fraction=0.05"))
    batch = trainer.batches.next()

    def error():
        trainer.model.eval()
        with torch.no_grad():
            out = trainer.model(*model_inputs(batch, trainer.device), render=False)
        return depth_loss(out.aux, batch["context"]["depth"],
                          batch["context"]["intrinsics"]).item()

    before = error()
    for _ in range(60):
        stats = trainer.train_step(batch)
    after = error()
    assert "depth" in stats
    # Measured: 3.6 -> 1.0 (the sum of two mean |log| errors) in 60 steps on one scene; a
    # halving cannot come from noise.
    assert after < 0.5 * before, (before, after)


def test_target_depth_supervision_learns_the_rendered_depth(synth_root, tmp_path):
    torch.manual_seed(0)
    trainer = Trainer(config(synth_root, tmp_path, 60, "model.variant=baseline",
                             "loss.depth=0.0", "loss.target_depth=1.0",
                             "optimizer.warm_up_fraction=0.05"))
    batch = trainer.batches.next()

    def error():
        trainer.model.eval()
        with torch.no_grad():
            out = trainer.model(*model_inputs(batch, trainer.device))
        return target_depth_loss(out.depth, out.alpha, batch["target"]["depth"]).item()

    before = error()
    for _ in range(60):
        stats = trainer.train_step(batch)
    after = error()
    assert "target_depth" in stats and "depth" not in stats
    # Measured: 1.16 -> 0.012 (mean |log| error of the rendered target depth) in 60 steps on
    # one scene; a halving cannot come from noise.
    assert after < 0.5 * before, (before, after)


def test_init_from_starts_finetuning_at_the_baseline(synth_root, tmp_path):
    trainer = Trainer(config(synth_root, tmp_path / "a", 2, "model.variant=baseline"))
    trainer.fit()
    ckpt = trainer.checkpoint_path
    batch = trainer.batches.next()
    args = model_inputs(batch, torch.device("cpu"))
    with torch.no_grad():
        ref = trainer.model.eval()(*args, render=False).gaussians
        for variant in ("agnostic", "full"):
            model = model_from_config({"preset": "tiny", "variant": variant,
                                       "init_from": str(ckpt)}).eval()
            g = model(*args, render=False).gaussians
            for name in ("means", "covariances", "harmonics", "opacities"):
                # W is the checkpoint's head reshaped through H_a's bias and Delta W = 0:
                # the same convolutions up to float32 summation order.
                torch.testing.assert_close(getattr(g, name), getattr(ref, name),
                                           rtol=1e-4, atol=1e-5)
    with pytest.raises(ConfigError, match="does not exist"):
        model_from_config({"preset": "tiny", "variant": "full",
                           "init_from": str(tmp_path / "none.ckpt")})
    full = Trainer(config(synth_root, tmp_path / "c", 1, "model.variant=full"))
    full.save()
    # a (c) starts another of the same configuration with every weight (the view-specific
    # stage, train.trainable=view_specific); any other model only from an (a)
    same = model_from_config({"preset": "tiny", "variant": "full",
                              "init_from": str(full.checkpoint_path)})
    for k, v in full.model.state_dict().items():
        assert torch.equal(same.state_dict()[k], v), k
    with pytest.raises(ConfigError, match="start from a baseline"):
        model_from_config({"preset": "tiny", "variant": "agnostic",
                           "init_from": str(full.checkpoint_path)})
    # another view-specific branch (a design change): all but the weights whose shape changed
    other = model_from_config({"preset": "tiny", "variant": "full",
                               "overrides": {"specific_hidden": 24, "proj_stride": 4},
                               "init_from": str(full.checkpoint_path)})
    fresh = [k for k, v in full.model.state_dict().items()
             if not torch.equal(other.state_dict()[k], v)]
    assert fresh and all(k.startswith("specific.hyper.") for k in fresh), fresh
    with pytest.raises(ConfigError, match="another configuration"):  # H_a's width differs
        model_from_config({"preset": "tiny", "variant": "full", "overrides": {"hyper_hidden": 8},
                           "init_from": str(full.checkpoint_path)})
