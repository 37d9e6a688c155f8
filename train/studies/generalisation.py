"""Generalisation: held-out PSNR and depth AbsRel against the number of distinct training
scenes, at a fixed step budget (the shipped recipe, tiny (a), one thread per run).

    python train/studies/generalisation.py --data outputs/big/train480 \
        --eval-data outputs/big/test2000 --scenes 24 96 480 --steps 1500 --out outputs/gen

Subsets are the first N scenes of ``--data`` (kinds round-robin), written as datasets of their
own. Each run is resumable; a second call skips finished runs. Writes ``<out>/curve.csv`` and
``<out>/curve.png`` (held-out and training PSNR against scenes).
"""

import argparse
import csv
import json
import logging
import sys
from pathlib import Path

import usplat_dr  # noqa: F401  (libLLVM before drjit)
from usplat_dr import portable

portable.enable()  # AVX2 code paths, as the usplat command (before torch is imported)

CONFIG = "synthetic_tiny_depth.yaml"  # packaged (usplat_dr/configs/)


def subset(data: Path, n: int, out: Path) -> Path:
    """The first ``n`` scenes of ``data``'s training stage as a dataset of their own."""
    from usplat_dr.data.chunks import ChunkWriter, read_chunk, read_index

    root = out / f"data_{n}"
    if (root / "train" / "index.json").is_file():
        return root
    index = read_index(data / "train")
    keys = list(index)[:n]
    if len(keys) < n:
        raise ValueError(f"{data} has {len(index)} training scenes, fewer than {n}")
    wanted = set(keys)
    with ChunkWriter(root, "train") as writer:
        for chunk in sorted({index[k] for k in keys}):
            for scene in read_chunk(data / "train" / chunk):
                if scene["key"] in wanted:
                    writer.add(scene)
    return root


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--eval-data", required=True)
    p.add_argument("--scenes", type=int, nargs="+", default=[24, 96, 480])
    p.add_argument("--steps", type=int, default=1500)
    p.add_argument("--out", type=Path, default=Path("outputs/gen"))
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    import torch

    from usplat_dr.config import load_config
    from usplat_dr.evaluation import evaluate, synthetic_indices
    from usplat_dr.training import train
    from usplat_dr.training.checkpoints import load_model

    rows = []
    for n in args.scenes:
        run = args.out / f"scenes_{n}"
        done = run / "result.json"
        if not done.is_file():
            root = subset(args.data, n, args.out)
            cfg = load_config([CONFIG], [
                f"dataset.roots=[{root}]", f"output_dir={run}", "model.variant=baseline",
                "threads=1", f"train.steps={args.steps}", "train.progress=false",
                f"train.checkpoint_every={max(100, args.steps // 10)}",
                f"train.validate_every={args.steps}"])
            train(cfg, resume=True)
            model, _ = load_model(run / "checkpoints" / "last.ckpt")
            torch.set_num_threads(1)
            s = evaluate(model, {"name": "synth", "roots": [args.eval_data],
                                 "image_shape": [64, 64]},
                         synthetic_indices(args.eval_data, ["standard"]), run / "eval",
                         images_per_split=2, progress=False)["splits"]["standard"]
            with open(run / "metrics.csv") as f:
                last = list(csv.DictReader(f))[-max(1, args.steps // 50):]  # last 2%
            s["train_psnr"] = sum(float(r["psnr"]) for r in last) / len(last)
            done.write_text(json.dumps(s))
        s = json.loads(done.read_text())
        rows.append({"scenes": n, "steps": args.steps, "held_out_psnr": s["psnr"],
                     "held_out_ssim": s["ssim"], "held_out_abs_rel": s["abs_rel"],
                     "train_psnr": s["train_psnr"]})
        print(json.dumps(rows[-1]), flush=True)
    with open(args.out / "curve.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.4))
    x = [r["scenes"] for r in rows]
    ax[0].plot(x, [r["train_psnr"] for r in rows], "o--", label="training (last 2% of steps)")
    ax[0].plot(x, [r["held_out_psnr"] for r in rows], "o-", label="held-out (standard split)")
    ax[0].set(xscale="log", xlabel="distinct training scenes", ylabel="PSNR (dB)",
              title=f"tiny (a), {args.steps} steps")
    ax[1].plot(x, [r["held_out_abs_rel"] for r in rows], "o-")
    ax[1].set(xscale="log", xlabel="distinct training scenes", ylabel="held-out depth AbsRel")
    ax[1].set(yscale="log")
    for a in ax:
        a.set_xticks(x, [str(n) for n in x])
        a.minorticks_off()
        a.grid(alpha=0.3)
    ax[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "curve.png", dpi=110)
    return 0


if __name__ == "__main__":
    sys.exit(main())
