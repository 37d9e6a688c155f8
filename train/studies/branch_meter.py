"""The view-specificity meter (``usplat_dr.evaluation.view_specificity``) of checkpoints on
sets of scenes: training scenes and held-out ones, one table. What the live-branch study reads
(train/studies/LOG.md, "A live view-specific branch").

    python train/studies/branch_meter.py --checkpoints tiny_full outputs/live/g02_lr1e-3 \\
        --sets train=outputs/big/train480/train:30 heldout=outputs/big/test2000:60 \\
        --out outputs/live/meter

A set is NAME=FOLDER[:SCENES]: FOLDER holds the chunk files and ``evaluation_index_standard.json``
(a ``usplat synth`` test root, or a train stage's ``train/`` folder: its scenes are scored with
the standard split's frames); SCENES caps how many (the index's first). A checkpoint is a
shipped name, a checkpoint file or a run folder (its ``checkpoints/last.ckpt``), or
``open:NAME:STD[:SEED[:FEATURES]]``: the shipped (c) NAME with its gate opened by STD
(``model.open_gate_std``) as a training run with that seed (default 0) starts, E_H reading
FEATURES (``model.overrides.view_features``, e.g. ``primary``): its step 0, the noise the
opened gate puts in and the new branch's initial weights. Writes
``meter.csv`` (per scene) and ``meter.json`` (the summaries) into ``--out``, and prints one
line per checkpoint and set.
"""

import argparse
import csv
import logging
import os
import shutil
from pathlib import Path

import torch

import usplat_dr  # noqa: F401  (libLLVM first)
from usplat_dr.data.dataset import dataset_from_section
from usplat_dr.data.types import model_inputs
from usplat_dr.evaluation.view_specificity import read_batch, summarise
from usplat_dr.io import atomic_open, write_json
from usplat_dr.training.loader import load


def checkpoint_path(name: str) -> str:
    run = Path(name) / "checkpoints" / "last.ckpt"
    return str(run) if run.is_file() else name


def load_model(spec: str, device: str = "cpu"):
    """The model a ``--checkpoints`` entry names (module docstring), on ``device``."""
    if spec.startswith("open:"):
        from usplat_dr.training.config import ModelSection, model_from_config

        _, name, std, *rest = spec.split(":")
        seed = int(rest[0]) if rest else 0
        overrides = {"view_features": rest[1]} if len(rest) > 1 else {}
        torch.manual_seed(seed)  # as the trainer seeds before it builds the model
        return model_from_config(ModelSection(preset="tiny", variant="full", init_from=name,
                                              open_gate_std=float(std), overrides=overrides)
                                 ).eval().to(device)
    return load(checkpoint_path(spec), device)


def as_test_root(folder: Path, where: Path) -> Path:
    """A dataset root whose ``test/`` stage holds ``folder``'s chunks (a train stage's scenes
    scored like test scenes: hard links, or copies across file systems, in ``where``; the
    chunk reader refuses links that leave their root), or ``folder`` itself when it is a test
    root."""
    if (folder / "test").is_dir():
        return folder
    stage = where / folder.resolve().parent.name / "test"
    stage.mkdir(parents=True, exist_ok=True)
    for f in folder.iterdir():
        if f.suffix in (".torch", ".json") and not (stage / f.name).exists():
            try:
                os.link(f, stage / f.name)
            except OSError:
                shutil.copyfile(f, stage / f.name)
    return stage.parent


def read_set(model, root: Path, index: Path, scenes: int | None, device: str = "cpu") -> list:
    ds = dataset_from_section({"name": "synth", "roots": [str(root)], "image_shape": [64, 64],
                               "evaluation_index": str(index)}, "test")
    readings = []
    for example in ds:
        readings += read_batch(model, torch.utils.data.default_collate([example]), device)
        if scenes is not None and len(readings) >= scenes:
            break
    return readings


