"""Reports from result files: the demo's ``report.md`` (training curves, gradient stability,
the tables), and ``usplat bench``'s chart and table. Pure functions from results to Markdown
and PNG; the measuring is in ``demo`` and ``bench``, and ``metrics.csv`` is read and
summarised (``curves``, ``stability``) by ``usplat_dr.training.run_log``, which writes it."""

import csv
from dataclasses import dataclass
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
from matplotlib.lines import Line2D

from usplat_dr.evaluation.speed import FIELDS, choose
from usplat_dr.evaluation.verdict import Comparison
from usplat_dr.evaluation.verdict import table as verdict_table
from usplat_dr.evaluation.view_specificity import LIVE_BOUND_DB
from usplat_dr.io import atomic_open, write_json
from usplat_dr.model.uniquesplat import VARIANTS
from usplat_dr.training.checkpoints import BASE, BEYOND, BUDGETED, LIVE, SHIPPED
from usplat_dr.training.recipes import FINETUNE_LR, PRESET, RunRecipe
from usplat_dr.training.run_log import GRAD_LABELS


def stability_lines(stable: dict) -> list[str]:
    if not stable:
        return []
    lines = [("Gradient norms before clipping (clip at 0.5): median / maximum, and the last "
              "quarter's median over the first quarter's; skipped non-finite steps."), "",
             "| variant | part | median | max | last/first quarter |", "|---|---|---|---|---|"]
    for variant, st in stable.items():
        for key, p in st["parts"].items():
            lines.append(f"| {VARIANTS[variant]} | {GRAD_LABELS.get(key, 'all parameters')} "
                         f"| {p['median']:.3g} | {p['max']:.3g} | "
                         f"{p['last_over_first_quarter']:.2f} |")
    lines += ["", "Skipped steps: " + ", ".join(
        f"{VARIANTS[v]} {st['skipped']} of {st['steps']}" for v, st in stable.items()), ""]
    return lines


def _label(variant: str, manifest: dict) -> str:
    if variant == "base":
        return f"(a) shipped `{BASE}` ({manifest[BASE]['steps']} steps)"
    e = manifest[SHIPPED[variant]]
    return f"{VARIANTS[variant]} `{e['name']}` ({e['steps']} steps)"


def _cells(m: dict) -> str:
    return f"{m['psnr']:.2f} / {m['ssim']:.3f} / {m['abs_rel']:.3f}"


def registered_lines(registered: dict | None) -> list[str]:
    """The pre-registered multi-seed verdict (``checkpoints/verdict.json``) as Markdown: per
    held-out set, (c) - (a) on PSNR with both intervals and the rule's label."""
    if not registered:
        return [("No multi-seed verdict is shipped beside the checkpoints "
                 "(`checkpoints/verdict.json`)."), ""]
    lines = [(f"The pre-registered multi-seed verdict of the same protocol "
              f"(`checkpoints/verdict.json`, {registered['date']}; rule: "
              f"{registered['rule']}):"), "",
             ("| held-out set | arm | (c) - (a) PSNR | 95% bootstrap | 95% seed-level t | "
              "seeds x scenes | label | branch live? |"), "|---|---|---|---|---|---|---|---|"]
    for r in registered["sets"]:
        if r.get("label") in (None, "not run"):
            lines.append(f"| {r['set']} | | | | | | not run: {r.get('why', '')} | |")
            continue
        lines.append(f"| {r['set']} | {r['arm']} | {r['mean']:+.3f} | [{r['low']:+.3f}, "
                     f"{r['high']:+.3f}] | [{r['seed_low']:+.3f}, {r['seed_high']:+.3f}] | "
                     f"{r['seeds']} x {r['scenes']} | **{r['label']}** | "
                     f"{r.get('branch_live', 'not measured').replace('|', '/')} |")
    if registered.get("note"):
        lines += ["", registered["note"]]
    return [*lines, ""]


# ---- the demo's report.md ------------------------------------------------------------------------

