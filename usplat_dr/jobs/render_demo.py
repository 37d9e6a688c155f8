"""``usplat render-demo``: render a procedural Gaussian scene from several cameras to PNGs."""

import argparse
import logging
import math
import time
from pathlib import Path

import numpy as np
import torch

from usplat_dr.io.images import colorize_depth, grid, save_png
from usplat_dr.jobs.arguments import (
    add_image_shape_option,
    add_square_size_alias,
    out_folder,
    positive_int,
)
from usplat_dr.render import RasterSettings, rasterize
from usplat_dr.render.scenes import covariances_from, orbit_cameras, random_rotations, sh_from_rgb

log = logging.getLogger(__name__)


def demo_gaussians(seed: int = 0) -> dict[str, torch.Tensor]:
    """A small still life: a checkered floor, a rainbow sphere shell with view-dependent sheen,
    and a ring of coloured blobs. About 20k Gaussians; world up is -Y (OpenCV-style)."""
    g = torch.Generator().manual_seed(seed)
    parts = []

    # Floor: a 100 x 100 grid of flat Gaussians at y = 0.8, checkered.
    n = 100
    u = torch.linspace(-2.5, 2.5, n)
    xx, zz = torch.meshgrid(u, u, indexing="xy")
    floor = torch.stack([xx, torch.full_like(xx, 0.8), zz], -1).reshape(-1, 3)
    check = ((torch.floor(xx * 2) + torch.floor(zz * 2)) % 2).reshape(-1, 1)
    rgb = 0.25 + 0.5 * check * torch.tensor([0.9, 0.85, 0.7]) + 0.05 * torch.rand(n * n, 3,
                                                                                generator=g)
    scales = torch.tensor([0.03, 0.004, 0.03]).expand(n * n, 3)
    parts.append((floor, covariances_from(torch.eye(3).expand(n * n, 3, 3), scales), rgb,
                  torch.full((n * n,), 0.95)))

    # Sphere shell: Fibonacci points, coloured by their normal.
    m = 6000
    k = torch.arange(m) + 0.5
    phi = torch.acos(1 - 2 * k / m)
    theta = math.pi * (1 + 5 ** 0.5) * k
    normal = torch.stack([torch.cos(theta) * torch.sin(phi), torch.cos(phi),
                          torch.sin(theta) * torch.sin(phi)], -1)
    centre = torch.tensor([0.0, 0.1, 0.0])
    pts = centre + 0.6 * normal
    rgb = 0.5 + 0.45 * normal
    # Flat discs tangent to the sphere: thin along the normal.
    z = torch.tensor([0.0, 0.0, 1.0]).expand(m, 3)
    t1 = torch.nn.functional.normalize(torch.linalg.cross(normal, z + 0.3 * normal.roll(1, 1)),
                                       dim=-1)
    t2 = torch.linalg.cross(normal, t1)
    rot = torch.stack([t1, t2, normal], -1)
    parts.append((pts, covariances_from(rot, torch.tensor([0.035, 0.035, 0.004]).expand(m, 3)),
                  rgb, torch.full((m,), 0.9)))

    # Ring of blobs.
    b = 400
    ang = torch.rand(b, generator=g) * 2 * math.pi
    rad = 1.3 + 0.15 * torch.randn(b, generator=g)
    blobs = torch.stack([rad * torch.cos(ang), 0.5 + 0.25 * torch.rand(b, generator=g),
                         rad * torch.sin(ang)], -1)
    hue = ang[:, None] / (2 * math.pi) * 6 - torch.tensor([0.0, 2.0, 4.0])
    rgb = torch.clamp(2 - torch.abs((hue % 6) - 3), 0, 1) * 0.8 + 0.1
    scales = torch.empty(b, 3).uniform_(0.02, 0.08, generator=g)
    parts.append((blobs, covariances_from(random_rotations(b, g), scales), rgb,
                  torch.empty(b).uniform_(0.6, 0.95, generator=g)))

    means = torch.cat([p[0] for p in parts])
    covs = torch.cat([p[1] for p in parts])
    rgb = torch.cat([p[2] for p in parts])
    opac = torch.cat([p[3] for p in parts])
    sh = sh_from_rgb(rgb, 1, g, view_dependence=0.15)
    return {"means": means, "covariances": covs, "sh_coefficients": sh, "opacities": opac}


def render_demo(out: Path, image_shape: tuple[int, int] = (256, 256), views: int = 6,
                device: str = "cpu", settings: RasterSettings | None = None) -> list[Path]:
    """Render the demo scene from ``views`` orbiting cameras at ``image_shape`` (H, W); write
    colour, depth and alpha PNGs per view and a contact sheet. Returns the written paths."""
    height, width = image_shape
    dev = torch.device(device)
    scene = {k: v.to(dev) for k, v in demo_gaussians().items()}
    c2w = orbit_cameras(views, radius=3.2, height=1.2, arc_degrees=360.0).to(dev)
    K = torch.tensor([[1.0, 0, 0.5], [0, 1.0, 0.5], [0, 0, 1]], device=dev)
    bg = torch.tensor([0.93, 0.95, 1.0], device=dev)
    written, colors, depths = [], [], []
    g = scene["means"].shape[0]
    log.info("rendering %d Gaussians from %d views at %dx%d on %s", g, views, width, height,
             device)
    for v in range(views):
        t0 = time.perf_counter()
        r = rasterize(c2w[v:v + 1], K[None], torch.tensor([0.1], device=dev),
                      torch.tensor([100.0], device=dev), (height, width), bg[None],
                      scene["means"][None], scene["covariances"][None],
                      scene["sh_coefficients"][None], scene["opacities"][None], settings)
        ms = (time.perf_counter() - t0) * 1e3
        color = r.color[0].permute(1, 2, 0).cpu().numpy()
        alpha = r.alpha[0].cpu().numpy()
        depth = colorize_depth(r.depth[0].cpu().numpy(), alpha)
        written += [save_png(out / f"view{v:02d}_color.png", color),
                    save_png(out / f"view{v:02d}_depth.png", depth),
                    save_png(out / f"view{v:02d}_alpha.png", alpha)]
        colors.append(color)
        depths.append(depth)
        log.info("view %d/%d: %.1f ms, %d tile-Gaussian pairs", v + 1, views, ms,
                 r.aux["num_pairs"])
    written.append(save_png(out / "contact_sheet.png", grid([colors, depths])))
    if not np.isfinite(np.stack(colors)).all():
        raise RuntimeError("the demo rendered non-finite values")
    return written


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=out_folder, default="outputs/render-demo", help="output folder")
    add_image_shape_option(p, [256, 256], "the images' height and width in pixels")
    add_square_size_alias(p)
    p.add_argument("--views", type=positive_int, default=6, help="number of cameras on the orbit")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"],
                   help="cpu: Dr.Jit LLVM backend; cuda: Dr.Jit CUDA backend")


def run(args: argparse.Namespace) -> int:
    paths = render_demo(Path(args.out), image_shape=tuple(args.image_shape), views=args.views,
                        device=args.device)
    print(f"wrote {len(paths)} images to {args.out} (overview: {paths[-1]})")
    return 0
