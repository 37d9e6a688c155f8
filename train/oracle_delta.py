"""How much could a per-target Delta W give at best? An oracle bound for the verdict.

(c) changes one layer per target view: the last Gaussian-head convolution gets W + Delta W,
with Delta W = U V (rank r) and a bias change that the view-specific branch predicts from
the context images and the target camera. Whatever that branch learns, its output is some
Delta W. This script finds, for each held-out scene, the best Delta W there is for its
target views by gradient descent on the target images themselves (which no model sees), on
top of the trained (a):

- ``shared``: one Delta W for all the scene's targets (scene-level adaptation, the same for
  every view);
- ``per-target``: one Delta W per target view (what view conditioning can express);
- ``context``: one Delta W fitted to render the two context views themselves, then scored on
  the targets: test-time adaptation with only what a test gives, which a network conditioned
  on the context could in principle learn to predict.

``shared`` and ``per-target`` are fitted to the images they are scored on, so they are upper
bounds; ``per-target`` minus ``shared`` bounds what making Delta W depend on the view adds
beyond adapting to the scene. ``per-target`` has one Delta W per view, so three times the
parameters of ``shared`` for three targets: ``--modes shared --rank 12`` is the control with as
many parameters as three rank-4 Delta Ws. At step 0 (Delta W = 0) each target's PSNR is (a)'s,
which the script checks against a plain forward.

    python train/oracle_delta.py --checkpoint checkpoints/tiny_baseline.pt \
        --data outputs/big/test2000 --split standard --scenes 30 --steps 100 --out outputs/oracle

One thread; writes ``<out>/per_target.csv`` and ``<out>/summary.json`` (each difference with
its bootstrap 95% interval over scenes). Two runs' columns are compared with ``--compare
DIR_X:COLUMN DIR_Y:COLUMN``, e.g. per-target against the rank-12 shared control.
"""

import argparse
import csv
import json
import math
import statistics
import sys
import time
from pathlib import Path

import usplat_dr  # noqa: F401  (libLLVM before drjit)
from usplat_dr import portable

portable.enable()  # AVX2 code paths, as the usplat command (before torch is imported)


MODES = ("shared", "per-target", "context")


def fit_scene(model, batch, mode: str, rank: int, steps: int, lr: float, seed: int) -> dict:
    """PSNR per target before and after fitting Delta W (``mode``: ``shared`` or
    ``per-target`` on the target images, ``context`` shared on the context images)."""
    import torch

    from usplat_dr.data.types import model_inputs
    from usplat_dr.evaluation.metrics import psnr
    from usplat_dr.model.hypernet.hypernetwork import LayerDelta

    args = model_inputs(batch, "cpu")
    gt = batch["target"]["image"][0]
    n = gt.shape[0]
    fit_args, fit_gt = args, gt
    if mode == "context":  # render the context views themselves: what a test has
        fit_args, fit_gt = (*args[:5], *args[1:5]), args[0][0]
    spec = next(s for s in model.specs if s.name in model.cfg.specific_layers)
    o, i, k = spec.out_channels, spec.in_channels, spec.kernel_size
    rows = n if mode == "per-target" else 1
    g = torch.Generator().manual_seed(seed)
    # U = 0 and the bias change = 0: the fit starts exactly at (a); V random (N(0, 1), scaled
    # by 1/sqrt(fan_in) as (c)'s V is) so that U gets a gradient from the first step
    u = torch.zeros(rows, o, rank, requires_grad=True)
    v = torch.randn(rows, rank, i, k, k, generator=g).requires_grad_(True)
    bias = torch.zeros(rows, o, requires_grad=True)
    weights = dict(zip(model.cfg.target_layers, model.agnostic_weights()))

    def target_weights(images, intrinsics, extrinsics, target_intrinsics, *_):
        m = target_intrinsics.shape[1]

        def each(t):
            return t if rows == m else t.expand(m, *t.shape[1:])
        delta = LayerDelta(bias=each(bias), u=each(u), v=each(v) / math.sqrt(spec.fan_in))
        return weights, {spec.name: delta}, {}

    model._target_weights = target_weights
    opt = torch.optim.Adam([u, v, bias], lr=lr)
    with torch.no_grad():
        before = psnr(model(*args).color[0], gt)
    for _ in range(steps):
        loss = (model(*fit_args).color[0] - fit_gt).square().mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    with torch.no_grad():
        after = psnr(model(*args).color[0], gt)
    del model._target_weights
    return {"before": before.tolist(), "after": after.tolist()}


def paired(rows_x: list, x: str, rows_y: list, y: str) -> dict:
    """Column ``x`` of ``rows_x`` minus column ``y`` of ``rows_y`` (per_target.csv rows), paired
    by scene (the mean of its targets): the mean over scenes, its bootstrap 95% interval over
    scenes (``usplat_dr.evaluation.verdict.bootstrap_interval``) and the scenes where x is
    higher."""
    import numpy as np

    from usplat_dr.evaluation.verdict import bootstrap_interval

    def by_scene(rows, col):
        out: dict[str, list[float]] = {}
        for r in rows:
            out.setdefault(r["scene"], []).append(float(r[col]))
        return {k: statistics.mean(v) for k, v in out.items()}

    a, b = by_scene(rows_x, x), by_scene(rows_y, y)
    if set(a) != set(b):
        raise SystemExit(f"{x} and {y}: the two tables hold different scenes")
    d = np.array([[a[k] - b[k] for k in sorted(a)]])
    low, high = bootstrap_interval(d)
    return {"mean": float(d.mean()), "low": low, "high": high,
            "scenes_higher": int((d > 0).sum()), "scenes": d.shape[1]}


