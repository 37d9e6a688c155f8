"""Evaluation with the field's protocol (docs/field_protocol.md, "Evaluation"): fixed context/target
frames from an evaluation index, metrics per target view, the mean over a scene's targets,
then the mean over scenes. PSNR on clipped images, SSIM with scikit-image (window 11,
Gaussian weights, data range 1), LPIPS-VGG when its weight files are given (else reported as
unavailable, never as a number); on synthetic sets also depth metrics against the ground
truth (AbsRel, RMSE, delta < 1.25 on pixels the prediction covers, alpha > 0.5) and PSNR on the
pixels of shiny (glossy or metallic) and of matte surfaces (``psnr_shiny``, ``psnr_matte``:
the MSE over a target's pixels of that class; NaN where a target has none).

Writes ``per_scene.csv``, ``summary.json`` (per split, plus parameters, inference time per
scene and peak memory) and, for the first ``images_per_split`` scenes of each split, a PNG of
context | ground truth | prediction | depth.
"""

import csv
import json
import logging
import resource
import shutil
import statistics
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import default_collate
from tqdm import tqdm

from usplat_dr.data.dataset import dataset_from_section
from usplat_dr.data.synth.render import MATTE, SHINY
from usplat_dr.data.types import model_inputs
from usplat_dr.data.view_sampler import read_evaluation_index
from usplat_dr.evaluation import view_specificity
from usplat_dr.evaluation.allocation import COLUMNS as ALLOCATION_COLUMNS
from usplat_dr.evaluation.allocation import allocation, kept_per_pixel, save_allocation
from usplat_dr.evaluation.baselines import copy_nearest
from usplat_dr.evaluation.figures import save_comparison
from usplat_dr.evaluation.metrics import psnr, ssim
from usplat_dr.evaluation.provenance import keys_in_training
from usplat_dr.io import atomic_open, write_json
from usplat_dr.model.auto_budget import AutoBudget, make_budget
from usplat_dr.model.budget import GaussianBudget

log = logging.getLogger(__name__)


def nan_mean(values) -> float:
    """Mean of the finite-or-inf values, NaN (without NumPy's "Mean of empty slice" warning)
    when every value is NaN: a scene whose targets cover no ground-truth pixel has no depth
    error."""
    a = np.asarray(values, dtype=np.float64)
    a = a[~np.isnan(a)]
    return float(a.mean()) if a.size else float("nan")


