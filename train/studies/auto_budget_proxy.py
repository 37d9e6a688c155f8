"""Can a scene's Gaussian count be chosen without its target images? The context-view proxy
(train/studies/README.md, "An automatic count: the context-view proxy").

Per held-out scene and budget (a fraction of the Gaussians, ranked by ``--rank-by``): the
proxy loss, PSNR of the context views rendered with all Gaussians minus with the budget (the
context views' own images as the reference; what an automatic count could compute at
inference), beside the real loss, the same on the target views against their images. An
automatic count picks, per scene, the smallest budget whose proxy loss is within a tolerance;
the study prints, per tolerance, the mean budget kept and the mean and worst real loss.

    python train/studies/auto_budget_proxy.py --checkpoint tiny_full --rank-by dither \\
        --data outputs/big/test5000 --scenes 20 --out outputs/auto_budget

Writes ``proxy.csv`` (one row per scene and budget) and ``summary.json``.
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
from usplat_dr.io import atomic_open, write_json
from usplat_dr.model.budget import RANKINGS, GaussianBudget
from usplat_dr.model.uniquesplat import StudyHooks
from usplat_dr.training.checkpoints import load

KEEPS = (0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.7)
TOLERANCES = (0.1, 0.2, 0.3, 0.5, 1.0)
FIELDS = ("scene", "keep", "proxy_loss", "real_loss")


def losses(model, x, targets_image, keeps, rank_by: str) -> dict:
    """{keep: (proxy loss, real loss)} of one scene (dB; 0 at keep 1)."""
    enc = model.encode(x.images, x.context.extrinsics, x.context.intrinsics, x.context.near,
                       x.context.far)
    hooks = StudyHooks(encoding=enc)

    def mean_psnr(cameras, reference, budget=None):
        out = model(x.images, x.context, cameras, hooks=hooks, budget=budget)
        return float(psnr(out.color.clamp(0, 1), reference).mean())

    context_all = mean_psnr(x.context, x.images)
    target_all = mean_psnr(x.targets, targets_image)
    found = {1.0: (0.0, 0.0)}
    for keep in keeps:
        budget = GaussianBudget(keep, rank_by=rank_by)
        found[keep] = (context_all - mean_psnr(x.context, x.images, budget),
                       target_all - mean_psnr(x.targets, targets_image, budget))
    return found


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", default="tiny_full", help="a shipped name or a file")
    p.add_argument("--rank-by", default="dither", choices=RANKINGS, help="the budget's ranking")
    p.add_argument("--data", required=True, help="held-out synthetic set (usplat synth)")
    p.add_argument("--scenes", type=int, default=20, help="first scenes of the standard split")
    p.add_argument("--size", type=int, default=64, help="image size (the model's training size)")
    p.add_argument("--threads", type=int, default=1, help="torch threads")
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    model = load(args.checkpoint).eval()
    dataset, index, scenes = held_out_scenes(args.data, count=args.scenes, size=args.size)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    per_scene = {}
    for scene in scenes:
        batch = load_example(dataset, index, scene)
        with torch.no_grad():
            per_scene[scene] = losses(model, model_inputs(batch, "cpu"),
                                      batch["target"]["image"], KEEPS, args.rank_by)
        print(scene, " ".join(f"{k:g}: {v[0]:.2f}/{v[1]:.2f}" for k, v in
                              sorted(per_scene[scene].items())), flush=True)
    with atomic_open(out / "proxy.csv", "w") as f:
        writer = csv.DictWriter(f, FIELDS)
        writer.writeheader()
        for scene, found in per_scene.items():
            for keep, (proxy, real) in sorted(found.items()):
                writer.writerow({"scene": scene, "keep": keep, "proxy_loss": proxy,
                                 "real_loss": real})
    summary = {}
    print("\n| tolerance (proxy, dB) | mean kept | mean real loss, dB | worst scene, dB |\n"
          "|---|---|---|---|")
    for tol in TOLERANCES:
        chosen = {s: min(k for k, v in found.items() if v[0] <= tol)
                  for s, found in per_scene.items()}
        real = [per_scene[s][k][1] for s, k in chosen.items()]
        summary[str(tol)] = {"mean_kept": statistics.mean(chosen.values()),
                             "mean_loss_db": statistics.mean(real), "worst_db": max(real)}
        print(f"| {tol:g} | {summary[str(tol)]['mean_kept']:.0%} | "
              f"{summary[str(tol)]['mean_loss_db']:+.2f} | {max(real):+.2f} |")
    print("\n| kept | mean proxy loss, dB | mean real loss, dB |\n|---|---|---|")
    for keep in KEEPS:
        proxy = statistics.mean(f[keep][0] for f in per_scene.values())
        real = statistics.mean(f[keep][1] for f in per_scene.values())
        summary[f"keep {keep:g}"] = {"proxy_db": proxy, "real_db": real}
        print(f"| {keep:.0%} | {proxy:+.2f} | {real:+.2f} |")
    write_json(out / "summary.json", {"checkpoint": args.checkpoint, "rank_by": args.rank_by,
                                      "data": args.data, "rows": summary})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
