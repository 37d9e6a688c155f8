"""Merge, then drop: does merging the two context views' copies of a surface before a Gaussian
budget beat dropping alone? (train/studies/LOG.md, "Merge, then drop").

The rule, per target set of a pixel-aligned model with two context views and one Gaussian per
pixel: each Gaussian of view 0 projects into view 1 (the context cameras); the view-1
Gaussian at that pixel is its candidate, kept when the pair is mutual (the candidate projects
back within one pixel of the first one's pixel, each axis), when the two describe the same
surface (Mahalanobis distance of their means under the sum of their covariances at most
``--chi2``), and when no other view-0 Gaussian claims the same candidate at a smaller
distance. Each pair is moment-matched into the view-0 slot (opacity-weighted mean, covariance
with the spread of the two means, SH; opacity ``1 - (1 - o1)(1 - o2)``, the coverage of the
two: the merge rule of ``render/prune.py``), and the view-1 slot is emptied. The budget then
ranks what remains with the dither rule (``rank_by="dither"``, its coverage-rule adaptation;
an emptied slot is never kept and counts as covered in the kept fraction around a Gaussian).
Compared with the dither rule on the unmerged Gaussians, at each ``--keeps`` fraction of all
G, PSNR against all Gaussians, per scene of the held-out set's standard split.

    python train/studies/merge_then_drop.py --checkpoint tiny_full \\
        --data outputs/big/test5000 --scenes 20 --chi2 9 1000 --out outputs/merge_then_drop

Writes ``merge.csv`` (one row per scene, chi2 and budget) and ``summary.json`` (means with 95%
t intervals over scenes) and prints the table.
"""

import argparse
import csv
import statistics
from pathlib import Path

import torch

import usplat_dr  # noqa: F401  (libLLVM first)
from usplat_dr.data.types import model_inputs
from usplat_dr.evaluation import held_out_scenes, load_example
from usplat_dr.evaluation.metrics import psnr
from usplat_dr.evaluation.verdict import t_interval
from usplat_dr.io import atomic_open, write_json
from usplat_dr.model.budget import (
    LOCAL_WINDOW,
    adapt,
    budget_count,
    coverage_rule,
    dither_offsets,
    local_fraction,
    ranking_scores,
    take,
    top_k,
)
from usplat_dr.model.types import Gaussians
from usplat_dr.render.prune import moment_match
from usplat_dr.training.loader import load

KEEPS = (0.5, 0.3, 0.1)
FIELDS = ("scene", "chi2", "keep", "merged_fraction", "psnr_all", "psnr_merged", "psnr_dither",
          "psnr_merge_dither")
GAUSSIAN_FIELDS = ("means", "covariances", "harmonics", "opacities", "scales", "rotations")


