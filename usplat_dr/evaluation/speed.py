"""Speed against accuracy, measured: each model's time per rendered novel view (wall and
process CPU time, the rendering's share alone), peak memory, Gaussians rendered and accuracy
(PSNR, SSIM, depth AbsRel) on a held-out set's scenes, configurations interleaved scene by
scene; across pruning settings, render sizes and Gaussian budgets (``measure``), and the two
decisions read from the rows (``choose``). ``usplat bench`` and ``usplat demo`` run it;
``usplat_dr.jobs.report.write_results`` writes its files. Method and axes: the ``usplat
bench`` module's docstring (usplat_dr/jobs/bench.py)."""

import ctypes
import logging
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from torch.utils.data import default_collate
from tqdm import tqdm

from usplat_dr.data.dataset import dataset_from_section
from usplat_dr.data.types import model_inputs
from usplat_dr.evaluation.metrics import psnr, ssim
from usplat_dr.evaluation.protocol import depth_metrics, nan_mean, synthetic_indices
from usplat_dr.geometry.cameras import Cameras
from usplat_dr.model.auto_budget import AutoBudget
from usplat_dr.model.budget import RANKINGS, GaussianBudget
from usplat_dr.model.uniquesplat import DEFAULT_INFERENCE_PRUNE, PRESETS, StudyHooks
from usplat_dr.render.prune import PRUNES

log = logging.getLogger(__name__)

LETTERS = {"baseline": "a", "agnostic": "b", "full": "c"}
#: The decision rules (train/bench/README.md, "Speed against accuracy: `usplat bench`"): a pruning
#: setting is safe where it costs < 0.05 dB (on by default only if it also saves time, which on
#: CPU none does: "Pruning that pays"); the demo's preset is the smallest configuration within
#: 0.3 dB of the best.
SAFE_PRUNE_DB = 0.05
PRESET_WITHIN_DB = 0.3


@dataclass(frozen=True)
class BenchConfig:
    preset: str
    variant: str
    tag: str = ""  # a model given by --checkpoint (e.g. "budget"), beside the trained ones

    @property
    def label(self) -> str:
        return f"{self.preset} ({LETTERS[self.variant]})" + (f" {self.tag}" if self.tag else "")

    def run_dir(self, out: Path) -> Path:
        # the demo's runs (tiny preset) are train_<variant>: shared
        name = self.variant if self.preset == "tiny" else f"{self.preset}_{self.variant}"
        return out / f"train_{name}"

    @classmethod
    def parse(cls, text: str, tag: str = "") -> "BenchConfig":
        """``preset:variant`` (variant: baseline/agnostic/full or a/b/c)."""
        preset, _, variant = text.partition(":")
        variant = {v: k for k, v in LETTERS.items()}.get(variant, variant)
        if preset not in PRESETS or variant not in LETTERS:
            raise ValueError(f"--configs: {text!r} is not preset:variant with preset in "
                             f"{sorted(PRESETS)} and variant in {sorted(LETTERS)} or a/b/c")
        return cls(preset, variant, tag)


#: Variants (a)/(b)/(c) at the tiny size, and the size axis for the method (c): on 2 CPU cores
#: the paper preset trains at ~1 s a step at 64x64 (small 0.55 s, tiny 0.33 s).
DEFAULT_CONFIGS = tuple(BenchConfig.parse(c) for c in (
    "tiny:a", "tiny:b", "tiny:c", "small:c", "paper:c"))


class PeakMemory:
    """Peak memory of a block: CUDA allocator peak, or on Linux the rise of the process's peak
    RSS (VmHWM, reset by writing 5 to /proc/self/clear_refs) after glibc's ``malloc_trim``
    has returned freed heap pages (else freed memory is reused without raising RSS and every
    block after the first reads ~0). ``None`` where unavailable."""

    def __init__(self, device: torch.device):
        self.device = device
        self.gib = None

    @staticmethod
    def _status(key: str) -> int | None:
        try:
            for line in Path("/proc/self/status").read_text().splitlines():
                if line.startswith(key + ":"):
                    return int(line.split()[1]) * 1024
        except OSError:
            return None
        return None

    def __enter__(self):
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            self.base = torch.cuda.memory_allocated(self.device)
        else:
            try:
                ctypes.CDLL("libc.so.6").malloc_trim(0)
            except (OSError, AttributeError):
                pass
            try:
                Path("/proc/self/clear_refs").write_text("5")
                self.base = self._status("VmRSS")
            except OSError:
                self.base = None
        return self

    def __exit__(self, *exc):
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            self.gib = (torch.cuda.max_memory_allocated(self.device) - self.base) / 2**30
        elif self.base is not None:
            peak = self._status("VmHWM")
            self.gib = None if peak is None else max(peak - self.base, 0) / 2**30
        return False