@dataclass(frozen=True)
class DemoResults:
    """What the demo's ``report.md`` reports: the results of its steps (``run_demo``)."""

    out: Path  # the demo's folder: report.md goes there; renders and bench tables are read there
    recipe: RunRecipe
    recipe_name: str  # "full" or "quick"
    summaries: dict  # "base" and each variant's shipped checkpoint -> evaluate()'s summary
    timings: dict  # stage -> seconds
    worst: dict  # variant -> worst_cases(): per split the worst scene's sheet and its PSNR
    bench: dict  # the demo's speed/accuracy summary (bench.write_results)
    stable: dict  # variant -> stability() of its fine-tuning run
    verdict: list[Comparison]  # the paired differences against (a) continued
    tuned: dict  # variant -> evaluate()'s summary after the brief fine-tuning
    provenance: dict  # the machine, libraries and data (evaluation.provenance)
    manifest: dict  # shipped checkpoint name -> its checkpoints/manifest.json entry
    registered: dict | None = None  # the shipped multi-seed verdict (checkpoints/verdict.json)
    allocation: dict | None = None  # evaluate()'s summary of (c) under a Gaussian budget
    auto: dict | None = None  # evaluate()'s summary of (c) with the automatic count
    live: dict | None = None  # evaluate()'s summary of the live (c) on the standard split
    # evaluate()'s summary of the (c) trained with extrapolated targets (standard and
    # extrapolation splits)
    beyond: dict | None = None


def write_report(results: DemoResults) -> Path:
    """``report.md`` in ``results.out``, from the results of the demo's steps and the files
    they wrote (renders, ``bench_demo/bench.md``, ``bench/bench.md``): a section each."""
    sections = (summary_lines, intro_lines, shipped_lines, verdict_lines, meter_lines, split_lines,
                worst_case_lines,
                fine_tuning_lines, speed_lines, allocation_lines, novel_view_lines,
                provenance_lines, wall_time_lines)
    lines = [line for section in sections for line in section(results)]
    path = results.out / "report.md"
    with atomic_open(path, "w") as f:
        f.write("\n".join(lines))  # every section ends with an empty line: the final newline
    return path


# Each section is a list of lines that ends with an empty one.

#: The most lines ``summary_lines`` may take: the report's first screen.
SUMMARY_LINES = 40
#: The registered question's splits, as the summary names them.
HEADLINE_SPLITS = {"standard": "standard (between the context views)",
                   "extrapolation": "extrapolation (1-4 frames beyond)"}


def headline_rows(registered: dict | None) -> list[tuple[str, str, dict]]:
    """The registered question's rows of ``checkpoints/verdict.json`` (the paper's protocol
    with extrapolated training targets), as (split, size, set): standard then extrapolation,
    64x64 then 128x128 (the README's table)."""
    rows = {}
    for s in (registered or {}).get("sets", []):
        split = s["set"].split(" split")[0]
        if "paper's protocol" in s.get("arm", "") and split in HEADLINE_SPLITS:
            size = "128x128" if "128x128" in s["set"] else "64x64"
            rows[(size, split)] = (HEADLINE_SPLITS[split], size, s)
    return [rows[k] for k in sorted(rows, key=lambda k: (k[0] != "64x64", k[1] != "standard"))]