def embedding_spread(model, root: Path, index: Path, scenes: int | None,
                     device: str = "cpu") -> dict:
    """How much e_s and H_s's second hidden layer differ between a scene's targets ("within":
    RMS distance to the scene's mean) against between scenes (RMS distance of the scene means
    to their mean), and their mean norm: what Delta W can vary with at all."""
    kept = {}
    hooks = [model.specific.hyper.net[3].register_forward_hook(
                 lambda mod, inp, out: kept.__setitem__("hidden", out.detach())),
             model.view_embedding.register_forward_hook(
                 lambda mod, inp, out: kept.__setitem__("e_s", out[0].detach()))]
    values: dict[str, list] = {"e_s": [], "hidden": []}
    ds = dataset_from_section({"name": "synth", "roots": [str(root)], "image_shape": [64, 64],
                               "evaluation_index": str(index)}, "test")
    with torch.no_grad():
        for i, example in enumerate(ds):
            if scenes is not None and i == scenes:
                break
            a = model_inputs(torch.utils.data.default_collate([example]), device)
            # the model's own path (E_H may read the encoder's features: near, far)
            model.view_delta_w(a.images, a.extrinsics, a.intrinsics, a.target_extrinsics,
                               a.target_intrinsics, a.target_near, a.target_far, a.near, a.far)
            values["e_s"].append(kept["e_s"][0])
            values["hidden"].append(kept["hidden"])
    for hook in hooks:
        hook.remove()
    return {name: within_between(torch.stack(xs)) for name, xs in values.items()}


def within_between(x: torch.Tensor) -> dict:
    """``x`` [S scenes, N targets, D]: the RMS distance of a target's vector to its scene's
    mean ("within"), of the scene means to their mean ("between"), and the mean norm.

    Examples:
        >>> x = torch.tensor([[[1.0, 0], [3, 0]], [[5, 0], [7, 0]]])  # scene means 2 and 6
        >>> within_between(x)
        {'within': 1.0, 'between': 2.0, 'norm': 4.0}
    """
    within = (x - x.mean(1, keepdim=True)).square().sum(-1).mean().sqrt()
    between = (x.mean(1) - x.mean((0, 1))).square().sum(-1).mean().sqrt()
    return {"within": within.item(), "between": between.item(),
            "norm": x.norm(dim=-1).mean().item()}


def chart(runs: list[str], path: Path) -> Path:
    """The meter of each run's validation steps (``metrics.csv``'s ``view_spread``, log scale)
    against the step: does Delta W's spread across targets grow while the branch trains?"""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from usplat_dr.training.run_log import curve, read_metrics

    fig, ax = plt.subplots(figsize=(7, 4))
    for run in runs:
        steps, values = curve(read_metrics(run), "view_spread")
        ax.plot(steps, values, marker="o", label=Path(run).name)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("Delta W spread across targets / norm of W")
    ax.set_title("The view-specificity meter on the validation scene while the branch trains")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoints", nargs="+")
    p.add_argument("--sets", nargs="+", metavar="NAME=FOLDER[:SCENES]")
    p.add_argument("--out", required=True)
    p.add_argument("--chart", nargs="+", metavar="RUN",
                   help="instead, chart these training runs' metrics.csv meter columns into "
                        "OUT (a PNG)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--device", default="cpu", help="cpu, or cuda (Dr.Jit's CUDA backend too)")
    p.add_argument("--embedding", action="store_true",
                   help="also how much e_s and H_s's hidden layer vary within and between "
                        "scenes (models with the ResNet18 E_H)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    if args.chart:
        print(chart(args.chart, Path(args.out)))
        return 0
    if not args.checkpoints or not args.sets:
        p.error("--checkpoints and --sets are required (unless --chart)")
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sets = {}
    for item in args.sets:
        name, _, spec = item.partition("=")
        folder, _, count = spec.partition(":")
        if not name or not folder:
            raise SystemExit(f"--sets: {item!r} is not NAME=FOLDER[:SCENES]")
        index = Path(folder) / "evaluation_index_standard.json"
        if not index.is_file():
            raise SystemExit(f"--sets: no {index}")
        sets[name] = (Path(folder), index, int(count) if count else None)
    rows, summaries = [], {}
    for ckpt in args.checkpoints:
        model = load_model(ckpt, args.device)
        for name, (folder, index, count) in sets.items():
            readings = read_set(model, as_test_root(folder, out / "roots"), index, count,
                                args.device)
            s = summarise(readings)
            summaries.setdefault(ckpt, {})[name] = s.as_dict()
            rows += [{"checkpoint": ckpt, "set": name, **r.row()} for r in readings]
            print(f"{ckpt} on {name}: {s.line()}", flush=True)
            if args.embedding:
                spread = embedding_spread(model, as_test_root(folder, out / "roots"), index,
                                          count, args.device)
                summaries[ckpt][name]["embedding"] = spread
                print("  " + "; ".join(
                    f"{k}: within a scene {v['within']:.3g}, between scenes {v['between']:.3g},"
                    f" norm {v['norm']:.3g}" for k, v in spread.items()), flush=True)
    with atomic_open(out / "meter.csv", "w") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    write_json(out / "meter.json", summaries)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
