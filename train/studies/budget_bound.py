"""What K Gaussians can reach at all: the bound that the learned Gaussian budget is judged by
(train/studies/LOG.md, "The bound of a Gaussian budget").

For each held-out scene and target view, the model predicts the target's Gaussians, all of
them and K of them by ``--rank-by`` (the feed-forward budget, adapted as at inference); then
every parameter of those Gaussians (means, covariances, opacities, SH) is optimised on that
target's own image, the per-scene fitting's loss and learning rates
(``usplat_dr.training.per_scene``: 0.8 L1 + 0.2 (1 - SSIM), Adam), starting from the
prediction. The bound's loss at K is PSNR(fitted, all) - PSNR(fitted, K): what keeping K costs
when the Gaussians may move; the feed-forward loss at K is PSNR(predicted, all) -
PSNR(predicted, K). Both in sample on the target image (the fit sees it): the bound is what
any K Gaussians of this scene can show of that view.

    python train/studies/budget_bound.py --checkpoint tiny_full_budget \\
        --data outputs/big/test5000 --scenes 20 --steps 300 --out outputs/budget_bound

Writes ``bound.csv`` (one row per scene, target and setting), ``summary.json`` (per K: the two
losses and their difference, mean over scenes with a 95% t interval) and ``bound.png``, and
prints the table. Resumes: scenes already in ``bound.csv`` are skipped.
"""

import argparse
import csv
import json
import statistics
from pathlib import Path

import torch

import usplat_dr  # noqa: F401  (libLLVM first)
from usplat_dr.data.chunks import read_chunk, read_index
from usplat_dr.data.dataset import dataset_from_section
from usplat_dr.data.types import model_inputs
from usplat_dr.evaluation import synthetic_indices
from usplat_dr.evaluation.metrics import psnr, ssim_torch
from usplat_dr.evaluation.verdict import t_interval
from usplat_dr.geometry.cameras import Cameras
from usplat_dr.io import atomic_open, write_json
from usplat_dr.model.budget import RANKINGS, GaussianBudget
from usplat_dr.model.types import Gaussians
from usplat_dr.model.uniquesplat import StudyHooks
from usplat_dr.training.loader import load
from usplat_dr.training.per_scene import FitCfg, views_from_record

#: The budgets of the study (fractions of a target's Gaussians), largest first.
KEEPS = (0.5, 0.3, 0.1, 0.05)
FIELDS = ("scene", "target", "keep", "kept", "psnr_predicted", "psnr_fitted")
GAUSSIAN_FIELDS = ("means", "covariances", "harmonics", "opacities", "scales", "rotations")
CAMERA_FIELDS = ("extrinsics", "intrinsics", "near", "far")


