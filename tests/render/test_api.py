"""The rasteriser's entry points: batching, Dr.Jit vs torch, determinism, recompilation, errors."""

import inspect

import drjit as dr
import pytest
import torch

from tests.render.helpers import gradients
from usplat_dr.render import RasterSettings, rasterize, rasterize_drjit
from usplat_dr.render.composite import padded_count
from usplat_dr.render.scenes import isotropic_scene, pixel_aligned_scene, random_scene


def test_batched_call_equals_per_image_calls(device):
    scene = random_scene(200, 20, 28, batch=3, seed=4, sh_degree=2).to(device=device)
    batched = rasterize(*scene.args())
    for b in range(3):
        args = [a[b:b + 1] if isinstance(a, torch.Tensor) else a for a in scene.args()]
        single = rasterize(*args)
        # Same per-pixel lists and arithmetic: identical, not just close.
        for x, y in zip((batched.color, batched.alpha, batched.depth),
                        (single.color, single.alpha, single.depth)):
            assert torch.equal(x[b:b + 1], y)


def test_batched_gradients_equal_per_image_gradients(device):
    s = random_scene(150, 16, 24, batch=2, seed=5).to(device=device)
    g = torch.Generator().manual_seed(0)
    weights = [torch.randn(shape, generator=g).to(device)
               for shape in ((2, 3, 16, 24), (2, 16, 24), (2, 16, 24))]

    def loss(out, w_slice):
        return sum((t * w[w_slice]).sum() for t, w in zip((out.color, out.alpha, out.depth),
                                                          weights))

    cams = (s.extrinsics, s.intrinsics, s.near, s.far)
    leaves = [t.clone().requires_grad_(True)
              for t in (s.means, s.covariances, s.sh_coefficients, s.opacities)]
    loss(rasterize(*cams, s.image_shape, s.background_color, *leaves), slice(None)).backward()
    for b in range(2):
        part = [t.detach()[b:b + 1].clone().requires_grad_(True) for t in leaves]
        out = rasterize(*(c[b:b + 1] for c in cams), s.image_shape,
                        s.background_color[b:b + 1], *part)
        loss(out, slice(b, b + 1)).backward()
        for full, single in zip(leaves, part):
            # Per-Gaussian sums of ~50 terms accumulated by atomic scatter-adds, whose order
            # follows thread scheduling: equal to float32 rounding of the largest terms.
            scale = full.grad.abs().max().item()
            torch.testing.assert_close(full.grad[b:b + 1], single.grad, rtol=0,
                                       atol=1e-5 * scale)


def test_drjit_entry_equals_torch_entry():
    from drjit.llvm.ad import TensorXf

    scene = random_scene(150, 18, 22, batch=2, seed=6, sh_degree=1)
    out_t = rasterize(*scene.args())
    args = [TensorXf(a.numpy()) if isinstance(a, torch.Tensor) else a for a in scene.args()]
    means = args[6]
    dr.enable_grad(means)
    out_d = rasterize_drjit(*args)
    for t, d in zip((out_t.color, out_t.alpha, out_t.depth),
                    (out_d.color, out_d.alpha, out_d.depth)):
        assert torch.equal(t, torch.from_numpy(d.numpy()))
    # Gradients through the Dr.Jit entry equal those through the torch bridge.
    dr.backward(dr.sum(out_d.depth.array))
    m = scene.means.clone().requires_grad_(True)
    o = rasterize(*scene.args()[:6], m, *scene.args()[7:])
    o.depth.sum().backward()
    torch.testing.assert_close(torch.from_numpy(dr.grad(means).numpy()), m.grad, rtol=1e-5,
                               atol=1e-6)  # same kernels; atomic summation order only


def test_drjit_entry_gradients_add_to_other_uses_of_the_inputs():
    # The input gathers' adjoints are plain scatters (ReduceMode.Permute), which overwrite a
    # gradient instead of adding to it: a second term on the same inputs must still count.
    from drjit.llvm.ad import TensorXf

    scene = random_scene(60, 12, 14, batch=1, seed=8, sh_degree=1)
    args = [TensorXf(a.numpy()) if isinstance(a, torch.Tensor) else a for a in scene.args()]
    leaves = args[6:]
    for t in leaves:
        dr.enable_grad(t)
    out = rasterize_drjit(*args)
    dr.backward(dr.sum(out.depth.array))
    alone = [dr.grad(t).numpy().copy() for t in leaves]
    for t in leaves:
        dr.clear_grad(t)
    out = rasterize_drjit(*args)
    extra = sum(dr.sum(t.array * t.array) for t in leaves)  # gradient 2 x
    dr.backward(dr.sum(out.depth.array) + extra)
    for t, g in zip(leaves, alone):
        torch.testing.assert_close(torch.from_numpy(dr.grad(t).numpy()),
                                   torch.from_numpy(g + 2.0 * t.numpy()), rtol=1e-5, atol=1e-5)


