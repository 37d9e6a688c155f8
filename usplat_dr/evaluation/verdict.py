"""The verdict on view conditioning: paired per-scene differences of a variant against the
baseline (a), over held-out scenes and training seeds, with bootstrap 95% confidence intervals.

Each variant is fine-tuned from the same trained (a) with the same seeds, steps and data as (a)
continued for those steps (the paper's protocol), and evaluated on the same scenes; so for seed
s and scene k the difference ``metric[variant][s, k] - metric[baseline][s, k]`` removes what the
scene and the seed share. The interval resamples scenes and seeds together (a two-level
bootstrap: seeds with replacement, scenes with replacement, the mean of the resampled table),
so it covers both sources of variation; with one seed it is the ordinary bootstrap over scenes.

With few seeds that crossed bootstrap is too narrow (3 seeds: about half the width of an
interval over the seeds themselves), so every row also has a seed-level interval: Student's t
over the per-seed mean differences (seeds - 1 degrees of freedom). A row says better or worse
only when the seed-level interval excludes 0 (with one seed: the bootstrap over scenes, and the
row says so). ``label`` applies the pre-registered rule for PSNR: **supports** the paper at
this scale when the mean is >= +0.3 dB and the seed-level lower bound > 0, **refutes** it
when the seed-level upper bound < +0.1 dB, **inconclusive** otherwise.

Examples:
    >>> import numpy as np
    >>> d = np.full((3, 50), 0.5)  # every scene and seed 0.5 dB better
    >>> lo, hi = bootstrap_interval(d, samples=200)
    >>> round(lo, 6), round(hi, 6)
    (0.5, 0.5)
"""

import csv
import logging
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from usplat_dr.io import atomic_open

log = logging.getLogger(__name__)

#: Metrics compared by default, and whether higher is better.
METRICS = {"psnr": True, "ssim": True, "abs_rel": False, "psnr_shiny": True}
#: Whether higher is better, for every metric of ``per_scene.csv`` a comparison may ask for.
HIGHER_IS_BETTER = {**METRICS, "psnr_matte": True, "lpips": False, "rmse": False,
                    "delta1": True}
LABELS = {"baseline": "(a)", "agnostic": "(b)", "full": "(c)"}
MIN_PAIRS = 5
#: The pre-registered rule on PSNR (dB): supports when mean >= SUPPORT and the seed-level
#: lower bound > 0; refutes when the seed-level upper bound < REFUTE.
SUPPORT, REFUTE = 0.3, 0.1


@dataclass(frozen=True)
class Comparison:
    """One row of the verdict: ``variant`` - ``baseline`` on ``metric`` over ``split``."""

    split: str
    metric: str
    variant: str
    mean: float  # mean paired difference (variant - baseline)
    low: float  # 95% bootstrap interval
    high: float
    scenes: int
    seeds: int
    better_fraction: float  # fraction of (seed, scene) pairs where the variant is better
    seed_low: float = float("nan")  # 95% t interval over the per-seed means (>= 2 seeds)
    seed_high: float = float("nan")

    @property
    def decisive(self) -> tuple[float, float]:
        """The interval a verdict is read from: the seed-level one with >= 2 seeds, the
        bootstrap over scenes with one."""
        return (self.seed_low, self.seed_high) if self.seeds >= 2 else (self.low, self.high)

    @property
    def verdict(self) -> str:
        """'better' / 'worse' when the seed-level interval excludes 0 (in the metric's good
        direction), else 'no difference shown'; with one seed the bootstrap over scenes
        decides and the verdict says "(one seed)"; 'too few scenes' under ``MIN_PAIRS``
        paired values (a bootstrap of one or two values has no meaningful interval)."""
        if self.scenes * self.seeds < MIN_PAIRS:
            return "too few scenes"
        low, high = self.decisive
        good = low > 0 if HIGHER_IS_BETTER[self.metric] else high < 0
        bad = high < 0 if HIGHER_IS_BETTER[self.metric] else low > 0
        word = "better" if good else "worse" if bad else "no difference shown"
        return word if self.seeds >= 2 else f"{word} (one seed)"

    @property
    def label(self) -> str:
        """The pre-registered rule (PSNR rows, >= 2 seeds): 'supports' / 'refutes' /
        'inconclusive'; '' for other metrics, 'needs >= 2 seeds' with one."""
        if self.metric != "psnr":
            return ""
        if self.seeds < 2:
            return "needs >= 2 seeds"
        return rule_label(self.mean, self.seed_low, self.seed_high)


