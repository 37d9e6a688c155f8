"""Seeds of the live view-specific arm, read by the rule registered for them
(train/studies/LOG.md, "Seeds of the live arm"): per seed and split, the view-specificity
meter of its (c) and (c) - (a) in PSNR over the split's scenes; a seed counts only if its
branch is live on the standard split (or the one ``--live-split`` names); over the live seeds,
the verdict's rule on the seed-level t interval (with one live seed, the interval over scenes,
and the label says it rests on one).

    python train/studies/live_seeds.py --baseline outputs/live/gpu_seeds/eval_a \\
        --seeds 0=outputs/live/gpu_seeds/eval_tiny_full_live:cuda \\
                1=outputs/live/gpu_seeds/eval_s1:cuda 2=outputs/live/gpu_seeds/eval_s2:cuda \\
        --confirm 1 2 3 4 --out outputs/live/gpu_seeds/verdict

Each folder is one ``usplat eval --out`` (``per_scene.csv`` and ``summary.json``); the (a) is
the same for every seed (the arm trains the branch alone from the shipped model), or, with
``--baseline SEED=FOLDER ...``, each seed's own (a) trained the same way (the verdict's design:
(c) - (a) paired by seed). ``--live-split`` names the split whose meter decides whether a seed
counts (default standard; the paper's-protocol verdict with extrapolated targets reads
extrapolation). ``--confirm`` names the seeds whose labels confirm the splits seed 0 suggested
(wide baseline and extrapolation): those splits are labelled over them alone and over all
seeds beside it.
``--min-live N``: the live seeds the registered rule needs (the 128x128 verdicts: 3); with
fewer, each label is "not readable", the numbers and what the rule would read beside it.
``--controls NAME=FOLDER``: other models (an (a) trained another way, say) read as control -
(a) per split, beside the rule.
Writes ``OUT/live_seeds.md`` and ``OUT/live_seeds.json``.
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np

import usplat_dr  # noqa: F401  (libLLVM before drjit)
from usplat_dr.evaluation.verdict import read_per_scene, rule_label, t_interval
from usplat_dr.io import atomic_open

#: Splits the amendment reads beside the standard one.
SPLITS = ("standard", "wide_baseline", "extrapolation")


def seed_reading(folder: Path, baseline: dict, split: str) -> dict:
    """One seed's (c) on one split: the meter from its summary and (c) - (a) per scene."""
    summary = json.loads((folder / "summary.json").read_text())
    meter = summary["splits"][split]["view_specificity"]
    own = read_per_scene(folder / "per_scene.csv", {"psnr": True})
    keys = sorted(k for k in own if k[0] == split and k in baseline)
    d = np.array([own[k]["psnr"] - baseline[k]["psnr"] for k in keys])
    low, high = t_interval(d)
    return {"scenes": len(keys), "c_minus_a": float(d.mean()), "low": low, "high": high,
            "meter_abs": meter["d_mean_abs"]["mean_db"],
            "meter_abs_low": meter["d_mean_abs"]["low"],
            "signed": meter["d_mean"]["mean_db"], "signed_low": meter["d_mean"]["low"],
            "signed_high": meter["d_mean"]["high"], "zero": meter["d_zero"]["mean_db"],
            "live": bool(meter["live"]), "spread": max(meter["spread_rel_w"].values())}


def read_baselines(parser, specs: list[str]) -> dict:
    """``--baseline``: one FOLDER (key None, every seed's (a)) or SEED=FOLDER items."""
    if len(specs) == 1 and "=" not in specs[0]:
        folder = Path(specs[0])
        if not (folder / "per_scene.csv").is_file():
            parser.error(f"--baseline {specs[0]!r}: not a usplat eval --out folder "
                         "(no per_scene.csv)")
        return {None: read_per_scene(folder / "per_scene.csv", {"psnr": True})}
    out = {}
    for spec in specs:
        name, _, folder = spec.partition("=")
        if not name or not Path(folder, "per_scene.csv").is_file():
            parser.error(f"--baseline {spec!r}: give one FOLDER, or SEED=FOLDER per seed, "
                         "FOLDER a usplat eval --out")
        out[name] = read_per_scene(Path(folder) / "per_scene.csv", {"psnr": True})
    return out


