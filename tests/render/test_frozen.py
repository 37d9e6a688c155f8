"""Fixed-capacity binning and the recorded forward (``dr.freeze``): the images of the traced
render, bit for bit, whatever the capacity, the shapes or the order of calls."""

import inspect

import drjit as dr
import pytest
import torch
from drjit.llvm.ad import TensorXf

from usplat_dr.render import RasterSettings, rasterize, rasterize_drjit
from usplat_dr.render.frozen import FrozenForward
from usplat_dr.render.scenes import isotropic_scene, pixel_aligned_scene, random_scene


def _tensors(scene):
    return [TensorXf(a.contiguous().numpy()) if isinstance(a, torch.Tensor) else a
            for a in scene.args()]


def _images(out):
    return [torch.from_numpy(t.numpy()) for t in (out.color, out.alpha, out.depth)]


def _assert_same(a, b):
    # The same pairs in the same order through the same arithmetic: identical, not close.
    for x, y in zip(a, b):
        assert torch.equal(x, y)


@pytest.mark.parametrize("tile_size", [4, 8, 16])
def test_fixed_capacity_renders_the_exact_images(tile_size):
    scene = random_scene(300, 20, 28, batch=2, seed=3, sh_degree=2)
    settings = RasterSettings(tile_size=tile_size)
    args = _tensors(scene)
    exact = rasterize_drjit(*args, settings)
    needed = exact.aux["pairs_needed"]
    assert exact.aux["num_pairs"] > 0 and needed >= exact.aux["num_pairs"]
    for capacity in (needed, needed + 1, 3 * needed + 17):
        fixed = rasterize_drjit(*args, settings, pair_capacity=capacity)
        _assert_same(_images(fixed), _images(exact))
        assert int(fixed.aux["pairs_needed"][0]) == needed
        assert int(fixed.aux["pairs_kept"][0]) == exact.aux["num_pairs"]
        assert not fixed.aux["overflow"][0]
    short = rasterize_drjit(*args, settings, pair_capacity=needed - 1)
    assert short.aux["overflow"][0] and int(short.aux["pairs_needed"][0]) == needed
    # gradients through the fixed-capacity render are the exact render's
    grads = []
    for capacity in (None, 2 * needed):
        leaves = [TensorXf(t) for t in args[6:]]
        for t in leaves:
            dr.enable_grad(t)
        out = rasterize_drjit(*args[:6], *leaves, settings, pair_capacity=capacity)
        dr.backward(dr.sum(out.color.array) + dr.sum(out.depth.array))
        grads.append([dr.grad(t).numpy() for t in leaves])
    for a, b in zip(*grads):
        # the same terms; the packet backward's per-thread sums may add them in another order
        assert abs(a - b).max() <= 1e-5 * abs(a).max()
    unchecked = inspect.unwrap(rasterize_drjit)  # as users call it (jaxtyping's hook aside)
    for bad in (0, -3, 2.5, True, 2 ** 24):
        with pytest.raises(ValueError, match="pair_capacity"):
            unchecked(*args, settings, pair_capacity=bad)


def test_fixed_capacity_reads_nothing_back_so_the_render_can_be_recorded():
    args = _tensors(pixel_aligned_scene(16, 16, seed=1))

    def render(capacity, *t):
        out = rasterize_drjit(*t, check=False, pair_capacity=capacity)
        return out.color, out.aux["overflow"]

    frozen = dr.freeze(render)
    color, overflow = frozen(10_000, *args)
    assert not overflow[0]
    _assert_same([torch.from_numpy(color.numpy())], _images(rasterize_drjit(*args))[:1])
    # the exact-size binning reads its pair counts back, which recording refuses
    with pytest.raises(RuntimeError):
        dr.freeze(render)(None, *args)


