"""How much could a per-target Delta W give at best? An oracle bound, per layer, with the
primary network frozen.

(c) changes the heads' convolutions per target view: W + Delta W, with Delta W = U V (rank r)
or a full matrix, and a bias change, that the view-specific branch predicts from the context
images and the target camera. Whatever that branch learns, its output is some Delta W. This
script finds, for each held-out scene, the best Delta W there is on the layers ``--layer``
names by gradient descent on the target images themselves (which no model sees), on top of a
trained (a) whose own weights stay frozen:

- ``shared``: one Delta W for all the scene's targets (scene-level adaptation, the same for
  every view), 2 x ``--steps`` Adam steps;
- ``per-target``: one Delta W per target view (what view conditioning can express), started
  from the shared fit at ``--steps`` and fitted ``--steps`` more. Every shared Delta W is also
  a per-target one, and both fits take the same steps from the same start, so the comparison
  is nested: per-target minus shared is what making Delta W depend on the view adds beyond
  adapting to the scene, at equal rank;
- ``context``: one Delta W fitted to render the two context views themselves, then scored on
  the targets: test-time adaptation with only what a test gives.

``shared`` and ``per-target`` are fitted to the images they are scored on, so they are upper
bounds, for this layer choice and rank and the frozen primary network; an optimiser that has
not converged understates both (run ``--steps`` 100 / 300 / 1000 on a few scenes: the
convergence check). ``--probe pair-bias`` replaces Delta W by a bias change of
``to_disparity.2`` (disparity and density) per (target, context view) pair, shared against
per target: whether a Delta W per (target, context view) pair would have room. At step 0
(Delta W = 0) each target's PSNR is (a)'s, which the script checks against a plain forward.

    python train/studies/oracle_delta.py --checkpoint checkpoints/tiny_baseline.pt \
        --data outputs/big/test2000 --split standard --scenes 30 --steps 100 \
        --layer all --rank 4 --out outputs/oracle/all_r4

``--between-frames``: is there view-specific headroom that a function of the camera can reach,
or does the per-target fit measure per-image fitting? Per scene of ``--split`` (context frames
L and L + G), the frames between the context views are split in two: **fit frames** L+1, L+3,
..., **scored frames** L+2, L+4, ..., and with the primary network frozen, on the four head
convolutions at rank ``--rank``:

- ``shared``: one Delta W fitted to the fit frames (2 x ``--steps``), scored on the scored
  frames;
- ``interpolated``: one Delta W per fit frame (the nested per-target fit above); a scored frame
  takes the mean of its two neighbours' Delta W (exact: the concatenated rank-r factors);
- ``linear``: Delta W(t) = D0 + t D1, t the frame's offset from the middle of the gap over G,
  D0 from the shared fit at ``--steps``, D1 from zero, ``--steps`` more: Delta W as a function
  of the camera's position along the path;
- ``in_sample``: the per-fit-frame Delta W on the fit frames themselves, against the shared
  fit there.

    python train/studies/oracle_delta.py --between-frames \\
        --checkpoint checkpoints/tiny_baseline.pt --data outputs/big/test2000 --scenes 10 \\
        --steps 300 --out outputs/oracle_transfer/s300

One thread; writes ``<out>/per_target.csv`` after every scene (a killed run resumes from it)
and ``<out>/summary.json`` (each difference with its bootstrap 95% interval over scenes). Two
runs' columns are compared with ``--compare DIR_X:COLUMN DIR_Y:COLUMN``.
"""

import argparse
import csv
import json
import math
import sys
import time
from pathlib import Path

import usplat_dr  # noqa: F401  (libLLVM before drjit)
from usplat_dr import portable
from usplat_dr.model.uniquesplat import StudyHooks

portable.enable()  # AVX2 code paths, as the usplat command (before torch is imported)


MODES = ("shared", "per-target", "context")
#: ``--layer`` values: a convolution of the heads, or ``all`` (every one, as (c) has it)
LAYERS = ("to_gaussians.0", "to_gaussians.2", "to_disparity.0", "to_disparity.2", "all")
INJECTABLE_ALL = LAYERS[:-1]
PROBE_LAYER = "to_disparity.2"  # outputs disparity and density: the probe's layer