def _examples(data: Path, model_size: int, render_sizes, split: str = "standard"
              ) -> list[dict]:
    """Per scene of ``split``: the batch at the model's size and the targets at every render
    size."""
    indices = synthetic_indices(data, [split])
    if split not in indices:
        raise ValueError(f"--splits: {data} has no evaluation index for split {split!r}")
    index = indices[split]
    sizes = sorted({model_size, *render_sizes})
    per_size = {}
    for s in sizes:
        ds = dataset_from_section({"name": "synth", "roots": [str(data)], "image_shape": [s, s],
                                  "evaluation_index": index}, "test")
        per_size[s] = [default_collate([e]) for e in ds]
    return [{"batch": per_size[model_size][i],
             "targets": {s: per_size[s][i]["target"] for s in sizes}}
            for i in range(len(per_size[model_size]))]


#: What ``_time_scene`` appends per (configuration, split, setting, render size) and scene.
MEASURES = ("wall", "cpu", "render", "psnr", "ssim", "abs_rel", "gaussians", "kept", "mem")


def budget_label(keep: float | int | str,  # noqa: PYI041 (beartype: int is no float)
                 rank_by: str) -> str:
    """A Gaussian budget's row name: ``learned30%``, ``opacity10%``, ``random5%`` for
    fractions, ``footprint5000`` for a count, ``dither-auto`` for the automatic count.

    Examples:
        >>> budget_label(0.3, "learned"), budget_label(5000, "footprint")
        ('learned30%', 'footprint5000')
        >>> budget_label("auto", "dither")
        'dither-auto'
    """
    if keep == "auto":
        return f"{rank_by}-auto"
    if isinstance(keep, int):
        return f"{rank_by}{keep}"
    return f"{rank_by}{100 * keep:g}%"


def budget_settings(gaussians, rank_by=RANKINGS) -> list[tuple[str, float | int | str, str]]:
    """``(name, keep, rank_by)`` of the Gaussian budgets to measure: each of ``gaussians``
    (counts or fractions) ranked by each of ``rank_by``."""
    return [(budget_label(k, r), k, r) for r in rank_by for k in gaussians]


def _settings(prunes: dict, model_size: int, render_sizes: list[int]) -> list[tuple]:
    """``(name, pruning, render size)`` to measure: each of ``prunes`` at the model's size,
    then the default pruning at each other render size."""
    default_label = next((k for k, v in PRUNES.items() if v == DEFAULT_INFERENCE_PRUNE), "cull")
    settings = [(name, p, model_size) for name, p in prunes.items()]
    return settings + [(default_label, DEFAULT_INFERENCE_PRUNE, s) for s in render_sizes
                       if s != model_size]


