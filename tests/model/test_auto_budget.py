"""The automatic Gaussian count (model/auto_budget.py): the choice rule, its calibration, and
the count on hand-built scenes whose answer is known (a duplicated surface is merged, finer
texture keeps more)."""

import math

import pytest
import torch

from usplat_dr.evaluation.metrics import psnr
from usplat_dr.geometry.cameras import Cameras
from usplat_dr.model.auto_budget import (
    AUTO_KEEPS,
    AutoBudget,
    Calibration,
    choose_keep,
    image_psnr,
    make_budget,
)
from usplat_dr.model.budget import GaussianBudget
from usplat_dr.render.prune import PruneSettings
from usplat_dr.training.loader import load

#: The proxy loss taken as it is: a line of slope 1 through 0 with no margin at every budget.
IDENTITY = Calibration("dither", tuple((k, 0.0, 1.0, 0.0) for k in AUTO_KEEPS), 0.9, "none")


def test_image_psnr_is_the_protocols():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(2, 3, 3, 8, 8, generator=g) * 1.2 - 0.1  # some outside [0, 1]: clipped
    b = torch.rand(2, 3, 3, 8, 8, generator=g)
    assert torch.equal(image_psnr(a, b), psnr(a, b))


def test_choose_keep_goes_down_from_the_largest_and_stops_at_the_first_outside():
    asked = []
    # within 0.2 from 70% down to 15%, then 10% outside; 5% within again (not reached: the
    # count keeps the smallest budget below which nothing larger fails)
    losses = {0.05: 0.0, 0.1: 0.5, 0.15: 0.1, 0.2: 0.0, 0.3: 0.0, 0.4: 0.0, 0.5: 0.0, 0.7: 0.0}

    def proxy(keep):
        asked.append(keep)
        return losses[keep]

    keep, readings = choose_keep(proxy, AutoBudget(tolerance=0.2), None)
    assert keep == 0.15 and asked == [0.7, 0.5, 0.4, 0.3, 0.2, 0.15, 0.1]
    assert readings[0.1] == (0.5, 0.5) and 0.05 not in readings
    # the largest outside: every Gaussian, after one render
    asked.clear()
    assert choose_keep(lambda k: asked.append(k) or 1.0, AutoBudget(), None)[0] == 1.0
    assert asked == [0.7]
    # all within: the smallest, after rendering each
    asked.clear()
    assert choose_keep(lambda k: asked.append(k) or 0.0, AutoBudget(), None)[0] == 0.05
    assert asked == list(reversed(AUTO_KEEPS))
    # a reading that failed (NaN: both renders exact, or a NaN render) stops the count there
    assert choose_keep(lambda k: math.nan, AutoBudget(), None)[0] == 1.0
    assert choose_keep(lambda k: math.nan if k < 0.5 else 0.0, AutoBudget(), None)[0] == 0.5


def test_choose_keep_predicts_through_the_calibration():
    cal = Calibration("dither", ((0.1, 0.5, 1.0, 0.1), (0.3, 0.0, 0.5, 0.05)), 0.9, "dev")
    # predicted 0.1 -> 0.5 + 1.0 + 0.1 = 1.6, 0.3 -> 0.5 * 0.2 + 0.05 = 0.15; 0.5 has no line:
    # its proxy loss is its prediction
    found = {0.1: 1.0, 0.3: 0.2, 0.5: 0.1}
    keeps = (0.1, 0.3, 0.5)
    keep, readings = choose_keep(found.get, AutoBudget(0.2, keeps=keeps), cal)
    assert keep == 0.3 and readings[0.1] == (1.0, pytest.approx(1.6))
    assert choose_keep(found.get, AutoBudget(0.12, keeps=keeps), cal)[0] == 0.5
    assert choose_keep(found.get, AutoBudget(0.05, keeps=keeps), cal)[0] == 1.0


