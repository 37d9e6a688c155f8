"""Can a scene's Gaussian count be chosen without its target images? The context-view proxy
(train/studies/LOG.md, "An automatic count: the context-view proxy").

Per held-out scene and budget (a fraction of the Gaussians, ranked by ``--rank-by``): the
proxy loss, PSNR of the context views rendered with all Gaussians minus with the budget (the
context views' own images as the reference; what an automatic count could compute at
inference), beside the real loss, the same on the target views against their images. An
automatic count picks, per scene, the smallest budget whose proxy loss is within a tolerance;
the study prints, per tolerance, the mean budget kept and the mean and worst real loss.

    python train/studies/auto_budget_proxy.py --checkpoint tiny_full --rank-by dither \\
        --data outputs/big/test5000 --scenes 20 --out outputs/auto_budget

``--calibration FILE`` (another set's ``proxy.csv``, say a development set's): the proxy
calibrated there. Per budget, the real loss predicted by a least-squares line in the proxy
loss, plus a margin, the ``--quantile`` of that line's residuals on the calibration scenes;
the count keeps what ``--gaussians auto`` keeps (``calibrated_choice``: the smallest budget
whose predicted loss plus margin, and every larger one's, is within the tolerance; until
2026-11-29 the smallest within it wherever it lay, which chose the same on the held-out
scenes), and the study prints the same table for it, with the mean budget per scene kind.

Writes ``proxy.csv`` (one row per scene and budget) and ``summary.json``.
"""

import argparse
import csv
import json
import statistics
from pathlib import Path

import torch

import usplat_dr  # noqa: F401  (libLLVM first)
from usplat_dr.data.types import model_inputs
from usplat_dr.evaluation import held_out_scenes, load_example
from usplat_dr.evaluation.metrics import psnr
from usplat_dr.io import atomic_open, write_json
from usplat_dr.model.auto_budget import AutoBudget, Calibration, choose_keep
from usplat_dr.model.budget import RANKINGS, GaussianBudget
from usplat_dr.model.uniquesplat import StudyHooks
from usplat_dr.training.checkpoints import CHECKPOINTS, training_image_shape
from usplat_dr.training.loader import load

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


def read_proxy_csv(path) -> dict:
    """``proxy.csv`` as {scene: {keep: (proxy loss, real loss)}}."""
    found = {}
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            found.setdefault(row["scene"], {})[float(row["keep"])] = (
                float(row["proxy_loss"]), float(row["real_loss"]))
    return found


def calibrated_choice(found: dict, calibration: Calibration, tolerance: float) -> float:
    """The budget the library's automatic count chooses for a scene measured as ``found``
    ({keep: (proxy loss, real loss)}): the smallest whose predicted loss, and every larger
    one's, is within ``tolerance`` (``auto_budget.choose_keep``), 1 (every Gaussian) where the
    largest's is not."""
    keeps = tuple(sorted(k for k in found if k < 1.0))
    return choose_keep(lambda k: found[k][0], AutoBudget(tolerance, keeps=keeps),
                       calibration)[0]


def calibration_data(path: Path) -> str:
    """What a calibration was fitted on: the set and scene count this study wrote beside its
    ``proxy.csv`` (``summary.json``'s ``data``), else the file's path."""
    summary = path.parent / "summary.json"
    scenes = len(read_proxy_csv(path))
    if summary.is_file():
        return f"{json.loads(summary.read_text()).get('data', path)}, {scenes} scenes"
    return f"{path}, {scenes} scenes"


def ship(name: str, calibration: Calibration, root: Path = CHECKPOINTS) -> None:
    """Record ``calibration`` in the manifest entry of the shipped checkpoint ``name`` (its
    ``auto_budget`` list, replacing one of the same ranking). Re-shipping the weights
    (train/ship_checkpoint.py) writes a new entry without it: a calibration belongs to the
    weights it was measured with."""
    path = root / "manifest.json"
    manifest = json.loads(path.read_text())
    entry = next((e for e in manifest if e["name"] == name), None)
    if entry is None:
        raise ValueError(f"--ship {name}: no such entry in {path} (names: "
                         f"{', '.join(e['name'] for e in manifest)})")
    kept = [d for d in entry.get("auto_budget", []) if d.get("rank_by") != calibration.rank_by]
    entry["auto_budget"] = [*kept, calibration.as_dict()]
    write_json(path, manifest)


def choice_table(per_scene: dict, chosen_by, summary: dict, key: str) -> None:
    """Print (and store under ``summary[key]``) per tolerance the mean budget kept, the mean
    and worst real loss, and the mean budget per scene kind (the name's prefix)."""
    print("\n| tolerance, dB | mean kept | mean real loss, dB | worst scene, dB | mean kept by "
          "kind |\n|---|---|---|---|---|")
    summary[key] = {}
    for tol in TOLERANCES:
        chosen = {s: chosen_by(found, tol) for s, found in per_scene.items()}
        real = [per_scene[s][k][1] for s, k in chosen.items()]
        kinds = {}
        for scene, keep in chosen.items():
            kinds.setdefault(scene.split("_")[0], []).append(keep)
        by_kind = {k: statistics.mean(v) for k, v in sorted(kinds.items())}
        summary[key][str(tol)] = {"mean_kept": statistics.mean(chosen.values()),
                                  "mean_loss_db": statistics.mean(real), "worst_db": max(real),
                                  "mean_kept_by_kind": by_kind, "chosen": chosen}
        kind_text = ", ".join(f"{k} {v:.0%} ({len(kinds[k])})" for k, v in by_kind.items())
        print(f"| {tol:g} | {statistics.mean(chosen.values()):.0%} | "
              f"{statistics.mean(real):+.2f} | {max(real):+.2f} | {kind_text} |")