class DeltaFit:
    """Trainable Delta W for ``specs``, ``rows`` of them (1: shared by every target).

    Rank-r form (``rank`` an int): U = 0 and the bias change = 0, so the fit starts exactly at
    (a); V random (N(0, 1), scaled by 1/sqrt(fan_in) as (c)'s V is) so that U gets a gradient
    from the first step. Full form (``rank`` None): Delta W = F / sqrt(fan_in), F = 0 at the
    start (the scale of V: unscaled, an Adam step of 1e-2 on every entry of F moved each entry
    of Delta W ~10x more than a step on the rank-4 factors does, and the fit oscillated: on
    the first scene the shared fit fell from +7.3 to +4.4 dB between its 100th and 200th
    step). ``pair_bias``: no weight
    change, a bias change per (target, context view) pair of ``views`` views (the probe)."""

    def __init__(self, specs, rows: int, rank, generator, pair_bias: bool = False,
                 views: int = 2):
        import torch

        self.specs, self.rank, self.pair_bias = specs, rank, pair_bias
        self.parts = {}
        for s in specs:
            o, i, k = s.out_channels, s.in_channels, s.kernel_size
            if pair_bias:
                p = {"bias": torch.zeros(rows, views, o)}
            elif rank is None:
                p = {"full": torch.zeros(rows, o, i, k, k), "bias": torch.zeros(rows, o)}
            else:
                p = {"u": torch.zeros(rows, o, rank),
                     "v": torch.randn(rows, rank, i, k, k, generator=generator),
                     "bias": torch.zeros(rows, o)}
            self.parts[s.name] = {key: t.requires_grad_(True) for key, t in p.items()}

    def parameters(self) -> list:
        return [t for p in self.parts.values() for t in p.values()]

    def spread(self, rows: int) -> "DeltaFit":
        """A copy with every row equal to this (one-row) fit: the nested start of a
        per-target fit from a shared one."""
        other = object.__new__(DeltaFit)
        other.specs, other.rank, other.pair_bias = self.specs, self.rank, self.pair_bias
        other.parts = {name: {key: t.detach().expand(rows, *t.shape[1:]).clone()
                              .requires_grad_(True) for key, t in p.items()}
                       for name, p in self.parts.items()}
        return other

    def deltas(self, m: int) -> dict:
        """layer -> ``LayerDelta`` for ``m`` targets (a shared fit repeated)."""
        import torch

        from usplat_dr.model.hypernet.hypernetwork import LayerDelta

        out = {}
        for s in self.specs:
            p = {key: t if t.shape[0] == m else t.expand(m, *t.shape[1:])
                 for key, t in self.parts[s.name].items()}
            if self.pair_bias:  # a rank-1 zero weight change carries the per-view bias
                out[s.name] = LayerDelta(
                    bias=p["bias"], u=torch.zeros(m, s.out_channels, 1),
                    v=torch.zeros(m, 1, s.in_channels, s.kernel_size, s.kernel_size))
            elif self.rank is None:  # scaled as V is: an Adam step moves Delta W as much
                out[s.name] = LayerDelta(bias=p["bias"], full=p["full"] / math.sqrt(s.fan_in))
            else:
                out[s.name] = LayerDelta(bias=p["bias"], u=p["u"],
                                         v=p["v"] / math.sqrt(s.fan_in))
        return out