@pytest.mark.parametrize("kwargs, needle", [
    ({"tolerance": -1}, "tolerance must be a number of dB >= 0"),
    ({"tolerance": math.nan}, "tolerance must be a number of dB >= 0"),
    ({"tolerance": True}, "tolerance must be a number of dB >= 0"),
    ({"rank_by": "size"}, "AutoBudget.rank_by must be one of"),
    ({"keeps": (0.5, 0.3)}, "keeps must be ascending distinct fractions"),
    ({"keeps": (0.5, 1.0)}, "keeps must be ascending distinct fractions"),
])
def test_auto_budget_settings_are_checked(kwargs, needle):
    with pytest.raises(ValueError, match=needle):
        AutoBudget(**kwargs)


def test_make_budget_takes_the_loose_settings():
    assert make_budget(None) is None
    assert make_budget(0.3, "opacity") == GaussianBudget(0.3, "opacity")
    assert make_budget("auto") == AutoBudget()
    assert make_budget("auto", "learned", 0.5) == AutoBudget(0.5, "learned")
    with pytest.raises(ValueError, match="applies to budget='auto' only"):
        make_budget(0.3, tolerance=0.5)
    with pytest.raises(ValueError, match="a count, a fraction, 'auto' or None"):
        make_budget("all")


def test_calibration_round_trips_and_malformed_ones_name_where():
    cal = Calibration("learned", ((0.3, 0.1, 0.5, 0.2),), 0.9, "dev, 40 scenes", 64)
    assert Calibration.from_dict(cal.as_dict()) == cal
    with pytest.raises(ValueError, match="at least one"):
        Calibration("dither", (), 0.9, "dev")
    with pytest.raises(ValueError, match="manifest entry x: not an automatic count's"):
        Calibration.from_dict({"rank_by": "dither", "fits": [[0.3, 1.0]]}, "manifest entry x")
    with pytest.raises(ValueError, match="fits rows must be"):
        Calibration("dither", ((1.5, 0.0, 1.0, 0.0),), 0.9, "dev")
    # validated as data: a list where a dict belongs, a bounded count of rows, one row per
    # budget, a quantile and a size that mean something
    with pytest.raises(ValueError, match="more than the 64 budgets"):
        Calibration("dither", tuple((k / 200, 0.0, 1.0, 0.0) for k in range(1, 100)), 0.9, "d")
    with pytest.raises(ValueError, match="two rows for one budget"):
        Calibration("dither", ((0.3, 0.0, 1.0, 0.0), (0.3, 0.1, 1.0, 0.0)), 0.9, "dev")
    with pytest.raises(ValueError, match="quantile must be in"):
        Calibration("dither", ((0.3, 0.0, 1.0, 0.0),), 9.0, "dev")
    with pytest.raises(ValueError, match="size must be pixels"):
        Calibration("dither", ((0.3, 0.0, 1.0, 0.0),), 0.9, "dev", 10**9)


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return load("tiny_full").eval()


def scene(images: torch.Tensor):
    """The hand-built scene's inputs: ``images`` [1, 2, 3, 64, 64] seen by two cameras 0.2
    apart looking down +z at a wall 3 units away, and two targets between them."""
    def cams(xs):
        e = torch.eye(4).repeat(1, len(xs), 1, 1)
        e[0, :, 0, 3] = torch.tensor(xs)
        k = torch.tensor([[1.0, 0, 0.5], [0, 1.0, 0.5], [0, 0, 1]]).repeat(1, len(xs), 1, 1)
        return Cameras(e, k, torch.full((1, len(xs)), 1.0), torch.full((1, len(xs)), 10.0))
    return images, cams([-0.1, 0.1]), cams([-0.05, 0.05])


def textures():
    g = torch.Generator().manual_seed(1)
    coarse = torch.rand((1, 1, 3, 8, 8), generator=g).repeat_interleave(8, -1)
    coarse = coarse.repeat_interleave(8, -2).repeat(1, 2, 1, 1, 1)  # 8x8-pixel blocks
    fine = torch.rand((1, 1, 3, 64, 64), generator=g).repeat(1, 2, 1, 1, 1)  # per-pixel noise
    return coarse, fine