def fit_gaussians(model, g: Gaussians, fit_cams: Cameras, fit_images: torch.Tensor,
                  score_cam: Cameras, score_image: torch.Tensor, steps: int,
                  batch_views: int = 2, seed: int = 0, cfg: FitCfg | None = None) -> float:
    """Optimise the Gaussians ``g`` (one set, [1, K, ...]) on ``fit_images`` [F, 3, H, W] seen
    from ``fit_cams`` ([1, F]), ``batch_views`` random ones a step, for ``steps`` Adam steps;
    the PSNR of the fitted set's render from ``score_cam`` ([1, 1]) against ``score_image``.

    Parameters: means (lr ``lr_means`` x the set's extent, decaying to 1/100 as 3DGS's),
    covariance ``s0^2 L L^T`` with ``L`` a free 3x3 factor starting at the Cholesky factor of
    the predicted covariance over ``s0`` (its RMS scale; lr ``lr_scales``), opacity logits
    (``lr_opacities``), SH DC (``lr_sh_dc``) and the rest (``lr_sh_rest``)."""
    cfg = cfg or FitCfg()
    means = g.means.detach().clone().requires_grad_(True)
    cov = g.covariances.detach().double()
    s0 = (torch.diagonal(cov, dim1=-2, dim2=-1).mean(-1).clamp_min(1e-12).sqrt())
    eye = 1e-9 * torch.eye(3, dtype=torch.float64)
    factor = torch.linalg.cholesky(cov / s0[..., None, None] ** 2 + eye).float()
    factor.requires_grad_(True)
    s0 = s0.float()[..., None, None]
    o = g.opacities.detach().clamp(1e-4, 1 - 1e-4)
    logits = torch.log(o / (1 - o)).requires_grad_(True)
    dc = g.harmonics[..., :1].detach().clone().requires_grad_(True)
    rest = g.harmonics[..., 1:].detach().clone().requires_grad_(True)
    extent = float((g.means - g.means.mean(1, keepdim=True)).norm(dim=-1).mean())
    opt = torch.optim.Adam([
        {"params": [means], "lr": cfg.lr_means * extent},
        {"params": [factor], "lr": cfg.lr_scales},
        {"params": [logits], "lr": cfg.lr_opacities},
        {"params": [dc], "lr": cfg.lr_sh_dc},
        {"params": [rest], "lr": cfg.lr_sh_rest},
    ], eps=1e-15)
    decay = 0.01 ** (1 / max(steps, 1))
    sched = torch.optim.lr_scheduler.LambdaLR(opt, [lambda s: decay**s] + [lambda s: 1.0] * 4)
    shape = tuple(score_image.shape[-2:])

    def render(cams: Cameras) -> torch.Tensor:
        m = cams.near.shape[1]
        covariances = s0**2 * (factor @ factor.transpose(-1, -2))
        fitted = Gaussians(means=means, covariances=covariances,
                           harmonics=torch.cat([dc, rest], -1), opacities=torch.sigmoid(logits),
                           scales=g.scales, rotations=g.rotations)
        fitted = Gaussians(*(getattr(fitted, f).expand(m, *getattr(fitted, f).shape[1:])
                             for f in GAUSSIAN_FIELDS))
        return model.decoder(fitted, cams.extrinsics, cams.intrinsics, cams.near, cams.far,
                             shape).color[0]

    gen = torch.Generator().manual_seed(seed)
    frames = fit_images.shape[0]
    for _ in range(steps):
        pick = torch.randperm(frames, generator=gen)[:batch_views]
        cams = Cameras(*(getattr(fit_cams, k)[:, pick] for k in CAMERA_FIELDS))
        color = render(cams)
        gt = fit_images[pick]
        loss = ((1 - cfg.ssim_weight) * (color - gt).abs().mean()
                + cfg.ssim_weight * (1 - ssim_torch(color, gt).mean()))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
    with torch.no_grad():
        return psnr(render(score_cam).clamp(0, 1), score_image[None]).item()


def scene_frames(root: Path, key: str, image_shape) -> tuple[Cameras, torch.Tensor]:
    """Every frame of the test scene ``key`` under ``root``: its cameras [1, V] and images
    [V, 3, H, W] (the stored size, which must be ``image_shape``)."""
    stage = root / "test"
    record = next(s for s in read_chunk(stage / read_index(stage)[key]) if s["key"] == key)
    views = views_from_record(record)
    if list(views.images.shape[-2:]) != list(image_shape):
        raise ValueError(f"{key}: frames are {tuple(views.images.shape[-2:])}, not "
                         f"{tuple(image_shape)}: give --image-shape as stored")
    v = views.images.shape[0]
    cams = Cameras(views.extrinsics[None], views.intrinsics[None],
                   torch.full((1, v), views.near), torch.full((1, v), views.far))
    return cams, views.images