def rule_label(mean: float, low: float, high: float) -> str:
    """The pre-registered rule on a PSNR difference (dB) and its interval: 'supports' at
    ``mean >= SUPPORT`` with ``low > 0``, 'refutes' when ``high < REFUTE``, else
    'inconclusive'.

    Examples:
        >>> rule_label(0.4, 0.1, 0.7), rule_label(0.0, -0.05, 0.05), rule_label(0.2, 0.1, 0.3)
        ('supports', 'refutes', 'inconclusive')
    """
    if mean >= SUPPORT and low > 0:
        return "supports"
    if high < REFUTE:
        return "refutes"
    return "inconclusive"


def t_interval(values, level: float = 0.95) -> tuple[float, float]:
    """Student's t interval of the mean of ``values`` (NaN entries left out; NaN with fewer
    than 2)."""
    from scipy.stats import t as student_t  # only here (import time)

    a = np.asarray(values, dtype=np.float64)
    a = a[~np.isnan(a)]
    if a.size < 2:
        return float("nan"), float("nan")
    half = student_t.ppf(0.5 + level / 2, a.size - 1) * a.std(ddof=1) / np.sqrt(a.size)
    return float(a.mean() - half), float(a.mean() + half)


def seed_interval(diffs: np.ndarray, level: float = 0.95) -> tuple[float, float]:
    """Student's t interval of the mean over the per-seed means of ``diffs`` [seeds, scenes]
    (NaN entries left out of each seed's mean): what a new training seed would give, the
    scenes held fixed. NaN with one seed (no spread to estimate)."""
    diffs = np.asarray(diffs, dtype=np.float64)
    if diffs.ndim != 2 or diffs.size == 0:
        raise ValueError(f"diffs must be a non-empty [seeds, scenes] array, got {diffs.shape}")
    with np.errstate(invalid="ignore"):
        means = np.nanmean(diffs, 1)
    return t_interval(means, level)


def bootstrap_interval(diffs: np.ndarray, samples: int = 10_000, seed: int = 0,
                       level: float = 0.95) -> tuple[float, float]:
    """Percentile interval of the mean of ``diffs`` [seeds, scenes] under resampling seeds and
    scenes with replacement (independently); NaN entries (a metric undefined for a scene,
    e.g. no covered pixel for depth) are left out of each mean."""
    diffs = np.asarray(diffs, dtype=np.float64)
    if diffs.ndim != 2 or diffs.size == 0:
        raise ValueError(f"diffs must be a non-empty [seeds, scenes] array, got {diffs.shape}")
    rng = np.random.default_rng(seed)
    s, k = diffs.shape
    means = np.empty(samples)
    for start in range(0, samples, 1000):  # blocks: bounded memory for large tables
        n = min(1000, samples - start)
        si = rng.integers(0, s, size=(n, s))
        ki = rng.integers(0, k, size=(n, k))
        table = diffs[si[:, :, None], ki[:, None, :]].reshape(n, -1)  # [n, s k]
        counts = (~np.isnan(table)).sum(1)
        with np.errstate(invalid="ignore"):  # a resample of only NaNs has no mean
            means[start:start + n] = np.nansum(table, 1) / counts
    alpha = (1 - level) / 2
    return float(np.nanquantile(means, alpha)), float(np.nanquantile(means, 1 - alpha))


def read_per_scene(path: str | os.PathLike, metrics=METRICS
                   ) -> dict[tuple[str, str], dict[str, float]]:
    """``usplat eval``'s ``per_scene.csv`` as (split, scene) -> metric -> value."""
    out = {}
    with open(path) as f:
        for row in csv.DictReader(f):
            out[(row["split"], row["scene"])] = {
                m: float(row[m]) if row.get(m) not in (None, "") else float("nan")
                for m in metrics}
    return out


