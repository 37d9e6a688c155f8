"""What resolution alone can buy: the detail a model at twice the size could add.

The registered test of the 128x128 (a) asks its renders to beat the 64x64 model's, upsampled 2x
(bicubic), by 1.0 dB. The upsampled renders' error against the 128x128 ground truth has two
parts: the detail no 64x64 image holds (the ground truth at 64x64, upsampled, against itself at
128x128) and the small model's own errors (its upsampled renders against the upsampled ground
truth). A large model that only adds the missing detail, its other errors those of the small
one, scores the second part alone. Per scene of the standard split (PSNR = -10 log10 MSE per
target, averaged over targets, as the protocol's):

- ``psnr_truth_up``: the ground truth at half the size upsampled, against the ground truth;
- ``psnr_small_up``: the small model's renders upsampled, against the ground truth (as
  res128_eval.py's ``psnr_64_up``);
- ``psnr_small_vs_truth_up``: the same renders upsampled against the upsampled ground truth;
- ``detail_gain``: ``psnr_small_vs_truth_up - psnr_small_up``, what such a large model gains
  (exactly: its render is the small one's upsampled plus the missing detail, so its error is
  the small model's own); not a limit on a large model, which may also mend its other errors;
- ``cross``: the share of the upsampled renders' MSE in the cross term of the two parts (0 when
  they are orthogonal: how far the two parts' MSEs add up to the whole).

    python train/studies/res128_ceiling.py --model-small tiny_baseline \\
        --data outputs/big128/test5000 --out outputs/res128_ceiling

Writes ``OUT/per_scene.csv`` and ``OUT/summary.json``.
"""

import argparse
import csv
import importlib.util
import sys
from pathlib import Path

import numpy as np
import torch

import usplat_dr  # noqa: F401  (libLLVM first)
from usplat_dr.evaluation import held_out_scenes
from usplat_dr.evaluation.verdict import t_interval
from usplat_dr.io import atomic_open, write_json
from usplat_dr.training.loader import load

_spec = importlib.util.spec_from_file_location(
    "res128_eval", Path(__file__).with_name("res128_eval.py"))
res128_eval = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(res128_eval)


def decompose(pred_small: torch.Tensor, truth_small: torch.Tensor,
              truth: torch.Tensor) -> dict:
    """[T, 3, h, w] renders and ground truth at half size, [T, 3, 2h, 2w] ground truth -> the
    scene's readings (module docstring); MSE per target in float64."""
    up = res128_eval.upsample(pred_small, 2).double()
    truth_up = res128_eval.upsample(truth_small, 2).double()
    truth = truth.double()
    dims = (-3, -2, -1)
    err = ((up - truth) ** 2).mean(dims)
    res = ((truth_up - truth) ** 2).mean(dims)
    own = ((up - truth_up) ** 2).mean(dims)

    def db(mse: torch.Tensor) -> float:
        return float((-10 * torch.log10(mse)).mean())

    return {"psnr_truth_up": db(res), "psnr_small_up": db(err),
            "psnr_small_vs_truth_up": db(own),
            "detail_gain": db(own) - db(err),
            "cross": float(((err - res - own) / err).mean())}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model-small", default="tiny_baseline",
                   help="the model of half --size (checkpoint or name)")
    p.add_argument("--size", type=int, default=128, help="the held-out set's image size")
    p.add_argument("--data", required=True, help="a usplat synth test root at --size")
    p.add_argument("--scenes", type=int, default=None, help="the first N scenes (default all)")
    p.add_argument("--threads", type=int, default=1, help="torch threads")
    p.add_argument("--out", required=True, type=Path, help="folder for the results")
    args = p.parse_args(argv)
    if args.size < 8 or args.size % 2:
        p.error(f"--size must be an even number of pixels >= 8, got {args.size}")
    if args.scenes is not None and args.scenes < 2:
        p.error(f"--scenes must be at least 2 (an interval over scenes), got {args.scenes}")
    torch.set_num_threads(args.threads)
    small = load(args.model_small).eval()
    big_set, index, scenes = held_out_scenes(args.data, "standard", args.scenes, size=args.size)
    small_set = {**big_set, "image_shape": [args.size // 2] * 2}
    rows = []
    for k, (big, half) in enumerate(zip(res128_eval.examples(big_set, index),
                                        res128_eval.examples(small_set, index))):
        if k == len(scenes):
            break
        assert big["scene"][0] == half["scene"][0] == scenes[k]
        pred, _ = res128_eval.render(small, half)
        rows.append({"scene": scenes[k], **decompose(
            pred, half["target"]["image"][0], big["target"]["image"][0])})
        print(f"{k + 1}/{len(scenes)} {scenes[k]}: detail gain {rows[-1]['detail_gain']:+.2f} dB",
              flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    with atomic_open(args.out / "per_scene.csv", "w") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    col = {key: np.array([r[key] for r in rows]) for key in rows[0] if key != "scene"}
    low, high = t_interval(col["detail_gain"])
    summary = {"scenes": len(rows), "data": str(args.data), "model_small": args.model_small,
               "size": args.size, "means": {k: float(v.mean()) for k, v in col.items()},
               "detail_gain": {"mean": float(col["detail_gain"].mean()), "low": low,
                              "high": high, "max": float(col["detail_gain"].max())},
               "margin_db": res128_eval.MARGIN_DB}
    write_json(args.out / "summary.json", summary)
    m = summary["means"]
    print(f"over {len(rows)} scenes at {args.size}: ground truth at {args.size // 2} upsampled "
          f"{m['psnr_truth_up']:.2f} dB; the small model upsampled {m['psnr_small_up']:.3f} dB, "
          f"against the upsampled ground truth {m['psnr_small_vs_truth_up']:.3f} dB; what "
          f"resolution alone can gain {low:+.3f}..{high:+.3f} (mean {m['detail_gain']:+.3f}) "
          f"dB against the test's +{res128_eval.MARGIN_DB}; cross term {m['cross']:+.3f} of "
          "the MSE")
    return 0


if __name__ == "__main__":
    sys.exit(main())
