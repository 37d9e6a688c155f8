"""Is there view-specific headroom that a function of the camera can reach? The oracle's
per-target Delta W, fitted on some frames of a path and scored on the frames between them.

``oracle_delta.py`` fits a Delta W per target to the very images it is scored on: an upper
bound that per-image fitting inflates. Here, per scene of ``--split`` (context frames L and
L + G as its index has them; G = 8 in the standard split), the frames between the context views
are split in two: **fit frames** L+1, L+3, ..., **scored frames** L+2, L+4, ... With the
primary network frozen (a trained (a)), on the layers and rank of (c):

- ``shared``: one Delta W fitted to the fit frames (2 x ``--steps`` Adam steps), scored on the
  scored frames: scene-level adaptation;
- ``interpolated``: one Delta W per fit frame (from the shared fit at ``--steps``, ``--steps``
  more: ``oracle_delta.py``'s nested per-target fit); a scored frame takes the mean of its two
  neighbours' Delta W (exact: the concatenated rank-r factors);
- ``linear``: Delta W(t) = D0 + t D1, t the frame's offset from the middle of the gap over G,
  D0 from the shared fit at ``--steps``, D1 from zero (U1 = 0, V1 random), ``--steps`` more:
  Delta W as a function of the camera's position along the path;
- ``in_sample``: the per-fit-frame Delta W scored on the fit frames themselves, against the
  shared fit there: the in-sample headroom on these frames, for comparison.

Per scene the mean over its scored frames; ``summary.json`` has each predictor minus ``shared``
with its Student's t 95% interval over scenes.

    python train/studies/oracle_transfer.py --checkpoint checkpoints/tiny_baseline.pt \\
        --data outputs/big/test2000 --scenes 10 --steps 300 --out outputs/oracle_transfer

One thread; ``per_scene.csv`` after every scene (a killed run resumes from it).
"""

import argparse
import csv
import json
import sys
import time
from pathlib import Path

from oracle_delta import INJECTABLE_ALL, DeltaFit, frozen_baseline, score_targets

from usplat_dr import portable

portable.enable()  # AVX2 code paths, as the usplat command (before torch is imported)

COLUMNS = ("a", "shared", "interpolated", "linear", "in_sample_shared", "in_sample_per_target")


def between_frames_index(index: dict) -> dict:
    """The split's index with every frame between the two context views as a target."""
    out = {}
    for scene, e in index.items():
        if e is None:
            continue
        lo, hi = sorted(e["context"])
        if hi - lo < 4:
            continue  # needs two fit frames around a scored one
        out[scene] = {"context": e["context"], "target": list(range(lo + 1, hi))}
    return out