def fit_scene(model, batch, specs, rank, steps: int, lr: float, seed: int, modes,
              pair_bias: bool = False, pixels: str = "all") -> dict:
    """PSNR per target before and after fitting Delta W on ``specs``, per mode:

    - ``shared``: one Delta W for every target, fitted to the targets for 2 x ``steps``;
    - ``per-target``: one per target, started from the shared fit after ``steps`` (each
      target's Delta W = the shared one) and fitted ``steps`` more: the same 2 x ``steps``,
      and a model class that contains the shared one (nested);
    - ``context``: one shared Delta W fitted to the two context views for ``steps``, scored on
      the targets (what a test has).

    Returns mode -> {"before", "after"} (PSNR lists over targets, on ``pixels``:
    ``score_targets``); ``shared_half``: the shared fit after ``steps`` (the per-target fit's
    start). Every fit minimises the MSE of whole images."""
    import torch

    from usplat_dr.data.types import model_inputs

    args = model_inputs(batch, "cpu")
    gt = batch["target"]["image"][0]
    n = gt.shape[0]
    with torch.no_grad():  # the primary network is frozen: its encoder runs once per scene
        encoding = model.encode(args.images, args.extrinsics, args.intrinsics, args.near,
                                args.far)

    def render(fit, fit_args):
        deltas = fit.deltas(fit_args.target_intrinsics.shape[1])
        return model(*fit_args, hooks=StudyHooks(encoding=encoding, delta_w=deltas)).color[0]

    def score(fit) -> list[float]:
        with torch.no_grad():
            return score_targets(render(fit, args), batch, pixels)

    def optimise(fit, fit_args, fit_gt, k: int):
        opt = torch.optim.Adam(fit.parameters(), lr=lr)
        for _ in range(k):
            loss = (render(fit, fit_args) - fit_gt).square().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        return fit

    g = torch.Generator().manual_seed(seed)
    out = {}
    if "shared" in modes or "per-target" in modes:
        shared = DeltaFit(specs, 1, rank, g, pair_bias)
        before = score(shared)
        optimise(shared, args, gt, steps)
        out["shared_half"] = {"before": before, "after": score(shared)}
        if "per-target" in modes:
            per = optimise(shared.spread(n), args, gt, steps)
            out["per-target"] = {"before": before, "after": score(per)}
        if "shared" in modes:
            optimise(shared, args, gt, steps)
            out["shared"] = {"before": before, "after": score(shared)}
    if "context" in modes:  # render the context views themselves: what a test has
        fit = DeltaFit(specs, 1, rank, g, pair_bias)
        before = score(fit)
        on_context = args.replaced(  # the context cameras as the targets
            target_extrinsics=args.extrinsics, target_intrinsics=args.intrinsics,
            target_near=args.near, target_far=args.far)
        optimise(fit, on_context, args.images[0], steps)
        out["context"] = {"before": before, "after": score(fit)}
    return out


#: ``--pixels``: where PSNR is measured (material codes of ``usplat synth``'s maps).
PIXELS = ("all", "shiny", "matte")


def score_targets(pred, batch, pixels: str) -> list[float]:
    """PSNR per target of ``pred`` [N, 3, H, W] against the batch's targets, on all pixels or
    on those of shiny (glossy, metal) or matte surfaces (NaN for a target without any)."""
    from usplat_dr.data.synth.render import MATTE, SHINY
    from usplat_dr.evaluation.metrics import psnr
    from usplat_dr.evaluation.protocol import masked_psnr

    gt = batch["target"]["image"][0]
    if pixels == "all":
        return psnr(pred, gt).tolist()
    if "material" not in batch["target"]:
        raise SystemExit(f"--pixels {pixels}: the data have no material maps (a `usplat synth` "
                         f"set has them)")
    return masked_psnr(pred, gt, batch["target"]["material"][0],
                       SHINY if pixels == "shiny" else MATTE)


def frozen_baseline(parser: argparse.ArgumentParser, checkpoint: str):
    """The trained (a) ``checkpoint``, every parameter frozen, torch on one thread; a
    ``parser.error`` for another variant."""
    import torch

    from usplat_dr.training.checkpoints import load_model

    torch.set_num_threads(1)
    model, _ = load_model(checkpoint)
    if model.cfg.variant != "baseline":
        parser.error(f"--checkpoint: a trained (a) (variant baseline), got "
                     f"{model.cfg.variant!r}")
    for q in model.parameters():
        q.requires_grad_(False)
    return model


def offset_index(index: str, offsets: list[int], out: Path) -> str:
    """``index`` (an evaluation index file) with each scene's targets at ``offsets`` from its
    first context frame, written into ``out``; scenes whose gap the offsets leave are
    dropped."""
    from usplat_dr.data.view_sampler import read_evaluation_index
    from usplat_dr.io import write_json

    entries = {}
    for scene, e in read_evaluation_index(index).items():
        if e is None:
            continue
        lo, hi = sorted(e["context"])
        if all(0 < o < hi - lo for o in offsets):
            entries[scene] = {"context": e["context"], "target": [lo + o for o in offsets]}
    if not entries:
        raise SystemExit(f"--targets {offsets}: no scene of {index} has these frames between "
                         f"its context views (offsets must lie in 1..gap-1)")
    out.mkdir(parents=True, exist_ok=True)
    path = out / "evaluation_index_offsets.json"
    write_json(path, entries)
    return str(path)


def rank_arg(text: str):
    """``--rank``: a positive int, or ``full``."""
    if text == "full":
        return None
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"a rank >= 1 or 'full', got {text!r}")
    return int(text)