def test_finer_texture_keeps_more(model):
    coarse, fine = textures()
    for tolerance in (0.3, 0.5):
        auto = AutoBudget(tolerance, calibration=IDENTITY)
        with torch.no_grad():
            kept = [float(model(*scene(x), budget=auto).aux["auto_keep"][0])
                    for x in (coarse, fine)]
        assert kept[0] < kept[1], (tolerance, kept)


def test_the_count_is_its_proxy_and_the_render_its_budget_with_merging(model):
    coarse, _ = textures()
    images, context, targets = scene(coarse)
    with torch.no_grad():
        out = model(images, context, targets, budget=AutoBudget(0.3, calibration=IDENTITY))
        keep = float(out.aux["auto_keep"][0])
        assert 0 < keep < 1
        # the reading at the chosen budget, measured here independently of the count
        def context_psnr(budget):
            r = model(images, context, context, budget=budget)
            return float(psnr(r.color, images).mean())
        direct = context_psnr(None) - context_psnr(GaussianBudget(keep, "dither"))
        # the same renders in the same order of operations: float32 PSNRs agree to rounding
        assert out.aux["auto_readings"][0][keep][0] == pytest.approx(direct, abs=1e-5)
        # the targets: that budget rendered with near-duplicates merged, bit for bit
        again = model(images, context, targets, budget=GaussianBudget(keep, "dither"),
                      prune=PruneSettings(merge=True))
    assert torch.equal(out.color, again.color)
    assert torch.equal(out.aux["rendered"], again.aux["rendered"])
    assert out.aux["auto_budget"] == GaussianBudget(keep, "dither")