def fit_transfer(model, batch, specs, rank: int, steps: int, lr: float, seed: int) -> dict:
    """The four predictors' PSNR per frame (module docstring); ``{column: [PSNR, ...]}``."""
    import torch

    from usplat_dr.data.types import model_inputs

    args = model_inputs(batch, "cpu")
    gt = batch["target"]["image"][0]
    n = gt.shape[0]
    fit_idx = list(range(0, n, 2))  # offsets 1, 3, 5, ...
    score_idx = list(range(1, n - 1, 2))  # offsets 2, 4, ... (each between two fit frames)
    lo, hi = sorted(batch["context"]["index"][0].tolist())
    offsets = torch.arange(1, n + 1, dtype=torch.float32)
    t_all = (offsets - (hi - lo) / 2) / (hi - lo)  # -0.5 .. 0.5 along the gap

    def sub(idx):
        i = torch.tensor(idx)
        return args._replace(target_extrinsics=args.target_extrinsics[:, i],
                             target_intrinsics=args.target_intrinsics[:, i],
                             target_near=args.target_near[:, i], target_far=args.target_far[:, i])

    fit_args, score_args = sub(fit_idx), sub(score_idx)
    sub_batch = {"target": {k: v[:, torch.tensor(score_idx)] for k, v in batch["target"].items()
                            if torch.is_tensor(v) and v.ndim >= 2}}
    fit_batch = {"target": {k: v[:, torch.tensor(fit_idx)] for k, v in batch["target"].items()
                            if torch.is_tensor(v) and v.ndim >= 2}}
    with torch.no_grad():
        encoding = model.encode(args.images, args.extrinsics, args.intrinsics, args.near,
                                args.far)

    def render(deltas, a):
        return model(*a, encoding=encoding, delta_w=deltas).color[0]

    def optimise(params, make, a, target, k):
        opt = torch.optim.Adam(params, lr=lr)
        for _ in range(k):
            loss = (render(make(), a) - target).square().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()

    def score(deltas, a, b):
        with torch.no_grad():
            return score_targets(render(deltas, a), b, "all")

    g = torch.Generator().manual_seed(seed)
    m_fit, m_score = len(fit_idx), len(score_idx)
    shared = DeltaFit(specs, 1, rank, g)
    out = {"a": score(shared.deltas(m_score), score_args, sub_batch)}
    optimise(shared.parameters(), lambda: shared.deltas(m_fit), fit_args, gt[fit_idx], steps)
    half = {name: {k: t.detach().clone() for k, t in p.items()}
            for name, p in shared.parts.items()}
    # per fit frame, nested from the shared fit at half-way
    per = shared.spread(m_fit)
    optimise(per.parameters(), lambda: per.deltas(m_fit), fit_args, gt[fit_idx], steps)
    # linear in t: D0 from the shared half-way fit, D1 = U1 V1 from U1 = 0
    lin0 = {name: {k: t.clone().requires_grad_(True) for k, t in p.items()}
            for name, p in half.items()}
    lin1 = DeltaFit(specs, 1, rank, g)

    def linear(ts):
        return linear_deltas(_with_parts(shared, lin0).deltas(1), lin1.deltas(1), ts)

    params = [t for p in lin0.values() for t in p.values()] + lin1.parameters()
    optimise(params, lambda: linear(t_all[fit_idx]), fit_args, gt[fit_idx], steps)
    optimise(shared.parameters(), lambda: shared.deltas(m_fit), fit_args, gt[fit_idx], steps)
    out["shared"] = score(shared.deltas(m_score), score_args, sub_batch)
    dp = per.deltas(m_fit)
    out["interpolated"] = score(midpoints(dp), score_args, sub_batch)
    out["linear"] = score(linear(t_all[score_idx]), score_args, sub_batch)
    out["in_sample_shared"] = score(shared.deltas(m_fit), fit_args, fit_batch)
    out["in_sample_per_target"] = score(dp, fit_args, fit_batch)
    return out


def midpoints(deltas: dict) -> dict:
    """Rank-r Delta W of M frames (layer -> ``LayerDelta``) -> of the M - 1 frames between
    them: (D_j + D_j+1) / 2 exactly, as rank 2r factors (U_j / 2, U_j+1 / 2) and (V_j; V_j+1)."""
    import torch

    from usplat_dr.model.hypernet.hypernetwork import LayerDelta

    out = {}
    for name, d in deltas.items():
        out[name] = LayerDelta(bias=(d.bias[:-1] + d.bias[1:]) / 2,
                               u=torch.cat((d.u[:-1] / 2, d.u[1:] / 2), 2),
                               v=torch.cat((d.v[:-1], d.v[1:]), 1))
    return out


def linear_deltas(d0: dict, d1: dict, ts) -> dict:
    """Delta W(t) = D0 + t D1 for each t of ``ts`` [T] (D0, D1: one-row rank-r ``LayerDelta``s
    per layer), as rank 2r factors (U0, t U1) and (V0; V1): exactly linear in t."""
    import torch

    from usplat_dr.model.hypernet.hypernetwork import LayerDelta

    out, n = {}, len(ts)
    for name, a in d0.items():
        b = d1[name]
        u = torch.cat((a.u.expand(n, -1, -1), ts.view(-1, 1, 1) * b.u.expand(n, -1, -1)), 2)
        v = torch.cat((a.v.expand(n, -1, -1, -1, -1), b.v.expand(n, -1, -1, -1, -1)), 1)
        out[name] = LayerDelta(bias=a.bias + ts.view(-1, 1) * b.bias, u=u, v=v)
    return out


