"""Per scene kind: mean PSNR, AbsRel and margin over copying of ``usplat eval`` runs
(their per_scene.csv), and each run's difference from the first (paired by scene).

``python train/studies/real_photos_kinds.py --split standard LABEL=EVAL_DIR ...``
"""

import argparse
import csv
import json
import math
from collections import defaultdict

import numpy as np


def read(folder: str, split: str) -> dict[str, dict]:
    with open(f"{folder}/per_scene.csv", newline="") as f:
        return {r["scene"]: r for r in csv.DictReader(f) if r["split"] == split}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--split", default="standard")
    p.add_argument("runs", nargs="+", metavar="LABEL=EVAL_DIR")
    args = p.parse_args()
    runs = {r.split("=")[0]: read(r.split("=", 1)[1], args.split) for r in args.runs}
    first = next(iter(runs))
    out = defaultdict(dict)
    for label, scenes in runs.items():
        by_kind = defaultdict(list)
        for key in scenes:
            by_kind[key.split("_")[0]].append(key)
            by_kind["all"].append(key)
        for kind, keys in sorted(by_kind.items()):
            d = np.array([float(scenes[k]["psnr"]) - float(runs[first][k]["psnr"]) for k in keys])
            half = 1.96 * d.std(ddof=1) / math.sqrt(len(d)) if len(d) > 1 else float("nan")
            out[kind][label] = {
                "scenes": len(keys),
                "psnr": round(float(np.mean([float(scenes[k]["psnr"]) for k in keys])), 3),
                "abs_rel": round(float(np.mean([float(scenes[k]["abs_rel"]) for k in keys])), 4),
                "over_copy": round(float(np.mean([float(scenes[k]["psnr_over_copy"])
                                                  for k in keys])), 3),
                f"minus_{first}": round(float(d.mean()), 3),
                "ci95": [round(float(d.mean() - half), 3), round(float(d.mean() + half), 3)]}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