def test_repeated_calls_are_deterministic(device):
    scene = pixel_aligned_scene(24, 24, seed=2).to(device=device)
    first = rasterize(*scene.args())
    for _ in range(3):
        again = rasterize(*scene.args())
        assert torch.equal(first.color, again.color)
        assert torch.equal(first.alpha, again.alpha)
        assert torch.equal(first.depth, again.depth)


def test_repeated_gradients_agree_to_summation_order(device):
    # The backward accumulates per-Gaussian gradients with atomic scatter-adds (as the CUDA
    # reference does) or per-thread copies summed afterwards (LLVM's packet records), so the
    # float32 summation order, and the last bits, follow thread scheduling: measured <= 1.3e-7
    # of the largest gradient; 1e-6 bounds it.
    scene = pixel_aligned_scene(32, 32, seed=2)
    first = gradients(scene, rasterize, torch.float32, device)
    for _ in range(2):
        again = gradients(scene, rasterize, torch.float32, device)
        for a, b in zip(first, again):
            torch.testing.assert_close(a, b, rtol=0, atol=1e-6 * b.abs().max().item())


def _kernel_hashes(fn) -> set:
    """Hashes of the JIT kernels ``fn`` launches. Compared across calls rather than reading
    ``cache_hit``, which is also true for kernels loaded from Dr.Jit's on-disk cache: a kernel
    whose IR changed (a baked literal) has a new hash either way."""
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        fn()
        history = dr.kernel_history()
    return {k["hash"] for k in history if k.get("type") == dr.KernelType.JIT}


def _render_fwd_bwd(scene):
    leaves = [t.clone().requires_grad_(True)
              for t in (scene.means, scene.covariances, scene.sh_coefficients, scene.opacities)]
    args = list(scene.args())
    args[6:] = leaves
    out = rasterize(*args)
    (out.color.sum() + out.alpha.sum() + out.depth.sum()).backward()


def test_no_recompilation_for_new_camera_gaussians_or_near_far():
    base = random_scene(200, 24, 24, seed=1)
    _render_fwd_bwd(base)  # first call of this image size: compiles
    reference = _kernel_hashes(lambda: _render_fwd_bwd(base))
    assert len(reference) > 10
    moved = base.to()
    moved.extrinsics[:, :3, 3] += torch.tensor([0.3, -0.1, 0.2])
    assert _kernel_hashes(lambda: _render_fwd_bwd(moved)) == reference, "new camera"
    for g in (317, 1000, 77):
        more = random_scene(g, 24, 24, seed=g)
        assert _kernel_hashes(lambda: _render_fwd_bwd(more)) == reference, f"G = {g}"  # noqa: B023 (called in this iteration)
    # the packet backward bakes its (padded) target size in: counts inside one bucket share
    # the kernels (1,100 and 1,250 both pad to 1,280)
    assert padded_count(1100) == padded_count(1250) == 1280
    in_bucket = _kernel_hashes(lambda: _render_fwd_bwd(random_scene(1100, 24, 24, seed=5)))
    assert _kernel_hashes(lambda: _render_fwd_bwd(random_scene(1250, 24, 24, seed=6))) == in_bucket
    nf = base.to()
    nf.near, nf.far = nf.near * 0.5, nf.far * 3
    nf.background_color = torch.rand(1, 3)
    assert _kernel_hashes(lambda: _render_fwd_bwd(nf)) == reference, "near/far/background"


def test_the_backward_scatter_follows_the_backend():
    assert RasterSettings().resolved_backward_scatter(is_cuda=False) == "packet"
    assert RasterSettings().resolved_backward_scatter(is_cuda=True) == "lanes"
    assert RasterSettings(backward_scatter="lanes").resolved_backward_scatter(False) == "lanes"
    with pytest.raises(ValueError, match="for the LLVM backend"):
        RasterSettings(backward_scatter="packet").resolved_backward_scatter(is_cuda=True)