def summary_lines(r: DemoResults) -> list[str]:
    """The report's first screen (at most ``SUMMARY_LINES``): what ran, each model's PSNR and
    margin over copying the nearest context view, the registered verdict's rows and the time
    taken; the sections below hold the detail."""
    b = r.recipe
    numerics = r.provenance.get("numerics")
    isa = numerics.get("ATEN_CPU_CAPABILITY") if isinstance(numerics, dict) else None
    lines = ["# usplat-dr demo report", "", "## Summary", "",
             (f"Recipe `{r.recipe_name}`: {b.test_scenes} fresh scenes at {b.size}x{b.size}, "
              f"{r.timings.get('total', sum(r.timings.values())):.0f} s in all "
              f"({r.provenance.get('cpu', 'this CPU')}"
              f"{f', {isa} kernels' if isa else ''}, "
              f"{r.provenance.get('torch_threads', '?')} thread(s))."), "",
             "| model | PSNR, standard split | over copying the nearest view | time per scene |",
             "|---|---|---|---|"]
    models = [(_label(v, r.manifest), s) for v, s in r.summaries.items()]
    if r.beyond:
        models.append((f"(c) `{BEYOND}` (the users' (c))", r.beyond))
    for name, s in models:
        std = s["splits"].get("standard")
        if std is None:
            continue
        time = s.get("time_per_scene_s")
        lines.append(f"| {name} | {std['psnr']:.2f} | {_over_copy(std)} | "
                     f"{'' if time is None else f'{1000 * time:.0f} ms'} |")
    rows = headline_rows(r.registered)
    if rows:
        lines += ["", ("The registered verdict, (c) - (a) trained the same way "
                       "(`checkpoints/verdict.json`, seed-level 95%):"), "",
                  "| held-out split | size | (c) - (a), dB | live seeds | label |",
                  "|---|---|---|---|---|"]
        lines += [f"| {split} | {size} | {s['mean']:+.3f} [{s['seed_low']:+.3f}, "
                  f"{s['seed_high']:+.3f}] | {s['seeds']} | **{s['label']}** |"
                  for split, size, s in rows]
        lines += ["", ("Per-view weights pay where a target leaves the context pair, not "
                       "between the context views.")]
    lines += ["", ("Below: the models in full, this run's verdict, the meter, per split, "
                   "fine-tuning, speed, novel views, provenance and wall time."), ""]
    return lines


def intro_lines(r: DemoResults) -> list[str]:
    """What the demo did."""
    b = r.recipe
    return ["## What the demo did", "",
            (f"Recipe `{r.recipe_name}`: {b.test_scenes} fresh held-out scenes rendered by "
             f"Mitsuba ({b.frames} frames, {b.size}x{b.size}; a seed none of the checkpoints was "
             f"trained or tested on), the shipped `{PRESET}` checkpoints evaluated on them with "
             f"the field's protocol, and a brief fine-tuning ({b.steps} steps on "
             f"{b.train_scenes} other scenes) from the shipped (a)."), ""]


def _over_copy(m: dict) -> str:
    """A split's margin over copying the nearest context view, as a table cell (a summary
    written before it was measured has none)."""
    if m.get("psnr_over_copy") is None:
        return "not measured"
    return (f"{m['psnr_over_copy']:+.2f} dB ({m['psnr_copy']:.2f}; {m['scenes_over_copy']} of "
            f"{m['scenes']})")


def shipped_lines(r: DemoResults) -> list[str]:
    """The shipped checkpoints on the standard split: size, speed, memory and accuracy."""
    lines = ["## The shipped checkpoints on fresh scenes (standard split)", "",
             ("| model | parameters | time per scene | peak memory | PSNR | over copying | SSIM "
              "| depth AbsRel |"),
             "|---|---|---|---|---|---|---|---|"]
    for variant, s in r.summaries.items():
        std = s["splits"]["standard"]
        lines.append(f"| {_label(variant, r.manifest)} | {s['parameters'] / 1e6:.2f}M | "
                     f"{1000 * s['time_per_scene_s']:.0f} ms | {s['peak_memory_gib']:.2f} GiB "
                     f"| {std['psnr']:.2f} | {_over_copy(std)} | {std['ssim']:.3f} | "
                     f"{std['abs_rel']:.3f} |")
    return [*lines, "",
            (f"(b) and (c) were initialised from `{BASE}` (zero-initialised hypernetwork "
             f"outputs: they start exactly at it) and fine-tuned for the same steps, seed and "
             f"data as (a) continued, the control they are paired with. Time per scene: 2 "
             f"context views in, Gaussians and renders for every target (CPU, "
             f"{r.provenance.get('torch_threads', '?')} thread(s)). "
             f"Over copying: the PSNR's margin over copying the context view nearest each "
             f"target (its PSNR in brackets; the scenes the model wins of all). "
             f"LPIPS: unavailable (no VGG/LPIPS weight files in the demo). Training recipes "
             f"and data: `checkpoints/manifest.json`."), ""]