def _project(points, w2c, intrinsics, h: int, w: int):
    """Pixel index (row-major), row, column and in-image flag of world ``points`` [S, N, 3]
    seen by cameras ``w2c`` [S, 4, 4] (world to camera, OpenCV) with normalised
    ``intrinsics`` [S, 3, 3]."""
    cam = points @ w2c[:, :3, :3].transpose(-1, -2) + w2c[:, None, :3, 3]
    z = cam[..., 2]
    uv = ((cam[..., :2] / z[..., None].clamp(min=1e-6)) @ intrinsics[:, :2, :2].transpose(-1, -2)
          + intrinsics[:, None, :2, 2])
    col, row = torch.floor(uv[..., 0] * w).long(), torch.floor(uv[..., 1] * h).long()
    inside = (z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    return row.clamp(0, h - 1) * w + col.clamp(0, w - 1), row, col, inside


def match_views(means, covariances, extrinsics, intrinsics, h: int, w: int, chi2: float):
    """For each view-0 Gaussian [S, H W]: its view-1 partner's pixel index and whether the pair
    merges (see the module docstring). ``means`` [S, 2 H W, 3], ``covariances`` [S, 2 H W, 3,
    3]; ``extrinsics`` [S, 2, 4, 4] camera-to-world, ``intrinsics`` [S, 2, 3, 3] normalised."""
    hw = h * w
    m, c = means.view(-1, 2, hw, 3), covariances.view(-1, 2, hw, 3, 3)
    w2c = torch.linalg.inv(extrinsics)
    partner, _, _, ok0 = _project(m[:, 0], w2c[:, 1], intrinsics[:, 1], h, w)
    m1 = torch.gather(m[:, 1], 1, partner[..., None].expand(-1, -1, 3))
    _, row, col, ok1 = _project(m1, w2c[:, 0], intrinsics[:, 0], h, w)
    pixel = torch.arange(hw, device=means.device)
    mutual = (ok0 & ok1 & ((row - pixel // w).abs() <= 1) & ((col - pixel % w).abs() <= 1))
    c1 = torch.gather(c[:, 1], 1, partner[..., None, None].expand(-1, -1, 3, 3))
    d = m1 - m[:, 0]
    distance = (d[..., None, :] @ torch.linalg.solve(c[:, 0] + c1, d[..., None]))[..., 0, 0]
    same = mutual & (distance <= chi2)
    closest = torch.full_like(distance, float("inf")).scatter_reduce(
        1, partner, torch.where(same, distance, torch.full_like(distance, float("inf"))), "amin")
    return partner, same & (distance <= torch.gather(closest, 1, partner))


def merge_pairs(g: Gaussians, partner, same) -> tuple[Gaussians, torch.Tensor]:
    """The Gaussians with each merging pair moment-matched into its view-0 slot (the merge rule
    of pruning, ``render.prune.moment_match``) and the view-1 slot emptied (opacity 0, its other
    values kept), and the mask of the emptied slots [S, G]."""
    s, g_total = g.opacities.shape
    hw = partner.shape[1]
    slots = torch.arange(g_total, device=partner.device).expand(s, g_total)
    own = torch.arange(hw, device=partner.device).expand(s, hw)
    emptied = torch.zeros_like(g.opacities, dtype=torch.bool).scatter_(1, hw + partner, same)
    group = slots.clone()  # one group per slot; a merged partner joins its view-0 Gaussian's
    rows = torch.arange(s, device=partner.device)[:, None].expand(s, hw)
    group[rows[same], hw + partner[same]] = own[same]
    flat = (group + g_total * torch.arange(s, device=group.device)[:, None]).reshape(-1)
    merged = moment_match(flat, s * g_total, g.means.reshape(-1, 3),
                          g.covariances.reshape(-1, 3, 3),
                          g.harmonics.reshape(-1, *g.harmonics.shape[2:]),
                          g.opacities.reshape(-1))
    survivor = torch.zeros_like(emptied)
    survivor[:, :hw] = same  # only merged slots change; every other Gaussian stays bit for bit
    out = {}
    for name in GAUSSIAN_FIELDS:
        x = getattr(g, name)
        if name in merged:
            mask = survivor.view(*survivor.shape, *(1,) * (x.dim() - 2))
            x = torch.where(mask, merged[name].view_as(x), x)
        out[name] = x
    out["opacities"] = torch.where(emptied, torch.zeros_like(out["opacities"]),
                                   out["opacities"])
    return Gaussians(**out), emptied


def dither_budget(g: Gaussians, keep: float, layout, emptied) -> Gaussians:
    """The dither rule's K of ``g`` (``model/budget.py``), an emptied slot never kept and
    counted as covered in the kept fraction around each Gaussian."""
    k = budget_count(keep, g.opacities.shape[1])
    scores = ranking_scores("dither", g.opacities, None, dither_offsets(*layout))
    scores = torch.where(emptied, torch.full_like(scores, -float("inf")), scores)
    index, _ = top_k(scores, k)
    kept = torch.zeros_like(emptied).scatter_(1, index, True)
    log_local = local_fraction(kept | emptied, layout).clamp(min=1 / LOCAL_WINDOW**2).log()
    chosen = Gaussians(**{name: take(getattr(g, name), index) for name in GAUSSIAN_FIELDS})
    return adapt(chosen, *coverage_rule(take(log_local, index)))


def rendered_psnr(model, pred, gaussians: Gaussians, targets, target) -> float:
    """Mean PSNR over the targets of ``gaussians`` rendered in place of ``pred``'s."""
    pred.gaussians = gaussians
    model.render_targets(pred, targets, tuple(target.shape[-2:]))
    return float(psnr(pred.color.clamp(0, 1), target).mean())


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", default="tiny_full", help="a shipped name or a file")
    p.add_argument("--data", required=True, help="held-out synthetic set (usplat synth)")
    p.add_argument("--scenes", type=int, default=20, help="first scenes of the standard split")
    p.add_argument("--chi2", type=float, nargs="+", default=[9.0],
                   help="Mahalanobis bound of a pair describing one surface")
    p.add_argument("--keeps", type=float, nargs="+", default=list(KEEPS),
                   help="budgets: fractions of the Gaussians kept")
    p.add_argument("--size", type=int, default=64, help="image size (the model's training size)")
    p.add_argument("--threads", type=int, default=1, help="torch threads")
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    model = load(args.checkpoint).eval()
    dataset, index, scenes = held_out_scenes(args.data, count=args.scenes, size=args.size)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for scene in scenes:
        batch = load_example(dataset, index, scene)
        x = model_inputs(batch, "cpu")
        target = batch["target"]["image"]
        h, w = x.images.shape[-2:]
        layout = (2, h, w, 1)
        with torch.no_grad():
            pred = model(x.images, x.context, x.targets)

            g = pred.gaussians

            def score(gaussians, pred=pred, targets=x.targets, target=target):
                return rendered_psnr(model, pred, gaussians, targets, target)

            n = g.means.shape[0] // x.images.shape[0]
            ext = x.context.extrinsics.repeat_interleave(n, 0)
            intr = x.context.intrinsics.repeat_interleave(n, 0)
            none = torch.zeros_like(g.opacities, dtype=torch.bool)
            every = score(g)
            dither = {keep: score(dither_budget(g, keep, layout, none)) for keep in args.keeps}
            for chi2 in args.chi2:
                partner, same = match_views(g.means.float(), g.covariances.float(), ext, intr,
                                            h, w, chi2)
                merged, emptied = merge_pairs(g, partner, same)
                merged_psnr = score(merged)
                for keep in args.keeps:
                    rows.append({"scene": scene, "chi2": chi2, "keep": keep,
                                 "merged_fraction": float(emptied.float().mean()),
                                 "psnr_all": every, "psnr_merged": merged_psnr,
                                 "psnr_dither": dither[keep],
                                 "psnr_merge_dither": score(dither_budget(merged, keep, layout,
                                                                          emptied))})
        print(f"{scene}: {rows[-1]['merged_fraction']:.1%} merged (chi2 {args.chi2[-1]:g})",
              flush=True)
    with atomic_open(out / "merge.csv", "w") as f:
        writer = csv.DictWriter(f, FIELDS)
        writer.writeheader()
        writer.writerows(rows)
    summary = {}
    print("\n| chi2 | kept | merged away | merge alone, dB | dither, dB | merge then dither, dB "
          "| difference, dB [95% t] |\n|---|---|---|---|---|---|---|")
    for chi2 in args.chi2:
        for keep in args.keeps:
            sel = [r for r in rows if r["chi2"] == chi2 and r["keep"] == keep]
            diff = [r["psnr_merge_dither"] - r["psnr_dither"] for r in sel]
            low, high = t_interval(diff)
            entry = {"scenes": len(sel),
                     "merged_fraction": statistics.mean(r["merged_fraction"] for r in sel),
                     "merge_alone_db": statistics.mean(r["psnr_merged"] - r["psnr_all"]
                                                       for r in sel),
                     "dither_db": statistics.mean(r["psnr_dither"] - r["psnr_all"] for r in sel),
                     "merge_dither_db": statistics.mean(r["psnr_merge_dither"] - r["psnr_all"]
                                                        for r in sel),
                     "difference_db": statistics.mean(diff), "low": low, "high": high}
            summary[f"{chi2:g}/{keep:g}"] = entry
            print(f"| {chi2:g} | {keep:.0%} | {entry['merged_fraction']:.1%} | "
                  f"{entry['merge_alone_db']:+.3f} | {entry['dither_db']:+.2f} | "
                  f"{entry['merge_dither_db']:+.2f} | {entry['difference_db']:+.2f} "
                  f"[{low:+.2f}, {high:+.2f}] |")
    write_json(out / "summary.json", {"checkpoint": args.checkpoint, "data": args.data,
                                      "rows": summary})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