def test_the_torch_entry_reuses_every_kernel_for_fresh_tensors_of_the_same_shapes():
    # a second call with new tensors (new memory, new values) of the same shapes compiles
    # nothing: the same kernel hashes as the first call's repeat (a data pointer, alignment or
    # value baked into a kernel would change them)
    scene = isotropic_scene(500, 32, sh_degree=3)
    _render_fwd_bwd(scene)  # first call of these shapes: compiles
    first = _kernel_hashes(lambda: _render_fwd_bwd(scene))
    fresh = isotropic_scene(500, 32, sh_degree=3, seed=1)
    assert _kernel_hashes(lambda: _render_fwd_bwd(fresh)) == first


# ---- Invalid input ----
# Under pytest, jaxtyping's import hook checks annotations at run time and would reject some of
# these inputs first (with a TypeCheckError). Users run without it, so test the function as they
# call it.
unchecked_rasterize = inspect.unwrap(rasterize)

def _args():
    return list(random_scene(10, 8, 8, seed=0).args())


NAMES = ["extrinsics", "intrinsics", "near", "far", "image_shape", "background_color", "means",
         "covariances", "sh_coefficients", "opacities"]


@pytest.mark.parametrize("index,value,match", [
    (0, torch.eye(4)[None, :3], r"extrinsics must have shape \(1, 4, 4\)"),
    (1, torch.eye(3)[None, None], r"intrinsics must have shape \(1, 3, 3\)"),
    (2, torch.ones(2), r"near must have shape \(1\)"),
    (4, (8,), "image_shape must be"),
    (4, (0, 8), "image_shape must be"),
    (4, (8.0, 8), "image_shape must be"),
    (5, torch.zeros(1, 4), r"background_color must have shape \(1, 3\)"),
    (6, torch.zeros(1, 10, 2), r"means must have shape \(1, \*, 3\)"),
    (7, torch.zeros(1, 9, 3, 3), r"covariances must have shape \(1, 10, 3, 3\)"),
    (8, torch.zeros(1, 10, 3, 10), "sh_coefficients must have"),
    (9, torch.zeros(1, 11), r"opacities must have shape \(1, 10\)"),
    (6, torch.zeros(1, 10, 3, dtype=torch.float64), "means must have dtype torch.float32"),
    (2, torch.zeros(1), "near must be > 0"),
    (3, torch.full((1,), 0.1), "far must be > near"),
])
def test_invalid_input_raises_naming_the_argument(index, value, match):
    args = _args()
    args[index] = value
    with pytest.raises(ValueError, match=match):
        unchecked_rasterize(*args)


@pytest.mark.parametrize("index", [0, 1, 2, 3, 5, 6, 7, 8, 9])
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_nan_or_inf_raises(index, bad):
    args = _args()
    args[index] = args[index].clone()
    args[index].view(-1)[0] = bad
    with pytest.raises(ValueError, match=f"{NAMES[index]} must be finite"):
        unchecked_rasterize(*args)


def test_not_a_tensor_raises():
    args = _args()
    args[6] = args[6].numpy()
    with pytest.raises(ValueError, match="means must be a torch.Tensor"):
        unchecked_rasterize(*args)


def test_invalid_settings_raise():
    settings = inspect.unwrap(RasterSettings.__init__)
    with pytest.raises(ValueError, match="tile_size"):
        settings(object.__new__(RasterSettings), tile_size=5)
    with pytest.raises(ValueError, match="sh_basis"):
        settings(object.__new__(RasterSettings), sh_basis="e3nn")
    with pytest.raises(ValueError, match="clamp_gradient"):
        settings(object.__new__(RasterSettings), clamp_gradient="straight")


def test_drjit_entry_validates_too():
    from drjit.llvm.ad import TensorXf

    args = [TensorXf(a.numpy()) if isinstance(a, torch.Tensor) else a for a in _args()]
    args[2] = TensorXf([-1.0], shape=(1,))
    with pytest.raises(ValueError, match="near must be > 0"):
        rasterize_drjit(*args)
    args = [TensorXf(a.numpy()) if isinstance(a, torch.Tensor) else a for a in _args()]
    args[6] = TensorXf([float("nan")] * 30, shape=(1, 10, 3))
    with pytest.raises(ValueError, match="means must be finite"):
        rasterize_drjit(*args)
