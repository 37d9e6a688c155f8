"""Overhead of the Mitsuba plugin over calling the rasteriser directly.

Renders the same Gaussians from the same camera three ways, interleaved round by round:
``rasterize_drjit`` on Dr.Jit tensors (the baseline), ``mi.render`` through ``usplat_splat``
(reading the ellipsoids shape, building covariances, the [H, W, C] film layout and the
sRGB-to-linear conversion), and the torch API ``rasterize``. Forward only, and forward +
backward (``dr.backward`` through ``mi.render`` against the torch API's ``backward``). Prints
median wall and process CPU time (``usplat_dr.evaluation.timing.interleaved``: one warm-up
round, then the order reversed every other round) and the ratio to the baseline measured in
the same run, under a line naming the machine.

    python train/bench/plugin.py                   # 20k Gaussians, 256x256, 7 rounds
    python train/bench/plugin.py --gaussians 100000 --size 512
"""

import argparse
from functools import partial

import numpy as np


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--gaussians", type=int, default=20000)
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--rounds", type=int, default=7)
    p.add_argument("--variant", default="llvm_ad_rgb")
    args = p.parse_args()

    from usplat_dr import plugins  # noqa: I001 (first: finds libLLVM before drjit loads)
    import drjit as dr
    import mitsuba as mi
    import torch

    mi.set_variant(args.variant)

    from usplat_dr.evaluation.timing import interleaved, machine_line
    from usplat_dr.render import rasterize
    from usplat_dr.render.pipeline import rasterize_drjit

    rng = np.random.default_rng(0)
    n, s = args.gaussians, args.size
    g = {"means": rng.normal(size=(n, 3)) * [1.0, 1.0, 0.6], "scales": np.exp(
        rng.normal(size=(n, 3)) * 0.3 - 3.5), "quats": rng.normal(size=(n, 4)),
         "opacities": rng.uniform(0.2, 0.9, n), "sh": rng.normal(size=(n, 3, 16)) * 0.3}
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "usplat_splat", "srgb_primitives": False},
        "sensor": {"type": "perspective", "fov": 50, "near_clip": 0.5, "far_clip": 100.0,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0],
                                                              up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": s, "height": s}},
        "gaussians": plugins.gaussians_to_ellipsoids(g["means"], g["scales"], g["quats"],
                                                     g["opacities"], g["sh"], sh_basis="3dgs")})
    sensor = scene.sensors()[0]
    cam = plugins.sensor_camera(sensor)
    tg = plugins.ellipsoids_to_gaussians(scene.shapes()[0])
    T = mi.TensorXf

    def dr_args():
        return (T(mi.Float(cam["extrinsics"].astype(np.float32).ravel()), shape=(1, 4, 4)),
                T(mi.Float(cam["intrinsics"].astype(np.float32).ravel()), shape=(1, 3, 3)),
                T(mi.Float([cam["near"]]), shape=(1,)), T(mi.Float([cam["far"]]), shape=(1,)),
                (s, s), T(dr.zeros(mi.Float, 3), shape=(1, 3)),
                T(mi.Float(tg["means"].numpy().ravel()), shape=(1, n, 3)),
                T(mi.Float(tg["covariances"].numpy().ravel()), shape=(1, n, 3, 3)),
                T(mi.Float(tg["harmonics"].numpy().ravel()), shape=(1, n, 3, 16)),
                T(mi.Float(tg["opacities"].numpy().ravel()), shape=(1, n)))

    torch_args = (torch.tensor(cam["extrinsics"], dtype=torch.float32)[None],
                  torch.tensor(cam["intrinsics"], dtype=torch.float32)[None],
                  torch.tensor([cam["near"]]), torch.tensor([cam["far"]]), (s, s),
                  torch.zeros(1, 3), tg["means"][None], tg["covariances"][None],
                  tg["harmonics"][None], tg["opacities"][None])
    params = mi.traverse(scene)
    keys = ["gaussians.data", "gaussians.opacities", "gaussians.sh_coeffs"]

    def direct(backward):
        a = dr_args()
        if backward:
            for t in a[6:]:
                dr.enable_grad(t)
        out = rasterize_drjit(*a)
        if backward:
            dr.backward(dr.sum(out.color, axis=None))
            dr.eval(dr.grad(a[6]))
        else:
            dr.eval(out.color)

    def plugin(backward):
        if backward:
            for k in keys:
                dr.enable_grad(params[k])
            params.update()
            image = mi.render(scene, params)
            dr.backward(dr.sum(image, axis=None))
            dr.eval(dr.grad(params["gaussians.data"]))
            for k in keys:
                dr.disable_grad(params[k])
            params.update()
        else:
            dr.eval(mi.render(scene))

    def torch_api(backward):
        if backward:
            leaves = [t.clone().requires_grad_(True) for t in torch_args[6:]]
            out = rasterize(*torch_args[:6], *leaves)
            out.color.sum().backward()
        else:
            with torch.no_grad():
                rasterize(*torch_args)

    ways = {"rasterize_drjit (baseline)": direct, "mi.render + usplat_splat": plugin,
            "torch rasterize": torch_api}
    print(machine_line())
    for backward in (False, True):
        times = interleaved({name: partial(f, backward) for name, f in ways.items()},
                            args.rounds, warmup=1)  # the warm-up round compiles the kernels
        base = times["rasterize_drjit (baseline)"]
        print(f"\n{'forward + backward' if backward else 'forward'}: {n} Gaussians, {s}x{s}, "
              f"median of {args.rounds} interleaved rounds")
        for name, t in times.items():
            print(f"  {name:28s} wall {t.wall:8.1f} ms ({t.wall / base.wall:.2f}x)   "
                  f"CPU {t.cpu:8.1f} ms ({t.cpu / base.cpu:.2f}x)")


if __name__ == "__main__":
    main()