def _with_parts(fit: DeltaFit, parts: dict) -> DeltaFit:
    """A ``DeltaFit`` like ``fit`` holding ``parts``."""
    other = object.__new__(DeltaFit)
    other.specs, other.rank, other.pair_bias = fit.specs, fit.rank, fit.pair_bias
    other.parts = parts
    return other


def t_summary(values: list[float]) -> dict:
    from usplat_dr.evaluation.view_specificity import t_interval

    lo, hi = t_interval(values)
    return {"mean": sum(values) / len(values), "low": lo, "high": hi,
            "scenes_higher": sum(v > 0 for v in values), "scenes": len(values)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", required=True, help="a trained (a), e.g. the shipped one")
    p.add_argument("--data", required=True, help="a held-out synthetic set")
    p.add_argument("--split", default="standard")
    p.add_argument("--scenes", type=int, default=10)
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--rank", type=int, default=4)
    p.add_argument("--lr", type=float, default=1e-2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    from torch.utils.data import default_collate

    from usplat_dr.data.dataset import dataset_from_section
    from usplat_dr.data.view_sampler import read_evaluation_index
    from usplat_dr.evaluation import synthetic_indices
    from usplat_dr.io import atomic_open, write_json
    from usplat_dr.training.checkpoints import training_image_shape

    model = frozen_baseline(p, args.checkpoint)
    specs = tuple(model.conv_spec(name) for name in INJECTABLE_ALL)
    index = between_frames_index(read_evaluation_index(
        synthetic_indices(args.data, [args.split])[args.split]))
    if not index:
        p.error(f"--split {args.split}: no scene of {args.data} has 4 or more frames between "
                f"its context views")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    settings = {k: v for k, v in vars(args).items() if k not in ("scenes", "out")}
    rows = []
    if (out / "per_scene.csv").is_file():  # resume: the same settings only
        old = json.loads((out / "settings.json").read_text())
        if old != settings:
            p.error(f"--out {out} holds a run with other settings ({old}); choose another "
                    f"--out or delete it")
        with open(out / "per_scene.csv") as f:
            rows = [{k: v if k == "scene" else float(v) for k, v in r.items()}
                    for r in csv.DictReader(f)]
    write_json(out / "settings.json", settings)
    done = {r["scene"] for r in rows}
    t0 = time.perf_counter()
    write_json(out / "evaluation_index_between.json", index)
    shape = training_image_shape(args.checkpoint) or (64, 64)
    ds = dataset_from_section({"name": "synth", "roots": [args.data], "image_shape": list(shape),
                               "evaluation_index": str(out / "evaluation_index_between.json")},
                              "test")
    for s, example in enumerate(ds):
        if s == args.scenes:
            break
        if example["scene"] in done:
            continue
        fits = fit_transfer(model, default_collate([example]), specs, args.rank, args.steps,
                            args.lr, args.seed + s)
        rows.append({"scene": example["scene"],
                     **{k: sum(v) / len(v) for k, v in fits.items()}})
        with atomic_open(out / "per_scene.csv", "w") as fo:
            w = csv.DictWriter(fo, fieldnames=["scene", *COLUMNS])
            w.writeheader()
            w.writerows(rows)
        r = rows[-1]
        print(f"[{s + 1}/{args.scenes}] {r['scene']}: "
              + ", ".join(f"{k} {r[k]:.3f}" for k in COLUMNS)
              + f" dB ({time.perf_counter() - t0:.0f} s)", flush=True)
    summary = {
        "settings": vars(args), "scenes": len(rows),
        **{f"psnr_{k}": sum(r[k] for r in rows) / len(rows) for k in COLUMNS},
        "interpolated_minus_shared": t_summary([r["interpolated"] - r["shared"] for r in rows]),
        "linear_minus_shared": t_summary([r["linear"] - r["shared"] for r in rows]),
        "in_sample_per_target_minus_shared": t_summary(
            [r["in_sample_per_target"] - r["in_sample_shared"] for r in rows])}
    write_json(out / "summary.json", summary)
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