def test_frozen_forward_replays_and_matches_the_traced_render():
    frozen = FrozenForward((24, 24))
    first = isotropic_scene(400, 24, sh_degree=1, seed=0)
    traced = _images(rasterize_drjit(*_tensors(first)))
    out = frozen(*_tensors(first)[:4], *_tensors(first)[5:])  # traced, measures the capacity
    _assert_same([torch.from_numpy(t.numpy()) for t in out[:3]], traced)
    assert frozen.recordings == 0
    for seed in (0, 1, 2):  # fresh tensors, same shapes: one recording, then replays
        scene = isotropic_scene(400, 24, sh_degree=1, seed=seed)
        # cameras, near plane and background are inputs of the recording, not baked into it
        scene.extrinsics[:, :3, 3] += torch.tensor([0.05, -0.03, 0.1]) * seed
        scene.intrinsics[:, 0, 0] *= 1.0 + 0.1 * seed
        scene.near = scene.near * (1.0 + seed)
        scene.background_color = torch.full_like(scene.background_color, 0.2 * seed)
        t = _tensors(scene)
        out = frozen(*t[:4], *t[5:])
        _assert_same([torch.from_numpy(x.numpy()) for x in out[:3]],
                     _images(rasterize_drjit(*t)))
        assert out[4] == rasterize_drjit(*t).aux["num_pairs"]
    assert frozen.recordings == 1
    # another Gaussian count is another shape: traced, then recorded anew (a replay of the
    # first recording would use its baked-in widths)
    other = _tensors(isotropic_scene(250, 24, sh_degree=1, seed=5))
    for _ in range(2):
        out = frozen(*other[:4], *other[5:])
        _assert_same([torch.from_numpy(x.numpy()) for x in out[:3]],
                     _images(rasterize_drjit(*other)))
    assert frozen.recordings == 2


def test_frozen_forward_grows_its_capacity_when_a_scene_needs_more_pairs():
    frozen = FrozenForward((24, 24))
    small = _tensors(isotropic_scene(400, 24, seed=0))
    frozen(*small[:4], *small[5:])
    key = next(iter(frozen.capacity))
    # a scene of the same shapes with ten times the radius per Gaussian needs more lanes
    big_scene = isotropic_scene(400, 24, seed=0)
    big_scene.covariances = big_scene.covariances * 100.0
    big = _tensors(big_scene)
    needed = rasterize_drjit(*big).aux["pairs_needed"]
    assert needed > frozen.capacity[key]
    out = frozen(*big[:4], *big[5:])
    _assert_same([torch.from_numpy(x.numpy()) for x in out[:3]], _images(rasterize_drjit(*big)))
    assert frozen.capacity[key] >= needed


def test_frozen_forward_traces_every_call_once_it_has_recorded_too_often(monkeypatch):
    from usplat_dr.render import frozen as module

    monkeypatch.setattr(module, "MAX_TOTAL_RECORDINGS", 2)
    frozen = FrozenForward((16, 16))
    for n in (30, 40, 50, 30, 40, 50):  # three shapes: two recorded, then traced
        t = _tensors(isotropic_scene(n, 16, seed=n))
        for _ in range(2):
            out = frozen(*t[:4], *t[5:])
            _assert_same([torch.from_numpy(x.numpy()) for x in out[:3]],
                         _images(rasterize_drjit(*t)))
    assert frozen.recordings == 2 and frozen.gave_up


def test_frozen_forward_refuses_gradients_and_empty_scenes():
    t = _tensors(isotropic_scene(50, 16, seed=0))
    frozen = FrozenForward((16, 16))
    dr.enable_grad(t[6])
    with pytest.raises(ValueError, match="without gradients"):
        frozen(*t[:4], *t[5:])
    empty = _tensors(isotropic_scene(50, 16, seed=0))
    empty[6:] = [TensorXf(dr.zeros(type(x.array), 0), shape=(1, 0, *x.shape[2:]))
                 for x in empty[6:]]
    with pytest.raises(ValueError, match="at least one Gaussian"):
        frozen(*empty[:4], *empty[5:])


def test_the_torch_entry_without_gradients_equals_the_traced_forward():
    settings_frozen, settings_traced = RasterSettings(freeze_forward=True), RasterSettings()
    assert not settings_traced.freeze_forward  # opt-in
    for seed in (0, 1, 2):  # traced, recorded, replayed
        scene = random_scene(200, 20, 20, batch=2, seed=seed)
        with torch.no_grad():
            a = rasterize(*scene.args(), settings_frozen)
            b = rasterize(*scene.args(), settings_traced)
        _assert_same((a.color, a.alpha, a.depth), (b.color, b.alpha, b.depth))
        assert a.aux["num_pairs"] == b.aux["num_pairs"]
        assert torch.equal(a.aux["radii"], b.aux["radii"])
    # unwrapped: under pytest jaxtyping's hook would reject the string first (as in test_api)
    init = inspect.unwrap(RasterSettings.__init__)
    with pytest.raises(ValueError, match="freeze_forward"):
        init(object.__new__(RasterSettings), freeze_forward="yes")