def resume(out: Path, settings: dict) -> tuple[list, set, float]:
    """Rows, scenes and seconds of an earlier run in ``out`` with the same settings (a killed
    run goes on from its last finished scene); nothing when there is none. A run with other
    settings in ``out`` is an error, not overwritten."""
    progress = out / "progress.json"
    if not progress.is_file():
        return [], set(), 0.0
    old = json.loads(progress.read_text())
    seconds = old.pop("seconds", 0.0)
    if old != settings:
        raise SystemExit(f"--out {out} holds a run with other settings ({progress}); choose "
                         f"another --out or delete it")
    with open(out / "per_target.csv") as f:
        rows = [{k: v if k == "scene" else int(v) if k == "target" else float(v)
                 for k, v in r.items()} for r in csv.DictReader(f)]
    print(f"resuming {out}: {len({r['scene'] for r in rows})} scenes done", flush=True)
    return rows, {r["scene"] for r in rows}, seconds


def paired(rows_x: list, x: str, rows_y: list, y: str) -> dict:
    """Column ``x`` of ``rows_x`` minus column ``y`` of ``rows_y`` (per_target.csv rows), paired
    by scene (the mean of its targets): the mean over scenes, its bootstrap 95% interval over
    scenes (``usplat_dr.evaluation.verdict.bootstrap_interval``) and the scenes where x is
    higher."""
    import numpy as np

    from usplat_dr.evaluation import nan_mean
    from usplat_dr.evaluation.verdict import bootstrap_interval

    def by_scene(rows, col):
        out: dict[str, list[float]] = {}
        for r in rows:
            out.setdefault(r["scene"], []).append(float(r[col]))
        return {k: nan_mean(v) for k, v in out.items()}  # NaN: no such pixels

    a, b = by_scene(rows_x, x), by_scene(rows_y, y)
    if set(a) != set(b):
        raise SystemExit(f"{x} and {y}: the two tables hold different scenes")
    d = np.array([[a[k] - b[k] for k in sorted(a)]])
    d = d[:, ~np.isnan(d[0])]  # scenes without pixels of the measured kind
    if d.size == 0:
        return {"mean": float("nan"), "low": float("nan"), "high": float("nan"),
                "scenes_higher": 0, "scenes": 0}
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


#: ``--between-frames``' columns: (a), the three predictors, the in-sample pair
BETWEEN_COLUMNS = ("a", "shared", "interpolated", "linear", "in_sample_shared",
                   "in_sample_per_target")


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