def scene_rows(model, batch: dict, key: str, frames: dict, keeps, rank_by: str, steps: int,
               fit_on: str) -> list[dict]:
    """The rows of one scene: per target, every Gaussian and each budget of ``keeps``,
    predicted and fitted (on the target's own image, or on the scene's other ``frames``:
    ``frames["cameras"]``, ``frames["images"]`` and the target frames ``frames["targets"]``)."""
    inputs = model_inputs(batch)
    images = batch["target"]["image"][0]
    others = [i for i in range(frames["images"].shape[0]) if i not in frames["targets"]]
    rows = []
    settings = [(1.0, None)] + [(k, GaussianBudget(k, rank_by)) for k in keeps]
    with torch.no_grad():  # the encoder once per scene, reused by every setting
        hooks = StudyHooks(encoding=model.encode(inputs.images, inputs.extrinsics,
                                                 inputs.intrinsics, inputs.near, inputs.far))
    for keep, budget in settings:
        with torch.no_grad():
            out = model(*inputs, budget=budget, hooks=hooks)
        for n in range(images.shape[0]):
            one = Gaussians(*(getattr(out.gaussians, f)[n:n + 1] for f in GAUSSIAN_FIELDS))
            predicted = psnr(out.color[0, n][None].clamp(0, 1), images[n][None]).item()
            target_cam = Cameras(*(getattr(inputs.targets, k)[:, n:n + 1]
                                   for k in CAMERA_FIELDS))
            if fit_on == "target":
                fit_cams, fit_images = target_cam, images[n:n + 1]
            else:
                fit_cams = Cameras(*(getattr(frames["cameras"], k)[:, others]
                                     for k in CAMERA_FIELDS))
                fit_images = frames["images"][others]
            fitted = fit_gaussians(model, one, fit_cams, fit_images, target_cam, images[n],
                                   steps, batch_views=min(2, fit_images.shape[0]))
            rows.append({"scene": key, "target": n, "keep": keep, "kept": len(one),
                         "psnr_predicted": predicted, "psnr_fitted": fitted})
    return rows


def summarise(rows: list[dict], keeps) -> dict:
    """Per K: the feed-forward loss, the bound's loss and their difference (dB), each a mean
    over scenes (a scene's value: the mean over its targets) with a 95% t interval."""
    by = {}
    for r in rows:
        by.setdefault((r["scene"], int(r["target"])), {})[float(r["keep"])] = r
    out = {}
    for k in keeps:
        per_scene: dict[str, list] = {}
        for (scene, _), row in by.items():
            if k not in row or 1.0 not in row:
                continue
            full, kept = row[1.0], row[k]
            ff = float(full["psnr_predicted"]) - float(kept["psnr_predicted"])
            bound = float(full["psnr_fitted"]) - float(kept["psnr_fitted"])
            per_scene.setdefault(scene, []).append((ff, bound, ff - bound))
        means = [[statistics.mean(v[i] for v in vals) for i in range(3)]
                 for vals in per_scene.values()]
        if not means:
            continue
        out[f"{100 * k:g}%"] = {
            name: {"mean": statistics.mean(m[i] for m in means),
                   "t95": list(t_interval([m[i] for m in means]))}
            for i, name in enumerate(("feed_forward_loss_db", "bound_loss_db",
                                      "feed_forward_minus_bound_db"))} | {"scenes": len(means)}
    return out