def rule(means: list[float], scene_interval: tuple[float, float], min_live: int = 1) -> dict:
    """The verdict's rule over the live seeds' means (seed-level t interval); with one seed,
    on that seed's interval over scenes, said in the label. Fewer than ``min_live`` seeds:
    the numbers are given, the label is "not readable" (a registration that asks for more)."""
    if not means:
        return {"seeds": 0, "label": "no live seed"}
    low, high = t_interval(means) if len(means) >= 2 else scene_interval
    mean = float(np.mean(means))
    label = rule_label(mean, low, high)
    notes = ["one live seed: interval over scenes"] if len(means) == 1 else []
    if len(means) < min_live:
        label = (f"not readable: {len(means)} live, the rule reads at {min_live} "
                 f"(would read {'; '.join([label, *notes])})")
    elif notes:
        label += f" ({notes[0]})"
    return {"seeds": len(means), "mean": mean, "low": float(low), "high": float(high),
            "label": label}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--baseline", required=True, nargs="+", metavar="FOLDER | SEED=FOLDER",
                   help="usplat eval --out folder of (a), one for every seed, or one per seed "
                        "as SEED=FOLDER (paired by seed)")
    p.add_argument("--live-split", default="standard", choices=SPLITS,
                   help="the split whose meter decides whether a seed counts")
    p.add_argument("--seeds", required=True, nargs="+", metavar="SEED=FOLDER[:DEVICE]",
                   help="each seed's usplat eval --out folder of its (c), and where it trained")
    p.add_argument("--confirm", nargs="*", default=[], metavar="SEED",
                   help="the seeds that confirm the wide-baseline and extrapolation readings")
    p.add_argument("--controls", nargs="*", default=[], metavar="NAME=FOLDER",
                   help="other models' usplat eval folders (no meter needed), each read as "
                        "control - (a) per split, exploratory")
    p.add_argument("--min-live", type=int, default=1, metavar="N",
                   help="live seeds the registered rule needs before it labels (fewer: 'not "
                        "readable', the numbers beside it); the 128x128 verdicts: 3")
    p.add_argument("--out", required=True, type=Path, help="folder for the table and JSON")
    args = p.parse_args(argv)
    if args.min_live < 1:
        p.error(f"--min-live must be at least 1, got {args.min_live}")
    baselines = read_baselines(p, args.baseline)
    seeds = {}
    for spec in args.seeds:
        name, _, rest = spec.partition("=")
        folder, _, device = rest.partition(":")
        if not name or not folder or not Path(folder, "summary.json").is_file():
            p.error(f"--seeds {spec!r}: give SEED=FOLDER[:DEVICE], FOLDER a usplat eval --out")
        if name not in baselines and None not in baselines:
            p.error(f"--seeds {spec!r}: no --baseline {name}=FOLDER for this seed")
        baseline = baselines.get(name, baselines.get(None))
        seeds[name] = {"device": device or "?", "splits": {
            s: seed_reading(Path(folder), baseline, s) for s in SPLITS}}
    live = [n for n, s in seeds.items() if s["splits"][args.live_split]["live"]]
    rows = [("| seed | device | split | meter: abs own - scene mean, dB [low] | signed, dB | "
             "own - (Delta W = 0), dB | spread | (c) - (a), dB [95% t over scenes] | counts |"),
            "|---|---|---|---|---|---|---|---|---|"]
    for name, s in seeds.items():
        for split, r in s["splits"].items():
            rows.append(
                f"| {name} | {s['device']} | {split} | {r['meter_abs']:.4f} "
                f"[{r['meter_abs_low']:.4f}]{' live' if r['live'] else ''} | "
                f"{r['signed']:+.4f} [{r['signed_low']:+.4f}, {r['signed_high']:+.4f}] | "
                f"{r['zero']:+.3f} | {r['spread']:.1e} | {r['c_minus_a']:+.3f} "
                f"[{r['low']:+.3f}, {r['high']:+.3f}] | {'yes' if name in live else 'no'} |")
    labels = {}
    for split in SPLITS:
        for group, names in (("all live seeds", live),
                             ("confirming live seeds", [n for n in live if n in args.confirm])):
            if group != "all live seeds" and (split == "standard" or not args.confirm):
                continue
            means = [seeds[n]["splits"][split]["c_minus_a"] for n in names]
            one = (seeds[names[0]]["splits"][split]["low"],
                   seeds[names[0]]["splits"][split]["high"]) if names else (np.nan, np.nan)
            labels[f"{split}, {group}"] = {**rule(means, one, args.min_live), "names": names}
    for split in SPLITS:  # not the registered rule: every seed, live or not
        means = [s["splits"][split]["c_minus_a"] for s in seeds.values()]
        if len(means) >= 2:
            labels[f"{split}, every seed (exploratory: live or not)"] = {
                **rule(means, (np.nan, np.nan)), "names": list(seeds)}
    rows += ["", "| split, seeds | seeds | mean (c) - (a), dB | 95% interval | label |",
             "|---|---|---|---|---|"]
    for key, lab in labels.items():
        if lab["seeds"]:
            rows.append(f"| {key} | {', '.join(lab['names'])} | {lab['mean']:+.3f} | "
                        f"[{lab['low']:+.3f}, {lab['high']:+.3f}] | {lab['label']} |")
        else:
            rows.append(f"| {key} | none | - | - | {lab['label']} |")
    controls = {}
    if args.controls:
        rows += ["", "| control (exploratory) | split | control - (a), dB [95% t over scenes] |",
                 "|---|---|---|"]
    for spec in args.controls:
        name, _, folder = spec.partition("=")
        if not name or not Path(folder, "per_scene.csv").is_file():
            p.error(f"--controls {spec!r}: give NAME=FOLDER, FOLDER a usplat eval --out")
        own = read_per_scene(Path(folder) / "per_scene.csv", {"psnr": True})
        if None not in baselines:
            p.error("--controls needs one --baseline FOLDER for every seed")
        baseline = baselines[None]
        controls[name] = {}
        for split in SPLITS:
            keys = sorted(k for k in own if k[0] == split and k in baseline)
            d = np.array([own[k]["psnr"] - baseline[k]["psnr"] for k in keys])
            low, high = t_interval(d)
            controls[name][split] = {"scenes": len(keys), "minus_a": float(d.mean()),
                                     "low": low, "high": high}
            rows.append(f"| {name} | {split} | {d.mean():+.3f} [{low:+.3f}, {high:+.3f}] |")
    text = "\n".join(rows)
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    with atomic_open(args.out / "live_seeds.md", "w") as f:
        f.write(text + "\n")
    with atomic_open(args.out / "live_seeds.json", "w") as f:
        json.dump({"seeds": seeds, "live": live, "live_split": args.live_split,
                   "paired": None not in baselines, "labels": labels, "controls": controls}, f,
                  indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