def fit_transfer(model, batch, specs, rank: int, steps: int, lr: float, seed: int,
                 pixels: str = "all") -> dict:
    """The four predictors' PSNR per frame (module docstring); ``{column: [PSNR, ...]}``, on
    ``pixels`` (``--pixels``: the fits minimise whole-image error either way)."""
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
        return args.replaced(target_extrinsics=args.target_extrinsics[:, i],
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
        return model(*a, hooks=StudyHooks(encoding=encoding, delta_w=deltas)).color[0]

    def optimise(params, make, a, target, k):
        opt = torch.optim.Adam(params, lr=lr)
        for _ in range(k):
            loss = (render(make(), a) - target).square().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()

    def score(deltas, a, b):
        with torch.no_grad():
            return score_targets(render(deltas, a), b, pixels)

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
    """Mean and 95% t interval over scenes; scenes whose value is NaN (no pixels of the
    measured kind, ``--pixels``) are left out."""
    from usplat_dr.evaluation.verdict import t_interval

    values = [v for v in values if not math.isnan(v)]
    lo, hi = t_interval(values)
    return {"mean": sum(values) / len(values), "low": lo, "high": hi,
            "scenes_higher": sum(v > 0 for v in values), "scenes": len(values)}


def run_between(args, p: argparse.ArgumentParser) -> int:
    """``--between-frames``: the held-out-frame oracle (``fit_transfer``) over ``--scenes``
    scenes; ``per_scene.csv`` after every scene (resumable with the same settings),
    ``summary.json`` with each predictor minus ``shared`` and its t interval over scenes."""
    if args.rank is None:
        p.error("--between-frames fits rank-r Delta W: give --rank N")
    from torch.utils.data import default_collate

    from usplat_dr.data.dataset import dataset_from_section
    from usplat_dr.data.view_sampler import read_evaluation_index
    from usplat_dr.evaluation import nan_mean, synthetic_indices
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
    settings = {k: getattr(args, k) for k in ("checkpoint", "data", "split", "steps", "rank",
                                              "lr", "seed")}
    if args.pixels != "all":  # (absent for all pixels: earlier runs keep resuming)
        settings["pixels"] = args.pixels
    rows = []
    if (out / "per_scene.csv").is_file():  # resume: the same settings only
        saved = out / "settings.json"  # (runs from before it was written: taken as theirs)
        old = json.loads(saved.read_text()) if saved.is_file() else settings
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
        if example["scene"] in done or s < args.skip_first:
            continue
        fits = fit_transfer(model, default_collate([example]), specs, args.rank, args.steps,
                            args.lr, args.seed + s, args.pixels)
        rows.append({"scene": example["scene"], **{k: nan_mean(v) for k, v in fits.items()}})
        with atomic_open(out / "per_scene.csv", "w") as fo:
            w = csv.DictWriter(fo, fieldnames=["scene", *BETWEEN_COLUMNS])
            w.writeheader()
            w.writerows(rows)
        r = rows[-1]
        print(f"[{s + 1}/{args.scenes}] {r['scene']}: "
              + ", ".join(f"{k} {r[k]:.3f}" for k in BETWEEN_COLUMNS)
              + f" dB ({time.perf_counter() - t0:.0f} s)", flush=True)
    summary = {
        "settings": vars(args), "scenes": len(rows),
        **{f"psnr_{k}": nan_mean([r[k] for r in rows]) for k in BETWEEN_COLUMNS},
        "interpolated_minus_shared": t_summary([r["interpolated"] - r["shared"] for r in rows]),
        "linear_minus_shared": t_summary([r["linear"] - r["shared"] for r in rows]),
        "in_sample_per_target_minus_shared": t_summary(
            [r["in_sample_per_target"] - r["in_sample_shared"] for r in rows])}
    write_json(out / "summary.json", summary)
    print(json.dumps(summary, indent=1))
    return 0



def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--compare", nargs=2, metavar="DIR:COLUMN",
                   help="instead, the paired difference of two runs' columns (e.g. "
                        "outputs/oracle:per_target outputs/oracle_r12_standard:shared)")
    p.add_argument("--checkpoint", help="a trained (a), e.g. the shipped one")
    p.add_argument("--data", help="a held-out synthetic set")
    p.add_argument("--split", default="standard")
    p.add_argument("--scenes", type=int, default=30)
    p.add_argument("--skip-first", type=int, default=0, metavar="K",
                   help="leave the first K of the --scenes to another process (each scene's "
                        "seed is --seed + its position, so two processes with --skip-first 0 "
                        "--scenes K and --skip-first K give the rows one process would); "
                        "merge their per_target.csv files, then rerun with --skip-first 0 "
                        "to write the summary")
    p.add_argument("--layer", nargs="+", choices=LAYERS, default=["all"],
                   help="the convolutions that take Delta W (all: both heads' four, as (c))")
    p.add_argument("--rank", type=rank_arg, default=4,
                   help="rank of Delta W (tiny (c): 4), or full (a full Delta W per view)")
    p.add_argument("--probe", choices=("pair-bias",),
                   help="instead of Delta W: a bias change of " + PROBE_LAYER + " (disparity "
                        "and density) per (target, context view) pair")
    p.add_argument("--steps", type=int, default=100,
                   help="Adam steps per fit: the shared fit runs 2x, the per-target one starts "
                        "from it at half-way (nested), the context fit runs 1x")
    p.add_argument("--lr", type=float, default=1e-2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    p.add_argument("--pixels", choices=PIXELS, default="all",
                   help="where PSNR is measured: all pixels, or those of shiny (glossy, metal) "
                        "or matte surfaces (synthetic sets; the fits use whole images)")
    p.add_argument("--targets", nargs="+", type=int, metavar="OFFSET",
                   help="target frames as offsets from each scene's first context frame "
                        "instead of the index's (e.g. 1 4 7: spread over the standard split's "
                        "gap of 8, where the index has 3 4 5)")
    p.add_argument("--between-frames", action="store_true",
                   help="instead, the oracle fitted on some frames of a path and scored on the "
                        "frames between them (shared, interpolated, linear in the camera's "
                        "position; the module docstring)")
    p.add_argument("--out")
    args = p.parse_args(argv)
    if args.compare:
        print(json.dumps(compare(*args.compare), indent=1))
        return 0
    for name in ("checkpoint", "data", "out"):
        if getattr(args, name) is None:
            p.error(f"--{name} is required (unless --compare)")
    if args.between_frames:
        return run_between(args, p)
    layers = INJECTABLE_ALL if "all" in args.layer else tuple(dict.fromkeys(args.layer))
    if args.probe:
        layers = (PROBE_LAYER,)
        if "context" in args.modes:
            p.error("--probe pair-bias compares shared and per-target fits: drop context from "
                    "--modes")
    import torch
    from torch.utils.data import default_collate

    from usplat_dr.data.dataset import dataset_from_section
    from usplat_dr.data.types import model_inputs
    from usplat_dr.evaluation import nan_mean, synthetic_indices
    from usplat_dr.io import atomic_open, write_json
    from usplat_dr.training.checkpoints import training_image_shape

    model = frozen_baseline(p, args.checkpoint)
    specs = tuple(model.conv_spec(name) for name in layers)
    shape = training_image_shape(args.checkpoint) or (64, 64)
    index = synthetic_indices(args.data, [args.split])[args.split]
    if args.targets:
        index = offset_index(index, args.targets, Path(args.out))
    ds = dataset_from_section({"name": "synth", "roots": [args.data],
                               "image_shape": list(shape), "evaluation_index": index}, "test")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    settings = {"checkpoint": args.checkpoint, "data": args.data, "split": args.split,
                "layers": list(layers), "rank": "full" if args.rank is None else args.rank,
                "probe": args.probe, "steps": args.steps, "lr": args.lr, "seed": args.seed,
                "modes": args.modes, "primary_network": "frozen",
                **({"targets": args.targets} if args.targets else {}),
                **({"pixels": args.pixels} if args.pixels != "all" else {})}
    rows, done, seconds = resume(out, settings)
    t0 = time.perf_counter() - seconds
    for s, example in enumerate(ds):
        if s == args.scenes:
            break
        if example["scene"] in done or s < args.skip_first:
            continue
        batch = default_collate([example])
        with torch.no_grad():  # (a) as `usplat eval` runs it: the step-0 check's reference
            plain = score_targets(model(*model_inputs(batch, "cpu")).color[0], batch,
                                  args.pixels)
        fits = fit_scene(model, batch, specs, args.rank, args.steps, args.lr, args.seed + s,
                         args.modes, args.probe == "pair-bias", args.pixels)
        for j, ref in enumerate(plain):
            for mode, f in fits.items():
                # Delta W = 0 renders (a): the same up to the rank-r path's float rounding
                # (1e-3 dB: measured differences are ~1e-5 dB; a wrong path is off by dBs)
                if abs(f["before"][j] - ref) > 1e-3:  # (NaN: no such pixels, passes)
                    raise SystemExit(f"scene {example['scene']} target {j}: {mode} at step 0 "
                                     f"{f['before'][j]:.4f} dB, (a) {ref:.4f} dB")
            rows.append({"scene": example["scene"], "target": j, "a": ref,
                         **{m.replace("-", "_"): f["after"][j] for m, f in fits.items()}})
        keys = [k for k in rows[0] if k not in ("scene", "target")]
        mean = {k: nan_mean([r[k] for r in rows]) for k in keys}
        elapsed = time.perf_counter() - t0
        with atomic_open(out / "per_target.csv", "w") as f:  # after every scene: resumable
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
        write_json(out / "progress.json", {**settings, "seconds": elapsed})
        print(f"[{s + 1}/{args.scenes}] {example['scene']}: "
              + ", ".join(f"{k} {mean[k]:.3f}" for k in keys) + f" dB ({elapsed:.0f} s)",
              flush=True)
    keys = [k for k in rows[0] if k not in ("scene", "target")]
    diffs = [(k, "a") for k in keys[1:]]
    if "shared" in keys and "per_target" in keys:
        diffs.append(("per_target", "shared"))
    summary = {
        **settings, "scenes": len({r["scene"] for r in rows}), "targets": len(rows),
        **{f"psnr_{k}": nan_mean([r[k] for r in rows]) for k in keys},
        **{f"{x}_minus_{y}": paired(rows, x, rows, y) for x, y in diffs},
        "seconds": time.perf_counter() - t0}
    write_json(out / "summary.json", summary)
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