def depth_scored_pixels(alpha: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """The pixels the depth metrics score: finite positive ground truth that the prediction
    covers (alpha > 0.5). Training's target-view depth loss uses the same pixels."""
    return torch.isfinite(gt) & (gt > 0) & (alpha > 0.5)


def depth_metrics(pred_depth: torch.Tensor, alpha: torch.Tensor, gt: torch.Tensor) -> dict:
    """AbsRel, RMSE and delta < 1.25 over ``depth_scored_pixels``; the rasteriser's depth is
    alpha-weighted, so divide by alpha."""
    mask = depth_scored_pixels(alpha, gt)
    if mask.sum() == 0:
        return {"abs_rel": float("nan"), "rmse": float("nan"), "delta1": float("nan")}
    d = (pred_depth / alpha.clamp(min=1e-6))[mask].double()
    g = gt[mask].double()
    ratio = torch.maximum(d / g, g / d)
    return {"abs_rel": ((d - g).abs() / g).mean().item(),
            "rmse": (d - g).square().mean().sqrt().item(),
            "delta1": (ratio < 1.25).double().mean().item()}


def masked_psnr(pred: torch.Tensor, gt: torch.Tensor, material: torch.Tensor,
                codes: tuple[int, ...]) -> list[float]:
    """PSNR per target ([N, 3, H, W] images in [0, 1], clipped) over the pixels whose
    ``material`` code [N, H, W] is one of ``codes``; NaN for a target without such pixels."""
    mask = torch.zeros_like(material, dtype=torch.bool)
    for c in codes:
        mask |= material == c
    err = (pred.clamp(0, 1) - gt).square().mean(1)  # [N, H, W]
    out = []
    for e, m in zip(err, mask):
        n = int(m.sum())
        out.append(float("nan") if n == 0 else
                   -10.0 * torch.log10(e[m].double().mean().clamp(min=1e-12)).item())
    return out


def peak_memory_gib(device: torch.device) -> float:
    """The process's peak memory so far: CUDA's allocator peak, or the peak RSS on CPU."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**30
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


#: What an evaluation writes in its folder: ``summary.json`` last (a folder with it holds one
#: complete run), ``per_scene.csv`` before it, render and allocation images before those.
RESULT_FILES = ("summary.json", "per_scene.csv")
RESULT_FOLDERS = ("renders", "allocation")


def clear_earlier_results(out: Path) -> None:
    """An earlier evaluation's results in ``out`` removed before a new one starts (its
    ``summary.json`` first): a run killed midway then leaves no earlier ``summary.json`` beside
    its own ``per_scene.csv`` or renders, so a folder with a ``summary.json`` always holds one
    run's files. Only a folder holding an evaluation's files is cleared, and only those."""
    if not any((out / name).is_file() for name in RESULT_FILES):
        return
    for name in RESULT_FILES:
        (out / name).unlink(missing_ok=True)
    for name in RESULT_FOLDERS:
        folder = out / name
        if folder.is_dir() and not folder.is_symlink():
            shutil.rmtree(folder)


@torch.no_grad()
def evaluate(model, dataset: dict, indices: dict[str, str], out: str | Path,
             lpips=None, device: torch.device | str = "cpu", images_per_split: int = 4,
             progress: bool = True, label: str = "", prune=None,
             provenance: dict | None = None, budget=None, rank_by: str | None = None,
             view_meter: bool | tuple[str, ...] = True) -> dict:
    """Evaluate ``model`` on each split (``indices``: split name -> evaluation index JSON) of
    ``dataset`` (a config section: name, roots, image_shape). Returns the summary.

    ``prune``: a ``PruneSettings`` applied per target before rendering, or ``None`` (the
    default: the protocol's numbers come from the exact model); the summary records it.
    ``budget`` and ``rank_by``: keep that many Gaussians per target (a count or a fraction;
    ``UniqueSplat.forward``), recorded in the summary as ``gaussians`` and ``rank_by``; then
    where the budget goes (``evaluation.allocation``: the kept fraction on textured and plain
    surfaces, near and far) is in ``per_scene.csv``, per split and scene kind in the summary
    (``allocation``), and as images in ``allocation/<split>/``.

    ``provenance``: the checkpoint's provenance record; when it lists the training scenes
    (``train_keys``), scored scenes among them are a warning (one line: the count and the
    first) and the summary's ``scenes_in_training_data``. An evaluation index none of whose
    keys names a scene of the data is a warning too.

    ``view_meter`` (True: every split; a tuple: those splits; False: none): for a model with
    a view-specific branch (and no budget or pruning), the view-specificity meter
    (``evaluation.view_specificity``) on every scene with >= 2 targets:
    ``view_spread``, ``view_psnr_mean``, ``view_psnr_abs`` and ``view_psnr_zero`` in
    ``per_scene.csv``, the summary's ``view_specificity`` per split, and a line in the log.
    It renders each scene three more times."""
    device = torch.device(device)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    clear_earlier_results(out)
    model = model.to(device).eval()
    keep = make_budget(budget, rank_by)  # checked before any scene is read
    # The view-specificity meter for a (c), on the exact model (no budget, no pruning)
    metered = (bool(view_meter) and getattr(model, "specific", None) is not None
               and budget is None and prune is None)
    rows, summary, times = [], {"splits": {}}, []
    scored_keys: set[str] = set()  # the data's scene keys scored, over every split
    for split, index in indices.items():
        ds = dataset_from_section({**dataset, "evaluation_index": index}, "test")
        warn_unmatched_index(ds, split, index)
        scenes, readings = [], []
        meter = metered and (view_meter is True or split in view_meter)
        bar = None
        if progress:
            bar = tqdm(desc=f"eval {label} {split}".strip(), unit="scene", dynamic_ncols=True)
        for i, example in enumerate(ds):
            batch = default_collate([example])
            t0 = time.perf_counter()
            result = model(*model_inputs(batch, device), prune=prune, budget=keep)
            times.append(time.perf_counter() - t0)
            gt = batch["target"]["image"][0].to(device)
            pred = result.color[0]
            per = {"psnr": psnr(pred, gt), "ssim": ssim(pred, gt)}
            if lpips is not None:
                per["lpips"] = lpips(pred.clamp(0, 1), gt)
            row = {"split": split, "scene": example["scene"], "targets": len(gt),
                   **{k: v.mean().item() for k, v in per.items()}}
            # the trivial predictor: each target as the context photo nearest it
            copied = copy_nearest(batch["context"]["image"][0].to(device),
                                  batch["context"]["extrinsics"][0],
                                  batch["target"]["extrinsics"][0])
            row["psnr_copy"] = psnr(copied, gt).mean().item()
            row["psnr_over_copy"] = row["psnr"] - row["psnr_copy"]
            if "depth" in batch["target"]:
                dm = [depth_metrics(result.depth[0, j].cpu(), result.alpha[0, j].cpu(),
                                    batch["target"]["depth"][0, j]) for j in range(len(gt))]
                for key in ("abs_rel", "rmse", "delta1"):
                    row[key] = nan_mean([d[key] for d in dm])
            if keep is not None:
                row["gaussians_kept"] = int(result.aux["kept"][0].float().mean())
                row["gaussians_rendered"] = float(result.aux["rendered"][0].float().mean())
            if "auto_keep" in result.aux:
                row["auto_keep"] = float(result.aux["auto_keep"][0])
                row["gaussians_total"] = int(result.aux["auto_total"])
            if "kept_mask" in result.aux:  # where a budget went (evaluation.allocation)
                v, h, w = batch["context"]["image"].shape[1], *gt.shape[-2:]
                kept = kept_per_pixel(result.aux["kept_mask"].cpu(), v, h, w)
                row.update(allocation(kept, batch["context"].get("material", [None])[0],
                                      batch["context"].get("depth", [None])[0]))
                if i < images_per_split:
                    save_allocation(out / "allocation" / split, batch, kept)
            if "material" in batch["target"]:
                material = batch["target"]["material"][0].to(device)
                for key, codes in (("psnr_shiny", SHINY), ("psnr_matte", MATTE)):
                    row[key] = nan_mean(masked_psnr(pred, gt, material, codes))
            if meter and len(gt) >= 2:
                reading = view_specificity.read_batch(model, batch, device)[0]
                readings.append(reading)
                row.update(view_spread=max(reading.spread.values()),
                           view_psnr_mean=reading.d_mean, view_psnr_abs=reading.d_mean_abs,
                           view_psnr_zero=reading.d_zero)
            rows.append(row)
            scenes.append(row)
            if i < images_per_split:
                save_comparison(out / "renders" / split, batch, result)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(psnr=f"{statistics.mean(r['psnr'] for r in scenes):.2f}")
        if bar is not None:
            bar.close()
        metrics = {}
        for key in ("psnr", "ssim", "lpips", "abs_rel", "rmse", "delta1", "psnr_shiny",
                    "psnr_matte", "psnr_copy", "psnr_over_copy"):
            vals = [r[key] for r in scenes if key in r]
            metrics[key] = nan_mean(vals) if vals else None
        if lpips is None:
            metrics["lpips"] = "unavailable (no LPIPS weight files given)"
        metrics["scenes_over_copy"] = sum(r["psnr_over_copy"] > 0 for r in scenes)
        if any("kept" in r for r in scenes):
            metrics["allocation"] = allocation_summary(scenes)
        for key in ("auto_keep", "gaussians_kept", "gaussians_rendered", "gaussians_total"):
            vals = [r[key] for r in scenes if key in r]
            if vals:  # a budget's mean count per scene (the automatic one's fraction)
                metrics[f"mean_{key}"] = statistics.mean(vals)
        if readings:
            reading = view_specificity.summarise(readings)
            metrics["view_specificity"] = reading.as_dict()
            log.info("%s: %s", split, reading.line())
        summary["splits"][split] = {"scenes": len(scenes), **metrics,
                                    **index_coverage(index, [r["scene"] for r in scenes])}
        if scenes:
            log.info("%s", copy_line(split, summary["splits"][split]))
        coverage = summary["splits"][split]
        if coverage["failed"]:
            log.warning("%s: %s (first: %s)", split, coverage["coverage"],
                        ", ".join(coverage["failed_scenes"][:5]))
        scored_keys |= scene_keys(ds, [r["scene"] for r in scenes])
    leaked = keys_in_training(scored_keys, provenance or {})
    if leaked:
        log.warning("%d evaluated scene(s) are in the checkpoint's training data (first: %s): "
                    "their scores are not held out", len(leaked), leaked[0])
    if leaked is not None:
        summary["scenes_in_training_data"] = len(leaked)
    steady = times[1:] if len(times) > 1 else times  # the first scene warms up kernels
    summary.update(
        parameters=sum(p.numel() for p in model.parameters()),
        variant=model.cfg.variant, prune=prune.label() if prune is not None else "none",
        gaussians=budget_record(keep),
        rank_by=None if keep is None else (keep.rank_by or (
            "learned" if getattr(model, "importance", None) is not None
            and not isinstance(keep, AutoBudget) else "dither")),  # auto: dither by default
        precision=getattr(model, "inference_precision", "float32"),
        image_shape=list(dataset.get("image_shape", ())),
        time_per_scene_s=statistics.median(steady) if steady else None,
        peak_memory_gib=peak_memory_gib(device), device=str(device))
    fields = ["split", "scene", "targets", "psnr", "ssim", "lpips", "abs_rel", "rmse", "delta1",
              "psnr_shiny", "psnr_matte", "psnr_copy", "psnr_over_copy"]
    if metered:
        fields += ["view_spread", "view_psnr_mean", "view_psnr_abs", "view_psnr_zero"]
    if keep is not None:
        fields += ["gaussians_kept", "gaussians_rendered"]
    if isinstance(keep, AutoBudget):
        fields += ["auto_keep", "gaussians_total"]
    if any("kept" in r for r in rows):
        fields += list(ALLOCATION_COLUMNS)
    with atomic_open(out / "per_scene.csv", "w") as f:
        w = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    write_json(out / "summary.json", summary)
    log.info("evaluation summary: %s", json.dumps(summary["splits"]))
    return summary


def copy_line(split: str, metrics: dict) -> str:
    """One line: a split's PSNR against copying the nearest context view.

    Examples:
        >>> copy_line("standard", {"psnr": 25.6, "psnr_copy": 19.96, "psnr_over_copy": 5.64,
        ...                        "scenes_over_copy": 58, "scenes": 60})
        'standard: 25.60 dB, copying the nearest view 19.96: +5.64 dB (wins 58 of 60 scenes)'
    """
    return (f"{split}: {metrics['psnr']:.2f} dB, copying the nearest view "
            f"{metrics['psnr_copy']:.2f}: {metrics['psnr_over_copy']:+.2f} dB "
            f"(wins {metrics['scenes_over_copy']} of {metrics['scenes']} scenes)")


def budget_record(keep: GaussianBudget | AutoBudget | None):
    """The summary's ``gaussians``: ``"all"``, the count or fraction kept, or the automatic
    count's settings.

    Examples:
        >>> budget_record(None), budget_record(GaussianBudget(0.3))
        ('all', 0.3)
        >>> budget_record(AutoBudget())
        {'auto': {'tolerance_db': 0.2, 'merge': True}}
    """
    if keep is None:
        return "all"
    if isinstance(keep, AutoBudget):
        return {"auto": {"tolerance_db": keep.tolerance, "merge": keep.merge}}
    return keep.keep


def allocation_summary(scenes: list[dict]) -> dict:
    """The mean of each ``allocation`` column over the scenes, and per scene kind (the scene
    name's prefix before ``_``: ``indoor``, ``outdoor``, ``object`` for synthetic sets)."""
    def means(rows):
        return {c: nan_mean([r[c] for r in rows if c in r]) for c in ALLOCATION_COLUMNS
                if any(c in r for r in rows)}

    kinds = sorted({r["scene"].split("_")[0] for r in scenes})
    return {"all": means(scenes),
            **{k: means([r for r in scenes if r["scene"].split("_")[0] == k]) for k in kinds}}


def scene_keys(ds, scored: list[str]) -> set[str]:
    """The scene keys of ``ds``'s data behind the scored example names ``scored``."""
    done = set(scored)
    return {k for k in ds.index if any(r in done for r in ds.run_names(k))}


def warn_unmatched_index(ds, split: str, index: str | Path) -> None:
    """Warn (one line) when no key of the evaluation index names a scene of ``ds``'s data:
    the split would score nothing (another dataset's index, or a preset whose example
    names differ from the index's, as DTU's ``<scan>_NN`` runs)."""
    entries = read_evaluation_index(index)
    names = {r for k in ds.index for r in ds.run_names(k)}
    if entries and ds.index and not names & set(entries):
        log.warning("%s: evaluation index %s matches no scene of the data (%d keys, e.g. %s; "
                    "the data's %d scenes are named e.g. %s): nothing to score", split, index,
                    len(entries), next(iter(entries)), len(names), min(names))


def index_coverage(index: str | Path, scored: list[str]) -> dict:
    """What an evaluation index asked for and what was scored: ``keys`` in the index,
    ``null`` entries (the index's own "not evaluated"), ``failed`` keys with an entry that
    were not scored (not in the data, or skipped: the dataset's warnings say why) and the
    first 20 of them by name, and a one-line ``coverage``."""
    entries = read_evaluation_index(index)
    done = set(scored)
    null = sum(1 for v in entries.values() if v is None)
    failed = [k for k, v in entries.items() if v is not None and k not in done]
    return {"keys": len(entries), "null": null, "failed": len(failed),
            "failed_scenes": failed[:20],
            "coverage": f"scored {len(done):,} of {len(entries):,} keys: {null:,} null, "
                        f"{len(failed):,} failed"}


def synthetic_indices(root: str | Path, splits=None) -> dict[str, str]:
    """The evaluation indices ``usplat synth`` wrote (``evaluation_index_<split>.json``)."""
    found = {p.stem.removeprefix("evaluation_index_"): str(p)
             for p in sorted(Path(root).glob("evaluation_index_*.json"))}
    if splits:
        missing = sorted(set(splits) - set(found))
        if missing:
            raise FileNotFoundError(f"no evaluation index for split(s) {missing} in {root} "
                                    f"(found {sorted(found)})")
        found = {s: found[s] for s in splits}
    # skip splits without scenes
    return {s: p for s, p in found.items()
            if any(v is not None for v in read_evaluation_index(p).values())}


def held_out_scenes(root: str | Path, split: str = "standard", count: int | None = None,
                    size: int = 64) -> tuple[dict, str, list[str]]:
    """A synthetic held-out set's split for a study: the dataset section (images at
    ``size`` x ``size``), the split's index and the first ``count`` scenes it scores (all of
    them for ``None``), in the index's order; ``load_example(dataset, index, scene)`` reads one.
    """
    index = synthetic_indices(root, [split])[split]
    scenes = [k for k, v in read_evaluation_index(index).items() if v is not None]
    dataset = {"name": "synth", "roots": [str(root)], "image_shape": [size, size]}
    return dataset, index, scenes[:count]


def load_example(dataset: dict, index: str, scene: str | None = None) -> dict:
    """One evaluation example as a batch of 1: ``scene`` (default: the index's first)."""
    ds = dataset_from_section({**dataset, "evaluation_index": index}, "test")
    for example in ds:
        if scene is None or example["scene"] == scene:
            return default_collate([example])
    raise ValueError(f"scene {scene!r} is not in {dataset['roots']} with index {index} (or it "
                   f"was skipped; see the dataset summary above)")