def compare(spec_x: str, spec_y: str) -> dict:
    """``--compare DIR_X:COLUMN DIR_Y:COLUMN``: the paired difference of two runs' columns."""
    tables = []
    for spec in (spec_x, spec_y):
        folder, _, col = spec.rpartition(":")
        with open(Path(folder) / "per_target.csv") as f:
            tables += [list(csv.DictReader(f)), col]
    return paired(*tables)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--compare", nargs=2, metavar="DIR:COLUMN",
                   help="instead, the paired difference of two runs' columns (e.g. "
                        "outputs/oracle:per_target outputs/oracle_r12_standard:shared)")
    p.add_argument("--checkpoint", help="a trained (a), e.g. the shipped one")
    p.add_argument("--data", help="a held-out synthetic set")
    p.add_argument("--split", default="standard")
    p.add_argument("--scenes", type=int, default=30)
    p.add_argument("--rank", type=int, default=4, help="rank of Delta W (tiny (c): 4)")
    p.add_argument("--steps", type=int, default=100, help="Adam steps per scene and mode")
    p.add_argument("--lr", type=float, default=1e-2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    p.add_argument("--out")
    args = p.parse_args(argv)
    if args.compare:
        print(json.dumps(compare(*args.compare), indent=1))
        return 0
    for name in ("checkpoint", "data", "out"):
        if getattr(args, name) is None:
            p.error(f"--{name} is required (unless --compare)")
    keys = ("a", *(m.replace("-", "_") for m in args.modes))  # per_target.csv's PSNR columns
    import torch
    from torch.utils.data import default_collate

    from usplat_dr.data.dataset import dataset_from_section
    from usplat_dr.data.types import model_inputs
    from usplat_dr.evaluation import synthetic_indices
    from usplat_dr.evaluation.metrics import psnr
    from usplat_dr.io import atomic_open, write_json
    from usplat_dr.training.checkpoints import load_model, training_image_shape

    torch.set_num_threads(1)
    model, _ = load_model(args.checkpoint)
    if model.cfg.variant != "baseline":
        p.error(f"--checkpoint: a trained (a) (variant baseline), got {model.cfg.variant!r}")
    for q in model.parameters():
        q.requires_grad_(False)
    shape = training_image_shape(args.checkpoint) or (64, 64)
    index = synthetic_indices(args.data, [args.split])[args.split]
    ds = dataset_from_section({"name": "synth", "roots": [args.data],
                               "image_shape": list(shape), "evaluation_index": index}, "test")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows, t0 = [], time.perf_counter()
    for s, example in enumerate(ds):
        if s == args.scenes:
            break
        batch = default_collate([example])
        with torch.no_grad():  # (a) as `usplat eval` runs it: the step-0 check's reference
            plain = psnr(model(*model_inputs(batch, "cpu")).color[0], batch["target"]["image"][0])
        fits = {mode: fit_scene(model, batch, mode, args.rank, args.steps, args.lr,
                                args.seed + s) for mode in args.modes}
        for j, ref in enumerate(plain.tolist()):
            for mode, f in fits.items():
                # Delta W = 0 renders (a): the same up to the rank-r path's float rounding
                # (1e-3 dB: measured differences are ~1e-5 dB; a wrong path is off by dBs)
                if abs(f["before"][j] - ref) > 1e-3:
                    raise SystemExit(f"scene {example['scene']} target {j}: {mode} at step 0 "
                                     f"{f['before'][j]:.4f} dB, (a) {ref:.4f} dB")
            rows.append({"scene": example["scene"], "target": j, "a": ref,
                         **{m.replace("-", "_"): f["after"][j] for m, f in fits.items()}})
        mean = {k: statistics.mean(r[k] for r in rows) for k in keys}
        print(f"[{s + 1}/{args.scenes}] {example['scene']}: "
              + ", ".join(f"{k} {mean[k]:.3f}" for k in keys)
              + f" dB ({time.perf_counter() - t0:.0f} s)", flush=True)
    with atomic_open(out / "per_target.csv", "w") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    diffs = [(k, "a") for k in keys[1:]]
    if "shared" in keys and "per_target" in keys:
        diffs.append(("per_target", "shared"))
    summary = {
        "checkpoint": args.checkpoint, "data": args.data, "split": args.split,
        "scenes": len({r["scene"] for r in rows}), "targets": len(rows), "rank": args.rank,
        "steps": args.steps, "lr": args.lr, "seed": args.seed,
        **{f"psnr_{k}": statistics.mean(r[k] for r in rows) for k in keys},
        **{f"{x}_minus_{y}": paired(rows, x, rows, y) for x, y in diffs},
        "seconds": time.perf_counter() - t0}
    write_json(out / "summary.json", summary)
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