def image_size(checkpoint: str, size: int | None) -> int:
    """``size`` as given, else the shorter side ``checkpoint`` was trained at (64 where it
    records none): a calibration holds at the size it was measured at."""
    if size is not None:
        return size
    shape = training_image_shape(checkpoint)
    return 64 if shape is None else min(shape)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", default="tiny_full", help="a shipped name or a file")
    p.add_argument("--rank-by", default="dither", choices=RANKINGS, help="the budget's ranking")
    p.add_argument("--data", required=True, help="held-out synthetic set (usplat synth)")
    p.add_argument("--scenes", type=int, default=20, help="first scenes of the standard split")
    p.add_argument("--size", type=int, default=None,
                   help="image size (default: the size the checkpoint was trained at, 64 where "
                   "it records none); recorded with a shipped calibration")
    p.add_argument("--threads", type=int, default=1, help="torch threads")
    p.add_argument("--calibration", type=Path, default=None,
                   help="another set's proxy.csv: calibrate the proxy there (see above)")
    p.add_argument("--quantile", type=float, default=0.9,
                   help="the calibration residuals' quantile added as a margin")
    p.add_argument("--reuse", action="store_true",
                   help="read OUT/proxy.csv instead of computing it again")
    p.add_argument("--ship", metavar="NAME",
                   help="record the calibration made from --calibration in the manifest entry "
                   "of the shipped checkpoint NAME (the one measured), where --gaussians auto "
                   "finds it")
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    if args.ship is not None and args.calibration is None:
        p.error("--ship needs --calibration (the development set's proxy.csv to fit)")
    if args.calibration is not None:
        made = args.calibration.parent / "summary.json"
        made = json.loads(made.read_text()) if made.is_file() else {}
        for key, mine in (("checkpoint", args.ship or args.checkpoint),
                          ("rank_by", args.rank_by)):
            if key in made and made[key] != mine:
                p.error(f"--calibration {args.calibration} was measured with {key} "
                        f"{made[key]!r}, not {mine!r}: calibrate the model and ranking you "
                        f"use (or ship)")
    if args.calibration is not None and not args.calibration.is_file():
        p.error(f"--calibration {args.calibration}: no such file (a proxy.csv this study "
                f"wrote for another set)")
    if not 0.0 < args.quantile < 1.0:
        p.error(f"--quantile must be between 0 and 1, got {args.quantile}")
    args.size = image_size(args.checkpoint, args.size)
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.reuse:
        per_scene = read_proxy_csv(out / "proxy.csv")
    else:
        per_scene = measure(args)
        with atomic_open(out / "proxy.csv", "w") as f:
            writer = csv.DictWriter(f, FIELDS)
            writer.writeheader()
            for scene, found in per_scene.items():
                for keep, (proxy, real) in sorted(found.items()):
                    writer.writerow({"scene": scene, "keep": keep, "proxy_loss": proxy,
                                     "real_loss": real})
    summary = {}
    print("\nThe proxy as it is (its loss within the tolerance):")
    choice_table(per_scene, lambda found, tol: min(k for k, v in found.items() if v[0] <= tol),
                 summary, "proxy")
    if args.calibration is not None:
        calibration = Calibration.fit(read_proxy_csv(args.calibration), args.quantile,
                                      args.rank_by, calibration_data(args.calibration),
                                      args.size)
        summary["calibration"] = {"file": str(args.calibration), **calibration.as_dict()}
        print(f"\nCalibrated on {args.calibration} (line per budget, margin = the "
              f"{args.quantile:g} quantile of its residuals):")
        choice_table(per_scene, lambda found, tol: calibrated_choice(found, calibration, tol),
                     summary, "calibrated")
        if args.ship is not None:
            ship(args.ship, calibration)
            print(f"\nrecorded in checkpoints/manifest.json, entry {args.ship}: auto_budget "
                  f"(rank_by={args.rank_by})")
    print("\n| kept | mean proxy loss, dB | mean real loss, dB |\n|---|---|---|")
    for keep in sorted({k for f in per_scene.values() for k in f if k < 1.0}):
        proxy = statistics.mean(f[keep][0] for f in per_scene.values())
        real = statistics.mean(f[keep][1] for f in per_scene.values())
        summary[f"keep {keep:g}"] = {"proxy_db": proxy, "real_db": real}
        print(f"| {keep:.0%} | {proxy:+.2f} | {real:+.2f} |")
    write_json(out / "summary.json", {"checkpoint": args.checkpoint, "rank_by": args.rank_by,
                                      "data": args.data, "rows": summary})
    return 0


def measure(args) -> dict:
    """{scene: losses(...)} over the set's first ``args.scenes`` scenes, printed as they come."""
    model = load(args.checkpoint).eval()
    dataset, index, scenes = held_out_scenes(args.data, count=args.scenes, size=args.size)
    per_scene = {}
    for scene in scenes:
        batch = load_example(dataset, index, scene)
        with torch.no_grad():
            per_scene[scene] = losses(model, model_inputs(batch, "cpu"),
                                      batch["target"]["image"], KEEPS, args.rank_by)
        print(scene, " ".join(f"{k:g}: {v[0]:.2f}/{v[1]:.2f}" for k, v in
                              sorted(per_scene[scene].items())), flush=True)
    return per_scene


if __name__ == "__main__":
    raise SystemExit(main())