def test_a_duplicated_surface_is_merged(model):
    # both context views the same image from the same camera: every Gaussian has an exact twin
    coarse, _ = textures()
    images, context, targets = scene(coarse)
    one = Cameras(*(t[:, :1].repeat(1, 2, *([1] * (t.dim() - 2)))
                    for t in (context.extrinsics, context.intrinsics, context.near, context.far)))
    with torch.no_grad():
        merged = model(images, one, targets, budget=AutoBudget(0.3, calibration=IDENTITY))
        kept = merged.aux["kept"][0]
        unmerged = model(images, one, targets,
                         budget=AutoBudget(0.3, calibration=IDENTITY, merge=False))
        every = model(images, one, targets, render=False).target(0, 0).means.reshape(-1, 3)
    half = every.shape[0] // 2
    assert torch.equal(every[:half], every[half:])  # the twins: view 1's set is view 0's
    # each twin pair becomes one Gaussian (or fewer, with neighbours in one cell)
    assert (merged.aux["rendered"][0] <= kept // 2).all(), (merged.aux["rendered"], kept)
    assert (unmerged.aux["rendered"][0] > kept // 2).all()


def test_auto_is_for_one_scene_at_inference(model):
    coarse, _ = textures()
    images, context, targets = scene(coarse)
    two = [torch.cat([t, t]) for t in (context.extrinsics, context.intrinsics, context.near,
                                        context.far)]
    two_targets = [torch.cat([t, t]) for t in (targets.extrinsics, targets.intrinsics,
                                                targets.near, targets.far)]
    with pytest.raises(ValueError, match="one scene a call"):
        model(torch.cat([images, images]), Cameras(*two), Cameras(*two_targets),
              budget=AutoBudget())
    model.train()
    try:
        with pytest.raises(ValueError, match="call model.eval"):
            model(images, context, targets, budget=AutoBudget())
    finally:
        model.eval()
    with pytest.raises(ValueError, match="measured with rank_by='learned'"):
        model(images, context, targets, budget=AutoBudget(
            calibration=Calibration("learned", ((0.5, 0.0, 1.0, 0.0),), 0.9, "dev")))


def test_a_calibration_of_another_size_is_said_once(model, caplog):
    import logging

    coarse, _ = textures()
    other = Calibration("dither", IDENTITY.fits, 0.9, "dev", size=128)
    caplog.set_level(logging.WARNING, logger="usplat_dr.model.uniquesplat")
    with torch.no_grad():
        for _ in range(2):
            model(*scene(coarse), budget=AutoBudget(10.0, calibration=other))
    said = [r for r in caplog.records if "measured at 128 pixels a side" in r.getMessage()]
    assert len(said) == 1 and "these images are 64" in said[0].getMessage()


def test_predict_chooses_once_and_chunks_render_alike(model, monkeypatch):
    coarse, _ = textures()
    images, context, targets = scene(coarse)
    calls = []
    original = type(model)._auto_budget

    def counted(self, *args, **kwargs):
        calls.append(1)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(type(model), "_auto_budget", counted)
    kwargs = dict(intrinsics=context.intrinsics[0], extrinsics=context.extrinsics[0],
                  target_intrinsics=targets.intrinsics[0],
                  target_extrinsics=targets.extrinsics[0], near=1.0, far=10.0,
                  budget=AutoBudget(0.3, calibration=IDENTITY))
    one = model.predict(images[0], chunk=2, **kwargs)
    assert len(calls) == 1
    two = model.predict(images[0], chunk=1, **kwargs)
    assert len(calls) == 2  # one choice per call, not per chunk
    assert one.auto_keep == two.auto_keep and 0 < one.auto_keep <= 1
    # one or two targets a forward changes the heads' float32 summation order (6e-7 on this
    # scene without any budget): 1e-5 is that noise, far below a budget's change
    assert (one.color - two.color).abs().max() < 1e-5


def test_shipped_models_carry_their_calibration(model):
    assert model.auto_calibration["dither"].data.startswith("outputs/big/test2000")
    budget = load("study/tiny_full_budget")
    assert set(budget.auto_calibration) == {"dither", "learned"}


@pytest.mark.parametrize("name, rankings, size", [
    ("tiny_baseline_budget", {"dither", "learned"}, 64),
    ("tiny_baseline_128", {"dither"}, 128),
    ("tiny_full_128", {"dither"}, 128),
    ("tiny_baseline_budget_128", {"dither", "learned"}, 128)])
def test_the_budget_and_128x128_models_carry_calibrations_at_their_size(name, rankings, size):
    # a 64x64 calibration would be warned about at every 128x128 render; none, logged and
    # uncalibrated: each model holds its own, from the development set at its training size
    found = load(name).auto_calibration
    assert set(found) == rankings
    for calibration in found.values():
        assert calibration.size == size
        folder = "big" if size == 64 else f"big{size}"
        assert calibration.data.startswith(f"outputs/{folder}/test2000")


def test_a_checkpoint_file_of_your_own_carries_its_calibration(tmp_path):
    from usplat_dr.training.checkpoints import CHECKPOINTS

    state = torch.load(CHECKPOINTS / "tiny_baseline.pt", weights_only=True)
    mine = tmp_path / "mine.pt"
    torch.save(state, mine)
    assert load(mine).auto_calibration == {}  # outside checkpoints/: no manifest entry
    cal = Calibration("dither", ((0.5, 0.1, 0.5, 0.2),), 0.9, "my dev set, 40 scenes")
    torch.save({**state, "auto_budget": [cal.as_dict()]}, mine)
    assert load(mine).auto_calibration == {"dither": cal}
    torch.save({**state, "auto_budget": [{"rank_by": "dither"}]}, mine)
    with pytest.raises(ValueError, match="mine.pt'?: auto_budget: not an automatic count's"):
        load(mine)
    torch.save({**state, "auto_budget": [[1, 2]]}, mine)  # a list where a calibration belongs
    with pytest.raises(ValueError, match="auto_budget: not an automatic count's"):
        load(mine)
    torch.save({**state, "auto_budget": [cal.as_dict(), cal.as_dict()]}, mine)
    with pytest.raises(ValueError, match="two calibrations for one ranking"):
        load(mine)
    torch.save({**state, "auto_budget": [cal.as_dict()] * 1000}, mine)
    with pytest.raises(ValueError, match="more than one per ranking"):
        load(mine)