def chart(summary: dict, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keeps = sorted(summary, key=lambda s: float(s[:-1]))
    x = [float(k[:-1]) for k in keeps]
    fig, ax = plt.subplots(figsize=(6, 4))
    for name, label in (("feed_forward_loss_db", "feed-forward (predicted K)"),
                        ("bound_loss_db", "bound (K fitted on other frames)")):
        y = [summary[k][name]["mean"] for k in keeps]
        lo = [summary[k][name]["t95"][0] for k in keeps]
        hi = [summary[k][name]["t95"][1] for k in keeps]
        ax.errorbar(x, y, yerr=[[a - b for a, b in zip(y, lo)], [b - a for a, b in zip(y, hi)]],
                    marker="o", capsize=3, label=label)
    ax.set_xscale("log")
    ax.set_xticks(x, [f"{v:g}" for v in x])
    ax.minorticks_off()
    ax.axhline(0, color="0.7", lw=0.8)
    ax.set_xlabel("Gaussians kept per target (%)")
    ax.set_ylabel("PSNR loss against all Gaussians (dB)")
    ax.set_title("What keeping K costs: the feed-forward budget and the bound")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", default="tiny_full_budget",
                   help="a shipped name or checkpoint file (default: tiny_full_budget)")
    p.add_argument("--data", required=True, help="a synthetic test root (usplat synth)")
    p.add_argument("--split", default="standard", help="its evaluation index (default: standard)")
    p.add_argument("--scenes", type=int, default=20, help="the index's first N scenes")
    p.add_argument("--steps", type=int, default=300, help="Adam steps per fit")
    p.add_argument("--keeps", type=float, nargs="+", default=list(KEEPS),
                   help="fractions of each target's Gaussians (default: 0.5 0.3 0.1 0.05)")
    p.add_argument("--rank-by", choices=RANKINGS, default="learned",
                   help="the budget's ranking (default: learned)")
    p.add_argument("--image-shape", type=int, nargs=2, default=[64, 64], metavar=("H", "W"),
                   help="the images' size (default: 64 64, the shipped models')")
    p.add_argument("--fit-on", choices=["frames", "target"], default="frames",
                   help="frames: fit on the scene's frames other than its targets and score "
                   "the target (the bound of a 3D model of K Gaussians); target: fit on the "
                   "target image itself (in sample)")
    p.add_argument("--threads", type=int, default=1, help="torch and Dr.Jit threads")
    p.add_argument("--out", required=True, help="folder for bound.csv, summary.json, bound.png")
    args = p.parse_args(argv)
    import drjit as dr

    torch.set_num_threads(args.threads)
    dr.set_thread_count(args.threads)
    torch.manual_seed(0)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    model = load(args.checkpoint).eval()
    index = synthetic_indices(Path(args.data))[args.split]
    targets = json.loads(Path(index).read_text())  # the evaluation index: frames per scene
    ds = dataset_from_section({"name": "synth", "roots": [args.data],
                               "image_shape": args.image_shape,
                               "evaluation_index": str(index)}, "test")
    table = out / "bound.csv"
    rows = []
    if table.is_file():
        with open(table) as f:
            rows = list(csv.DictReader(f))
    done = {r["scene"] for r in rows}
    for i, example in enumerate(ds):
        if i == args.scenes:
            break
        key = example["scene"]
        if key in done:
            continue
        batch = torch.utils.data.default_collate([example])
        cameras, images = scene_frames(Path(args.data), key, args.image_shape)
        frames = {"cameras": cameras, "images": images,
                  "targets": set(targets[key]["target"])}
        rows += scene_rows(model, batch, key, frames, args.keeps, args.rank_by, args.steps,
                           args.fit_on)
        with atomic_open(table, "w") as f:
            w = csv.DictWriter(f, FIELDS)
            w.writeheader()
            w.writerows(rows)
        print(f"scene {i + 1}/{args.scenes} {key}: done", flush=True)
    summary = summarise(rows, args.keeps)
    write_json(out / "summary.json", {"checkpoint": args.checkpoint, "data": args.data,
                                      "split": args.split, "steps": args.steps,
                                      "fit_on": args.fit_on,
                                      "rank_by": args.rank_by, "per_keep": summary})
    chart(summary, out / "bound.png")
    print("| kept | feed-forward loss, dB [95% t] | bound's loss, dB [95% t] | "
          "feed-forward - bound, dB [95% t] | scenes |")
    print("|---|---|---|---|---|")
    for keep, s in summary.items():
        cells = [f"{s[n]['mean']:+.3f} [{s[n]['t95'][0]:+.3f}, {s[n]['t95'][1]:+.3f}]"
                 for n in ("feed_forward_loss_db", "bound_loss_db",
                           "feed_forward_minus_bound_db")]
        print(f"| {keep} | " + " | ".join(cells) + f" | {s['scenes']} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