def compare(runs: dict[str, list[str | os.PathLike]], baseline: str = "baseline",
            samples: int = 10_000, scene_prefixes: tuple[str, ...] = (),
            metrics: dict[str, bool] | None = None) -> list[Comparison]:
    """``runs``: variant -> one ``per_scene.csv`` per seed (the same seeds, in the same order,
    for every variant). Every variant other than ``baseline`` is compared with it, per split
    and metric, on the (split, scene) pairs all runs evaluated; with ``scene_prefixes``, only
    on scenes whose name starts with one of them (``usplat synth`` names start with the kind:
    ``("object_", "outdoor_")``). ``metrics``: name -> higher is better (default ``METRICS``).
    """
    if baseline not in runs:
        raise ValueError(f"runs must include the baseline {baseline!r}, got {sorted(runs)}")
    metrics = metrics or METRICS
    tables = {v: [read_per_scene(p, metrics) for p in paths] for v, paths in runs.items()}
    seeds = {len(t) for t in tables.values()}
    if len(seeds) != 1:
        raise ValueError(f"every variant needs the same number of seeds, got "
                         f"{ {v: len(t) for v, t in tables.items()} }")
    common = set.intersection(*(set(t) for ts in tables.values() for t in ts))
    if scene_prefixes:
        common = {k for k in common if k[1].startswith(tuple(scene_prefixes))}
    splits = sorted({s for s, _ in common}, key=lambda s: (s != "standard", s))
    rows = []
    for split in splits:
        keys = sorted(k for k in common if k[0] == split)
        for variant, ts in tables.items():
            if variant == baseline:
                continue
            for metric, higher in metrics.items():
                d = np.array([[t[k][metric] - b[k][metric] for k in keys]
                              for t, b in zip(ts, tables[baseline])])
                if np.isnan(d).all():
                    continue
                lo, hi = bootstrap_interval(d, samples)
                valid = d[~np.isnan(d)]
                rows.append(Comparison(
                    split, metric, variant, float(valid.mean()), lo, hi, len(keys), len(ts),
                    float(((valid > 0) if higher else (valid < 0)).mean()),
                    *seed_interval(d)))
    return rows


def table(rows: list[Comparison], rule: bool = True) -> str:
    """The verdict as a Markdown table (``rule``: with the pre-registered rule's label, which
    is for (c) - (a) on PSNR only)."""
    lines = [("| split | metric | difference | mean | 95% bootstrap (scenes x seeds) | "
              "95% seed-level t | scenes x seeds | better in | verdict | rule (PSNR) |"),
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        seed = (f"[{r.seed_low:+.3f}, {r.seed_high:+.3f}]" if r.seeds >= 2 else
                "(one seed)")
        lines.append(
            f"| {r.split} | {r.metric} | {LABELS.get(r.variant, r.variant)} - (a) | "
            f"{r.mean:+.3f} | [{r.low:+.3f}, {r.high:+.3f}] | {seed} | {r.scenes} x {r.seeds} | "
            f"{100 * r.better_fraction:.0f}% | {r.verdict} | {r.label if rule else ''} |")
    return "\n".join(lines)


def chart(rows: list[Comparison], path: str | os.PathLike) -> Path:
    """Forest plot: per metric a panel, per split and variant the mean difference with its
    interval; the zero line is "no effect"."""
    import matplotlib  # only for the chart (start-up time)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # after choosing the backend

    metrics = [m for m in METRICS if any(r.metric == m for r in rows)]
    fig, axes = plt.subplots(1, len(metrics), figsize=(4.2 * len(metrics), 0.5 + 0.32 * len(
        rows) / max(1, len(metrics))), squeeze=False)
    variants = sorted({r.variant for r in rows})
    for ax, metric in zip(axes[0], metrics):
        sel = [r for r in rows if r.metric == metric]
        labels = []
        for i, r in enumerate(sel):
            colour = f"C{variants.index(r.variant)}"
            if r.seeds >= 2:  # the seed-level interval: thin and wider, behind
                ax.errorbar(r.mean, i, xerr=[[r.mean - r.seed_low], [r.seed_high - r.mean]],
                            fmt="none", color=colour, alpha=0.45, capsize=2, linewidth=0.8)
            ax.errorbar(r.mean, i, xerr=[[r.mean - r.low], [r.high - r.mean]], fmt="o",
                        color=colour, capsize=3)
            labels.append(f"{r.split} {LABELS.get(r.variant, r.variant)}")
        ax.axvline(0, color="k", linewidth=0.8)
        ax.set_yticks(range(len(sel)), labels, fontsize=7)
        ax.invert_yaxis()
        better = "higher is better" if HIGHER_IS_BETTER[metric] else "lower is better"
        ax.set(xlabel=f"{metric}: variant - (a) ({better})\n"
                      "thick: bootstrap; thin: seed-level t")
        ax.grid(alpha=0.3, axis="x")
    fig.tight_layout()
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=110)
    plt.close(fig)
    return Path(path)


def as_dicts(rows: list[Comparison]) -> list[dict]:
    """The comparisons as plain dicts (for JSON)."""
    return [{**asdict(r), "verdict": r.verdict, "label": r.label} for r in rows]