def verdict_lines(r: DemoResults) -> list[str]:
    """The paired differences against (a) continued on these scenes, then the shipped
    multi-seed verdict (``registered_lines``)."""
    test = next(iter(r.summaries.values()))["splits"]["standard"]["scenes"]
    return ["## Verdict on view conditioning (these scenes, the shipped seed)", "",
            (f"Paired per-scene differences against (a) continued over the {test} fresh "
             "scenes (the stress splits hold the scenes that qualify), with bootstrap 95% "
             "intervals over scenes. One fine-tuning seed: the interval does not cover seed "
             "variation, so no row here is a verdict; the multi-seed one "
             "(`train/studies/verdict_study.py`) follows the table, and "
             "train/studies/LOG.md (\"View conditioning as the paper has it\") has it in "
             "full with the oracle per layer "
             "(`train/studies/oracle_delta.py`)."), "", verdict_table(r.verdict), "",
            "![verdict](verdict.png)", "", *registered_lines(r.registered)]


def meter_lines(r: DemoResults) -> list[str]:
    """The view-specificity meter (``evaluation.view_specificity``) of the shipped and the
    briefly fine-tuned (c) on the standard split: is Delta W different per target view?"""
    rows = [("(c) shipped", r.summaries.get("full")), ("(c) fine-tuned here", r.tuned.get("full")),
            (f"(c) live (`{LIVE}`: E_H reads the primary features)", r.live)]
    rows = [(name, s["splits"]["standard"].get("view_specificity")) for name, s in rows if s]
    beyond = (r.beyond or {}).get("splits", {})
    rows += [(f"(c) trained beyond the context (`{BEYOND}`), {split}",
              beyond[split].get("view_specificity"))
             for split in ("standard", "extrapolation") if split in beyond]
    rows = [(name, m) for name, m in rows if m]
    if not rows:
        return []
    lines = ["## Is (c)'s view-specific branch live? (the view-specificity meter)", "",
             ("Per scene of the standard split (and of the extrapolation split for the (c) "
              "trained beyond the context, where its Delta W varies): how much Delta W differs "
              "between the scene's "
              "target views (relative to ||W||, the largest of the four layers), and what that "
              "difference does to the renders: PSNR with each target's own Delta W minus PSNR "
              "with the scene's mean Delta W for every target (mean of the absolute value; 0 "
              "when Delta W is the same for every view), and minus PSNR with Delta W = 0; 95% t "
              "intervals over scenes. A (c) counts as view-specific (live) at >= "
              f"{LIVE_BOUND_DB} dB."), "",
             ("| model | scenes | Delta W spread (of norm W) | abs PSNR(own) - PSNR(scene mean) | "
              "PSNR(own) - PSNR(Delta W = 0) | live? |"), "|---|---|---|---|---|---|"]
    for name, m in rows:
        a, z = m["d_mean_abs"], m["d_zero"]
        lines.append(f"| {name} | {m['scenes']} | {max(m['spread_rel_w'].values()):.1e} | "
                     f"{a['mean_db']:.4f} dB [{a['low']:.4f}, {a['high']:.4f}] | "
                     f"{z['mean_db']:+.4f} dB [{z['low']:+.4f}, {z['high']:+.4f}] | "
                     f"{'yes' if m['live'] else 'no'} |")
    if not all(m["live"] for _, m in rows):
        lines += ["", ("Where the branch is not live, (c) is (b) plus a constant Delta W per "
                       "scene: a verdict on such a (c) tests the fine-tuning protocol, not "
                       "weights that depend on the view (docs/verdict.md).")]
    base, live = r.summaries.get("base"), r.live
    if base and live and "view_specificity" in live["splits"]["standard"]:
        b, c = base["splits"]["standard"], live["splits"]["standard"]
        lines += ["", (f"On these scenes the live (c) renders {c['psnr']:.2f} dB against the "
                       f"shipped (a)'s {b['psnr']:.2f} dB; its per-target Delta W against the "
                       f"scene's mean: {c['view_specificity']['d_mean']['mean_db']:+.4f} dB "
                       f"(signed; its pre-registered verdict on 60 held-out scenes: "
                       f"docs/verdict.md).")]
    far = beyond.get("extrapolation", {})
    a_far = (base or {}).get("splits", {}).get("extrapolation")
    if a_far and "view_specificity" in far:
        lines += ["", (f"On the extrapolation split (targets beyond the context pair) the (c) "
                       f"trained with such targets renders {far['psnr']:.2f} dB against the "
                       f"shipped (a)'s {a_far['psnr']:.2f} dB; its per-target Delta W against "
                       f"the scene's mean: {far['view_specificity']['d_mean']['mean_db']:+.4f} "
                       f"dB (signed; its pre-registered verdict: docs/verdict.md).")]
    return [*lines, ""]


