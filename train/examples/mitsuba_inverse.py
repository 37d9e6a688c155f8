"""Inverse rendering in Mitsuba's own API through the ``usplat_splat`` integrator.

A synthetic scene (rendered by Mitsuba, with known depth) gives training and held-out views.
Gaussians are initialised from the depth of a few training views, with grey colours and
inflated sizes, as a Mitsuba ``ellipsoids`` shape; ``mi.ad.Adam`` then optimises the shape's
``data`` (centres, scales, quaternions), ``opacities`` and ``sh_coeffs`` with the standard
Mitsuba loop (``mi.render`` -> loss -> ``dr.backward`` -> ``opt.step()`` ->
``params.update(opt)``). Prints held-out PSNR before and after and writes renders.

    python train/examples/mitsuba_inverse.py                       # ~1 minute on 2 CPU cores
    python train/examples/mitsuba_inverse.py --kind object --iterations 400 --size 64
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np


def perspective_sensor(c2w_cv: np.ndarray, k: np.ndarray, size: tuple[int, int], near: float,
                       far: float) -> dict:
    """A Mitsuba perspective sensor dict for an OpenCV camera (normalised intrinsics with the
    principal point at the centre and square pixels, as the synthetic sets have)."""
    import mitsuba as mi

    h, w = size
    flip = np.diag([-1.0, -1.0, 1.0, 1.0])  # OpenCV -> Mitsuba camera axes
    fov_x = np.degrees(2 * np.arctan(0.5 / k[0, 0]))
    return {"type": "perspective", "fov": float(fov_x), "fov_axis": "x",
            "near_clip": near, "far_clip": far,
            "to_world": mi.ScalarTransform4f((c2w_cv @ flip).tolist()),
            "film": {"type": "hdrfilm", "width": w, "height": h, "pixel_format": "rgb"}}


def run(kind: str = "indoor", seed: int = 3, size: int = 48, frames: int = 12,
        iterations: int = 150, out: str | Path = "outputs/mitsuba_inverse",
        variant: str = "llvm_ad_rgb", progress: bool = True) -> dict:
    from usplat_dr import plugins  # noqa: I001 (first: finds libLLVM before drjit loads)
    import drjit as dr
    import mitsuba as mi

    mi.set_variant(variant)  # registers usplat_splat for this variant

    from usplat_dr.data.synth import render_spec, scene_record
    from usplat_dr.data.synth.scenes import make_spec
    from usplat_dr.io.images import grid, save_png
    from usplat_dr.training.per_scene import init_from_depth, split_views, views_from_record

    t0 = time.perf_counter()
    spec = make_spec(kind, seed, frames)
    record = scene_record(f"{kind}_{seed}", spec, *render_spec(spec, (size, size), spp=32,
                                                               seed=seed))
    views = views_from_record(record)
    train, held = split_views(len(views.images))

    # ---- the initial Gaussians: depth of every third training view, grey, too large ----
    init = init_from_depth(views, train[::3], stride=2, sh_degree=1)
    n = len(init["means"])
    sh = np.zeros((n, 3, 4))
    shape = plugins.gaussians_to_ellipsoids(
        init["means"], 1.5 * init["log_scales"].exp(), init["quats_xyzw"],
        np.full(n, 0.5), sh, sh_basis="3dgs")
    bg = [float(v) for v in views.background]
    scene = mi.load_dict({"type": "scene", "gaussians": shape,
                          "integrator": {"type": "usplat_splat", "background": bg}})
    sensors = [mi.load_dict(perspective_sensor(views.extrinsics[v].double().numpy(),
                                               views.intrinsics[v].double().numpy(),
                                               (size, size), views.near, views.far))
               for v in range(len(views.images))]
    # the film holds linear RGB; the primitives' colours (and the PNGs) are sRGB
    def tensor_map(f, t):
        return mi.TensorXf(f(t.array), shape=t.shape)

    refs = [tensor_map(mi.math.srgb_to_linear,
                       mi.TensorXf(views.images[v].permute(1, 2, 0).numpy()))
            for v in range(len(views.images))]

    def held_out_psnr() -> tuple[float, list]:
        values, images = [], []
        for v in held:
            img = np.clip(np.array(tensor_map(mi.math.linear_to_srgb,
                                              mi.render(scene, sensor=sensors[v]))), 0, 1)
            gt = views.images[v].permute(1, 2, 0).numpy()
            values.append(-10 * np.log10(np.mean((img - gt) ** 2)))
            images.append(img)
        return float(np.mean(values)), images

    before, before_images = held_out_psnr()

    # ---- the standard Mitsuba optimisation loop ----
    params = mi.traverse(scene)
    keys = ["gaussians.data", "gaussians.opacities", "gaussians.sh_coeffs"]
    opt = mi.ad.Adam(lr=0.01)
    for key in keys:
        opt[key] = params[key]
    extent = float(views.depths[views.depths.isfinite()].median())
    opt.set_learning_rate({"gaussians.data": 2e-4 * extent, "gaussians.opacities": 0.02,
                           "gaussians.sh_coeffs": 0.02})
    params.update(opt)
    losses = []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=iterations, desc="mitsuba inverse", dynamic_ncols=True)
    for it in range(iterations):
        v = train[it % len(train)]
        image = mi.render(scene, params, sensor=sensors[v], seed=it)
        loss = dr.mean(dr.abs(image - refs[v]), axis=None)
        dr.backward(loss)
        opt.step()
        opt["gaussians.opacities"] = dr.clip(opt["gaussians.opacities"], 1e-3, 0.999)
        params.update(opt)
        losses.append(float(loss.array[0]))
        if bar is not None:
            bar.update(1)
            bar.set_postfix(l1=f"{losses[-1]:.4f}")
    if bar is not None:
        bar.close()

    after, after_images = held_out_psnr()
    out = Path(out)
    rows = [[views.images[v].permute(1, 2, 0).numpy(), b, a]
            for v, b, a in zip(held, before_images, after_images)]
    png = save_png(out / f"inverse_{kind}_{seed}.png", grid(rows))
    result = {"scene": f"{kind}_{seed}", "gaussians": n, "iterations": iterations,
              "held_out_views": len(held), "psnr_before": before, "psnr_after": after,
              "first_loss": losses[0] if losses else None,
              "last_loss": losses[-1] if losses else None,
              "seconds": time.perf_counter() - t0, "renders": str(png)}
    from usplat_dr.io import write_json

    write_json(out / f"inverse_{kind}_{seed}.json", result)
    return result


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--kind", default="indoor", choices=["indoor", "outdoor", "object"])
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--size", type=int, default=48)
    p.add_argument("--frames", type=int, default=12)
    p.add_argument("--iterations", type=int, default=150)
    p.add_argument("--variant", default="llvm_ad_rgb", help="or cuda_ad_rgb on a GPU")
    p.add_argument("--out", default="outputs/mitsuba_inverse")
    args = p.parse_args(argv)
    result = run(args.kind, args.seed, args.size, args.frames, args.iterations, args.out,
                 args.variant)
    print(f"{result['scene']}: held-out PSNR {result['psnr_before']:.2f} -> "
          f"{result['psnr_after']:.2f} dB after {result['iterations']} Adam steps on "
          f"{result['gaussians']} Gaussians ({result['seconds']:.0f} s; renders: "
          f"{result['renders']})")
    print(json.dumps({k: v for k, v in result.items() if k != "renders"}))


if __name__ == "__main__":
    main()