def _wait(device: torch.device) -> None:
    """Wait for the device's queued work (CUDA runs asynchronously), so a clock read after it
    counts the work."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _time_scene(config: BenchConfig, model, inputs, targets: dict, settings: list[tuple],
                acc: dict, device: torch.device, split: str = "standard") -> None:
    """One scene and configuration: the model's forward timed once (wall, CPU, peak memory),
    then each ``(name, pruning, size)`` of ``settings`` rendered on ``targets[size]`` and timed;
    per setting, the time per view (the forward's share included) and the render's accuracy
    (``_append_accuracy``) appended to ``acc[(config, split, name, size)]``."""
    n = inputs.target_intrinsics.shape[1]
    model.eval()
    with PeakMemory(device) as mem:
        w0, c0 = time.perf_counter(), time.process_time()
        out = model(*inputs, render=False)
        _wait(device)
        model_wall, model_cpu = time.perf_counter() - w0, time.process_time() - c0
    total = len(out.gaussians)
    for name, prune, size in settings:
        tgt = targets[size]
        w0, c0 = time.perf_counter(), time.process_time()
        model.render_targets(out, Cameras(*(tgt[k].to(device) for k in (
            "extrinsics", "intrinsics", "near", "far"))), (size, size), prune=prune)
        _wait(device)
        a = acc[(config, split, name, size)]
        a["render"].append((time.perf_counter() - w0) / n)  # pruning and rasterising
        a["wall"].append((model_wall + time.perf_counter() - w0) / n)
        a["cpu"].append((model_cpu + time.process_time() - c0) / n)
        a["mem"].append(mem.gib)
        _append_accuracy(a, out, tgt, n, total, device)


def _time_budgets(config: BenchConfig, model, inputs, tgt: dict, size: int, budgets: list,
                  acc: dict, device: torch.device, split: str = "standard") -> None:
    """One scene and configuration, each Gaussian budget ``(name, fraction, rank_by)``: the
    encoder timed once, then per budget the rest of the forward (heads, Gaussians, ranking,
    selection, adaptation) and the render, timed; the time per view (the encoder's share
    included), the peak memory (the larger of the encoder's and the rest's rise: the encoder's
    output is held between them, so a lower bound of one whole prediction's) and the accuracy
    appended to ``acc[(config, split, name, size)]``. ``kept`` is against the model's G."""
    n = inputs.target_intrinsics.shape[1]
    model.eval()
    with PeakMemory(device) as enc_mem:
        w0, c0 = time.perf_counter(), time.process_time()
        encoding = model.encode(inputs.images, inputs.extrinsics, inputs.intrinsics,
                                inputs.near, inputs.far)
        _wait(device)
        enc_wall, enc_cpu = time.perf_counter() - w0, time.process_time() - c0
    total = inputs.images.shape[1] * size * size * model.cfg.primary.gaussians_per_pixel
    cams = Cameras(*(tgt[k].to(device) for k in ("extrinsics", "intrinsics", "near", "far")))
    for name, fraction, rank_by in budgets:
        with PeakMemory(device) as mem:
            w0, c0 = time.perf_counter(), time.process_time()
            # "auto": the count chosen per scene, its renders of the context views timed with it
            budget = (AutoBudget(rank_by=rank_by) if fraction == "auto"
                      else GaussianBudget(fraction, rank_by))
            out = model(*inputs, render=False, hooks=StudyHooks(encoding=encoding),
                        budget=budget)
            _wait(device)
            r0 = time.perf_counter()
            model.render_targets(out, cams, (size, size), prune=out.aux.get("auto_prune"))
            _wait(device)
        a = acc[(config, split, name, size)]
        a["render"].append((time.perf_counter() - r0) / n)  # rasterising the K kept
        a["wall"].append((enc_wall + time.perf_counter() - w0) / n)
        a["cpu"].append((enc_cpu + time.process_time() - c0) / n)
        peaks = [m for m in (enc_mem.gib, mem.gib) if m is not None]
        a["mem"].append(max(peaks) if peaks else None)
        _append_accuracy(a, out, tgt, n, total, device)


def _append_accuracy(a: dict, out, tgt: dict, n: int, total: int, device: torch.device) -> None:
    """The ``n`` rendered targets of ``out`` against ``tgt``: PSNR, SSIM, depth AbsRel, the
    Gaussians rendered per view and their fraction of the model's ``total``, appended to ``a``."""
    gt = tgt["image"][0].to(device)
    a["psnr"].append(psnr(out.color[0], gt).mean().item())
    a["ssim"].append(ssim(out.color[0], gt).mean().item())
    dm = [depth_metrics(out.depth[0, j].cpu(), out.alpha[0, j].cpu(),
                        tgt["depth"][0, j])["abs_rel"] for j in range(n)]
    a["abs_rel"].append(nan_mean(dm))
    rendered = out.aux["rendered"].float().mean().item()
    a["gaussians"].append(rendered)
    a["kept"].append(rendered / total)


def _aggregate(acc: dict, models: dict, scenes: dict, budgets=()) -> list[dict]:
    """A row per ``acc`` key ``(config, split, name, size)`` that was measured, in its order:
    times as medians over the split's scenes (``scenes[split]``; the first, which warms
    kernels up, left out when there are more), the peak memory's maximum, the other measures'
    means, and the PSNR change against rendering everything ("all") for the same model, split
    and size (``None`` without an "all" row). Budget rows (``budgets``' names) say their
    fraction and ranking."""
    budget_of = {name: (f, r) for name, f, r in budgets}
    rows = []
    for (c, split, name, size), a in acc.items():
        if not a["wall"]:  # (a learned budget for a model without the head)
            continue
        steady = slice(1, None) if scenes[split] > 1 else slice(None)
        mems = [m for m in a["mem"] if m is not None]
        fraction, rank_by = budget_of.get(name, (None, None))
        rows.append({
            "config": c.label, "preset": c.preset, "variant": c.variant,
            "parameters": sum(p.numel() for p in models[c].parameters()),
            "prune": name, "budget_fraction": fraction, "rank_by": rank_by,
            "render_size": size, "split": split,
            "time_per_view_ms": 1000 * statistics.median(a["wall"][steady]),
            "cpu_time_per_view_ms": 1000 * statistics.median(a["cpu"][steady]),
            "render_time_per_view_ms": 1000 * statistics.median(a["render"][steady]),
            "peak_memory_mib": 1024 * max(mems) if mems else None,
            "gaussians_per_view": statistics.mean(a["gaussians"]),
            "kept_fraction": statistics.mean(a["kept"]),
            "psnr": statistics.mean(a["psnr"]), "ssim": statistics.mean(a["ssim"]),
            "abs_rel": nan_mean(a["abs_rel"]), "scenes": scenes[split]})
    for r in rows:
        base = next((q for q in rows if q["config"] == r["config"] and q["prune"] == "all"
                     and q["render_size"] == r["render_size"] and q["split"] == r["split"]),
                    None)
        r["psnr_change_db"] = None if base is None else r["psnr"] - base["psnr"]
    return rows


@torch.no_grad()
def measure(models: dict, data: Path, model_size: int, render_sizes=None, prunes=None,
            device="cpu", progress: bool = True, gaussians=(), rank_by=RANKINGS,
            splits=("standard",)) -> list[dict]:
    """One row per (configuration, split, pruning or budget, render size); see the module
    docstring. Split by split, scene by scene, each configuration in turn (``_time_scene``,
    ``_time_budgets`` at the model's size for ``gaussians`` x ``rank_by``; a learned ranking
    only for models with an importance head), then the rows (``_aggregate``)."""
    device = torch.device(device)
    render_sizes = sorted(set(render_sizes or (model_size // 2, model_size)))
    settings = _settings(PRUNES if prunes is None else prunes, model_size, render_sizes)
    budgets = budget_settings(gaussians, rank_by)
    names = [(name, s) for name, _, s in settings] + [(name, model_size) for name, *_ in budgets]
    acc = {(c, split, name, s): {k: [] for k in MEASURES}
           for split in splits for c in models for name, s in names}
    own = {c: [b for b in budgets if b[2] != "learned" or m.importance is not None]
           for c, m in models.items()}
    for c in models:
        if len(own[c]) < len(budgets):
            log.info("bench: %s has no importance head: no learned budget rows", c.label)
    examples = {split: _examples(data, model_size, render_sizes, split) for split in splits}
    with tqdm(total=sum(map(len, examples.values())) * len(models), desc="bench",
              unit="scene", dynamic_ncols=True, disable=not progress) as bar:
        for split, exs in examples.items():
            for ex in exs:
                inputs = model_inputs(ex["batch"], device)
                for c, model in models.items():
                    _time_scene(c, model, inputs, ex["targets"], settings, acc, device, split)
                    if own[c]:
                        _time_budgets(c, model, inputs, ex["targets"][model_size], model_size,
                                      own[c], acc, device, split)
                    bar.update(1)
    return _aggregate(acc, models, {k: len(v) for k, v in examples.items()}, budgets)


def choose(rows: list[dict], model_size: int) -> dict:
    """The two decisions (see ``SAFE_PRUNE_DB``, ``PRESET_WITHIN_DB``) from the measured rows
    of the first split (the standard one), and each Gaussian budget's worst PSNR change."""
    split = rows[0].get("split") if rows else None
    rows = [r for r in rows if r.get("split") == split]
    budget_rows = [r for r in rows if r.get("rank_by")]
    rows = [r for r in rows if not r.get("rank_by")]
    base = [r for r in rows if r["render_size"] == model_size and r["prune"] == "all"]
    best = max(base, key=lambda r: r["psnr"])
    within = [r for r in base if r["psnr"] >= best["psnr"] - PRESET_WITHIN_DB]
    smallest = min(within, key=lambda r: r["parameters"])
    safe = {}
    for name in {r["prune"] for r in rows if r["prune"] != "all"}:
        changes = [r["psnr_change_db"] for r in rows
                   if r["prune"] == name and r["render_size"] == model_size]
        safe[name] = {"worst_psnr_change_db": min(changes),
                      "kept_fraction": statistics.mean(
                          r["kept_fraction"] for r in rows
                          if r["prune"] == name and r["render_size"] == model_size),
                      "safe": min(changes) > -SAFE_PRUNE_DB}
    decision = {"best": best["config"], "best_psnr": best["psnr"],
                "smallest_within_0.3dB": smallest["config"], "its_psnr": smallest["psnr"],
                "its_parameters": smallest["parameters"], "pruning": safe}
    if budget_rows:  # the targets: <= 0.3 dB at 30%, <= 1.0 dB at 10% (docs/model.md)
        decision["budgets"] = {
            name: {"worst_psnr_change_db": min(r["psnr_change_db"] for r in group),
                   "kept_fraction": statistics.mean(r["kept_fraction"] for r in group)}
            for name in dict.fromkeys(r["prune"] for r in budget_rows)
            for group in [[r for r in budget_rows if r["prune"] == name]]}
    return decision


FIELDS = ["config", "preset", "variant", "parameters", "prune", "budget_fraction", "rank_by",
          "render_size", "split", "time_per_view_ms", "cpu_time_per_view_ms",
          "render_time_per_view_ms", "peak_memory_mib",
          "gaussians_per_view", "kept_fraction", "psnr", "psnr_change_db", "ssim", "abs_rel",
          "scenes"]