def split_lines(r: DemoResults) -> list[str]:
    """PSNR / SSIM / AbsRel of every shipped checkpoint per split."""
    lines = ["## Per split (PSNR / SSIM / depth AbsRel)", "",
             "| split | scenes | " + " | ".join(_label(v, r.manifest) for v in r.summaries)
             + " |",
             "|---|---|" + "---|" * len(r.summaries)]
    first = next(iter(r.summaries.values()))
    for split, m in first["splits"].items():
        cells = [_cells(s["splits"][split]) for s in r.summaries.values()]
        lines.append(f"| {split} | {m['scenes']} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def worst_case_lines(r: DemoResults) -> list[str]:
    """Per split and variant, the sheet of the held-out scene with the lowest PSNR."""
    lines = ["### Worst cases", "",
             ("Per split, the held-out scene with the lowest PSNR (context views, ground truth, "
              "prediction, depth per target).")]
    for split in next(iter(r.summaries.values()))["splits"]:
        for variant, w in r.worst.items():
            if split in w:
                lines.append(f"\n{VARIANTS[variant]}, {split}: {w[split].stem} "
                             f"({w[split + '_psnr']:.2f} dB)\n\n![{split}]"
                             f"({w[split].relative_to(r.out)})")
    return [*lines, ""]


def fine_tuning_lines(r: DemoResults) -> list[str]:
    """The brief fine-tuning: accuracy before and after, the training curves, and the
    gradient norms' stability (``stability_lines``)."""
    b = r.recipe
    lines = ["## Fine-tuning briefly from the shipped (a)", "",
             (f"{b.steps} steps of (a) and (c) from `{BASE}` on the demo's {b.train_scenes} "
              f"training scenes (learning rate {FINETUNE_LR:g}, depth supervision as shipped; "
              "(c)'s view-specific ResNet18 starts from random weights, as in the shipped "
              "(c): no ImageNet weight file here), "
              "evaluated on the standard split: it shows that training runs; at this length it "
              "says nothing about the verdict."), "",
             "| model | PSNR / SSIM / AbsRel before | after |", "|---|---|---|"]
    before = _cells(r.summaries["base"]["splits"]["standard"])
    for variant, s in r.tuned.items():
        lines.append(f"| {VARIANTS[variant]} | {before} | {_cells(s['splits']['standard'])} |")
    return [*lines, "", "![training curves](training_curves.png)", "",
            *stability_lines(r.stable)]


def speed_lines(r: DemoResults) -> list[str]:
    """Speed against accuracy: the demo's bench table, its pruning verdicts and, when
    ``usplat bench`` ran in the same folder, its full table."""
    lines = ["## Speed against accuracy", "",
             ("The shipped (a) continued and (c), measured by `usplat bench`'s code on the "
              "standard split: Gaussian budgets (pruning per target before rasterising) at "
              f"{r.recipe.size}x{r.recipe.size} and a smaller render size."), "",
             "![speed against accuracy](bench_demo/bench.png)", "",
             (r.out / "bench_demo" / "bench.md").read_text().rstrip(), "",
             ("Pruning (worst PSNR change over the models, mean fraction of Gaussians kept; "
              "safe: it costs less than 0.05 dB). Off by default at inference: on CPU it costs "
              "more time than it saves at every size measured (train/bench/README.md, "
              "\"Pruning that pays\")."), "",
             "| pruning | worst PSNR change | kept | safe |", "|---|---|---|---|"]
    for name, p in sorted(r.bench["pruning"].items()):
        lines.append(f"| {name} | {p['worst_psnr_change_db']:+.3f} dB | "
                     f"{p['kept_fraction']:.2f} | {'yes' if p['safe'] else 'no'} |")
    if r.bench.get("budgets"):
        lines += ["", ("Gaussian budgets chosen at inference (docs/model.md, \"A Gaussian budget "
                       "chosen at inference\"), on the budget stage's add-ons "
                       f"(`{'`, `'.join(BUDGETED.values())}`: the models above with a trained "
                       "importance head; `learned` is its ranking, `dither` its untrained "
                       "start): worst PSNR change over the models against all Gaussians, mean "
                       "fraction kept."), "",
                  "| budget | worst PSNR change | kept |", "|---|---|---|"]
        lines += [f"| {name} | {p['worst_psnr_change_db']:+.3f} dB | {p['kept_fraction']:.2f} |"
                  for name, p in r.bench["budgets"].items()]
    full_bench = r.out / "bench" / "bench.md"
    if full_bench.is_file():
        lines += ["", "### Full `usplat bench` (all presets)", "",
                  "![usplat bench](bench/bench.png)", "", full_bench.read_text().rstrip()]
    return [*lines, ""]


def allocation_lines(r: DemoResults) -> list[str]:
    """Where a Gaussian budget goes in (c): the kept fraction by material and depth, per scene
    kind, and the first scenes' maps (``evaluation.allocation``); nothing without it."""
    if r.allocation is None:
        return []
    split = r.allocation["splits"]["standard"]
    lines = ["## Where the budget goes", "",
             (f"(c) keeping {r.allocation['gaussians']} of its Gaussians "
              f"(`rank_by={r.allocation['rank_by']}`) on the standard split: "
              f"{split['psnr']:.2f} dB. The fraction kept on textured and plain "
              f"(textureless) surfaces and on the near and far half of the context depths:"),
             "", "| scenes | kept | textured | plain | near | far |", "|---|---|---|---|---|---|"]
    for kind, a in split.get("allocation", {}).items():
        cells = " | ".join(f"{a.get(c, float('nan')):.3f}" for c in (
            "kept", "kept_textured", "kept_plain", "kept_near", "kept_far"))
        lines.append(f"| {kind} | {cells} |")
    lines += ["", ("Each row: a context view, the fraction of targets that kept its pixels' "
                   "Gaussians (white: all), its material (orange textured, grey plain, blue "
                   "glossy) and depth.")]
    folder = r.out / "eval_budget_full" / "allocation" / "standard"
    for path in sorted(folder.glob("*.png"))[:2]:
        lines += ["", f"![{path.stem}]({path.relative_to(r.out)})"]
    return [*lines, "", *auto_lines(r)]


def auto_lines(r: DemoResults) -> list[str]:
    """What the automatic count (``--gaussians auto``) kept and lost in (c) on the standard
    split, against all Gaussians (the shipped (c)'s evaluation); nothing without it."""
    if r.auto is None or not r.auto["splits"]["standard"]["scenes"]:
        return []
    split = r.auto["splits"]["standard"]
    every = r.summaries["full"]["splits"]["standard"]["psnr"]
    rendered = split["mean_gaussians_rendered"] / split["mean_gaussians_total"]
    return [(f"The automatic count (`--gaussians auto`, tolerance "
             f"{r.auto['gaussians']['auto']['tolerance_db']:g} dB; docs/model.md) chose "
             f"{split['mean_auto_keep']:.0%} of (c)'s Gaussians per scene on average and "
             f"rendered {rendered:.0%} after culling and merging: {split['psnr']:.2f} dB "
             f"against {every:.2f} dB with all of them ({split['scenes']} scenes; per scene in "
             f"`eval_auto_full/per_scene.csv`)."), ""]


def novel_view_lines(r: DemoResults) -> list[str]:
    """The first two renders of the standard split of (a) continued and (c)."""
    lines = ["## Novel views", "",
             "Each row: context views, ground truth, prediction, predicted depth."]
    for variant in ("baseline", "full"):
        renders = sorted((r.out / f"eval_shipped_{variant}" / "renders" / "standard")
                         .glob("*.png"))[:2]
        for render in renders:
            lines.append(f"\n{VARIANTS[variant]}, {render.stem}:\n\n![{render.stem}]"
                         f"({render.relative_to(r.out)})")
    return [*lines, ""]


def provenance_lines(r: DemoResults) -> list[str]:
    """The machine, libraries, data hashes and shipped checkpoints the numbers came from."""
    prov = r.provenance
    return ["## Where these numbers came from", "",
            "| | |", "|---|---|",
            *[f"| {k} | {v} |" for k, v in prov.items() if k != "data"],
            *[f"| data `{k}` | sha256 `{v}` |" for k, v in prov["data"].items()],
            *[f"| checkpoint `{n}` | sha256 `{e['sha256'][:16]}...`, {e['steps']} steps, "
              f"data: {e['data']} |" for n, e in r.manifest.items()],
            "",
            ("Same command, same machine kind: docs/reproducibility.md says what is "
             "pinned (USPLAT_PORTABLE) and what can still differ."), ""]


def wall_time_lines(r: DemoResults) -> list[str]:
    """The seconds each stage of the demo took."""
    return ["## Wall time", "", "| stage | seconds |", "|---|---|",
            *[f"| {k} | {v:.0f} |" for k, v in r.timings.items()], ""]


def pareto(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats (lower x and higher y, at least one
    strictly), sorted by x.

    >>> pareto([(1.0, 1.0), (2.0, 3.0), (3.0, 2.0), (4.0, 4.0)])
    [0, 1, 3]
    """
    front = [i for i, (x, y) in enumerate(points)
             if not any(x2 <= x and y2 >= y and (x2 < x or y2 > y) for x2, y2 in points)]
    return sorted(front, key=lambda i: points[i][0])


#: Markers of ``bench_chart``: pruning settings by name, Gaussian budgets by ranking.
PRUNE_MARKERS = {"all": "o", "cull": "s", "cull+merge1px": "D", "cull+merge2px": "d"}
RANK_MARKERS = {"learned": "*", "dither": "p", "footprint": "v", "opacity": "P", "random": "X"}


def _marker(r: dict) -> str:
    return RANK_MARKERS.get(r.get("rank_by") or "", PRUNE_MARKERS.get(r["prune"], "o"))


def bench_chart(rows: list[dict], model_size: int, path: Path) -> Path:
    """``usplat bench``'s chart, on the first split's rows (the standard one): accuracy against
    time per view and against Gaussians rendered per view, each with its Pareto front;
    pruning settings and Gaussian budgets (by ranking) as markers."""
    matplotlib.use("Agg")  # files only, no display
    split = rows[0].get("split") if rows else None
    rows = [r for r in rows if r.get("split") == split]
    configs = list(dict.fromkeys(r["config"] for r in rows))
    colours = {c: plt.cm.tab10(i % 10) for i, c in enumerate(configs)}
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(12, 4.6))
    main = [r for r in rows if r["render_size"] == model_size]
    for r in main:
        kw = dict(color=colours[r["config"]], marker=_marker(r), s=36,
                  edgecolors="k", linewidths=0.4, zorder=3)
        ax0.scatter(r["time_per_view_ms"], r["psnr"], **kw)
        ax1.scatter(r["gaussians_per_view"], r["psnr"], **kw)
    for r in rows:
        if r["render_size"] != model_size:
            ax0.scatter(r["time_per_view_ms"], r["psnr"], color=colours[r["config"]],
                        marker="o", s=36, facecolors="none", zorder=2)
            ax0.annotate(f"{r['render_size']}px", (r["time_per_view_ms"], r["psnr"]),
                         fontsize=7, xytext=(3, -8), textcoords="offset points")
    for ax, key in ((ax0, "time_per_view_ms"), (ax1, "gaussians_per_view")):
        front = pareto([(r[key], r["psnr"]) for r in main])
        ax.plot([main[i][key] for i in front], [main[i]["psnr"] for i in front],
                "k--", linewidth=1, label="Pareto front", zorder=1)
        for i in front:
            ax.annotate(f"{main[i]['config']}, {main[i]['prune']}",
                        (main[i][key], main[i]["psnr"]), fontsize=7,
                        xytext=(4, 4), textcoords="offset points")
    handles = [Line2D([], [], color=colours[c], marker="o", linestyle="", label=c)
               for c in configs]
    handles += [Line2D([], [], color="grey", marker=m, linestyle="", label=p)
                for p, m in PRUNE_MARKERS.items()
                if any(r["prune"] == p and not r.get("rank_by") for r in main)]
    handles += [Line2D([], [], color="grey", marker=m, linestyle="", label=f"budget: {p}")
                for p, m in RANK_MARKERS.items() if any(r.get("rank_by") == p for r in main)]
    handles += [Line2D([], [], color="k", linestyle="--", label="Pareto front"),
                Line2D([], [], color="grey", marker="o", markerfacecolor="none",
                       linestyle="", label="other render size")]
    ax0.set(xscale="log", xlabel="time per novel view (ms, log)",
            ylabel="PSNR (dB, held-out, standard split)",
            title=f"accuracy against time ({model_size}x{model_size})")
    ax1.set(xscale="log", xlabel="Gaussians rendered per view (log)", ylabel="PSNR (dB)",
            title="accuracy against Gaussians")
    for ax in (ax0, ax1):
        ax.grid(alpha=0.3, which="both")
    ax1.legend(handles=handles, fontsize=7, loc="best")
    fig.tight_layout()
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=110)
    plt.close(fig)
    return path


def bench_table(rows: list[dict]) -> str:
    """``usplat bench``'s rows as a Markdown table."""
    def fmt(v, spec):
        return "-" if v is None else format(v, spec)

    lines = [("| config | params | pruning | size | ms/view | CPU ms/view | render ms/view | "
              "peak MiB | Gaussians/view | kept | PSNR | dPSNR | SSIM | AbsRel |"),
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['config']} | {r['parameters'] / 1e6:.2f}M | {r['prune']} | "
            f"{r['render_size']} | {r['time_per_view_ms']:.1f} | "
            f"{r['cpu_time_per_view_ms']:.1f} | {fmt(r.get('render_time_per_view_ms'), '.1f')} | "
            f"{fmt(r['peak_memory_mib'], '.0f')} | "
            f"{r['gaussians_per_view']:.0f} | {r['kept_fraction']:.2f} | {r['psnr']:.2f} | "
            f"{fmt(r['psnr_change_db'], '+.3f')} | {r['ssim']:.3f} | {r['abs_rel']:.3f} |")
    return "\n".join(lines)


def write_results(rows: list[dict], model_size: int, out: Path) -> dict:
    """``usplat bench``'s files in ``out`` from ``measure``'s rows: ``bench.csv``, ``bench.png``,
    ``summary.json`` (``choose``'s decisions, returned) and ``bench.md``."""
    out.mkdir(parents=True, exist_ok=True)
    with atomic_open(out / "bench.csv", "w") as f:
        w = csv.DictWriter(f, fieldnames=FIELDS)
        w.writeheader()
        w.writerows(rows)
    bench_chart(rows, model_size, out / "bench.png")
    decision = choose(rows, model_size)
    write_json(out / "summary.json", decision)
    with atomic_open(out / "bench.md", "w") as f:
        f.write(bench_table(rows) + "\n")
    return decision
