"""Synthetic scenes with known geometry, rendered by Mitsuba 3 into the field's chunk format.

``synthesize(out, scenes, frames, resolution, seed)`` writes ``<out>/<stage>/*.torch`` and
``index.json`` (readable by ``ChunkDataset`` and by pixelSplat/MVSplat's own loaders), one
evaluation index per split (``evaluation_index_<split>.json``), ``splits.json`` (per-scene
measurements behind the stress splits), ``synth.json`` (the arguments) and preview images
(``previews/<key>.png``: colour above depth). The test stage writes these into ``<out>``
(where ``usplat eval`` finds the indices); any other stage into ``<out>/<stage>/``, beside its
chunks, so that the stages of one root never overwrite each other's (``metadata_folder``).

Scene ``i`` of a set is made from ``scene_seed(seed, i)``; its key ``<kind>_<seed>_<i>`` names
both, so two stages share a scene exactly when they share a key. Without a seed each stage
takes its own (``DEFAULT_SEEDS``), and ``synthesize`` refuses to write a stage that would
share scenes with the other stage of the same root (``check_stages_disjoint``).

Each scene record carries, besides the standard keys: ``depths`` (float16 [V, H, W],
camera-space z, +inf on a miss), ``materials`` (uint8 [V, H, W]: 0 miss, 1 textured,
2 textureless, 3 glossy, 4 metal), ``near_far`` (float32 [2]), ``tags`` (list of str) and
``mitsuba`` (the scene description, re-renderable with ``render_spec`` at any resolution).
"""

import hashlib
import logging
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from usplat_dr.data.chunks import (
    ChunkWriter,
    encode_image,
    matrices_to_cameras,
    metadata_folder,
    read_index,
)
from usplat_dr.data.synth.render import render_spec
from usplat_dr.data.synth.scenes import APPEARANCES, KINDS, make_spec
from usplat_dr.data.synth.splits import SPLITS, scene_splits
from usplat_dr.io import write_json
from usplat_dr.io.images import colorize_depth, save_png

log = logging.getLogger(__name__)

__all__ = ["APPEARANCES", "DEFAULT_SEEDS", "KINDS", "SPLITS", "check_stages_disjoint",
           "default_seed", "make_spec", "metadata_folder", "render_spec", "scene_record",
           "synthesize"]


#: Samples per pixel by appearance (``synthesize``'s default).
DEFAULT_SPP = {"diffuse": 64, "view-dependent": 256, "rough-glossy": 256, "photographic": 64}

#: The seed of each stage when none is given: different, so that a train and a test set made
#: without ``--seed`` share no scene (test keeps 0, the seed its default always had).
DEFAULT_SEEDS = {"test": 0, "train": 1}
#: The stages ``usplat synth`` writes (the test stage's metadata stays at the root:
#: ``usplat_dr.data.chunks.metadata_folder``).
STAGES = ("train", "test")


def default_seed(stage: str) -> int:
    """The seed ``synthesize`` uses for ``stage`` when it is given none (``DEFAULT_SEEDS``).

    Examples:
        >>> default_seed("train") != default_seed("test")
        True
    """
    if stage not in DEFAULT_SEEDS:
        raise ValueError(f"stage must be one of {sorted(DEFAULT_SEEDS)}, got {stage!r}")
    return DEFAULT_SEEDS[stage]


#: Scene keys' suffix by appearance (none for the diffuse one).
APPEARANCE_SUFFIXES = {"view-dependent": "_vd", "rough-glossy": "_rg", "photographic": "_ph"}


def scene_key(kind: str, seed: int, i: int, appearance: str = "diffuse") -> str:
    """The key of scene ``i`` of a set made with ``seed``: ``<kind>_<seed>_<i:05d>`` (``_vd``
    for the view-dependent appearance, ``_rg`` for the rough-glossy one)."""
    return f"{kind}_{seed}_{i:05d}" + APPEARANCE_SUFFIXES.get(appearance, "")


def check_stages_disjoint(out: str | os.PathLike, stage: str, keys: list[str]) -> None:
    """Raise a ``ValueError`` (one line: the root, the other stage, the fix) when another
    stage of ``out`` already holds any of the scenes ``keys`` (the same key is the same kind,
    seed and scene number, so the same scene; ``_vd`` aside, the same geometry and cameras):
    training on test scenes would make the evaluation score memorised scenes."""
    def base(key: str) -> str:
        for suffix in APPEARANCE_SUFFIXES.values():
            key = key.removesuffix(suffix)
        return key

    wanted = {base(k) for k in keys}
    for other in STAGES:
        index = Path(out) / other / "index.json"
        if other == stage or not index.is_file():
            continue
        try:
            held = read_index(index.parent)
        except ValueError:
            continue  # not ours to judge here; the dataset reports a broken index
        shared = sorted(k for k in held if base(k) in wanted)
        if shared:
            raise ValueError(
                f"{out}: its {other} stage already holds {len(shared)} of these scenes (e.g. "
                f"{shared[0]}), so {stage} and {other} would share scenes; pass another --seed "
                f"(or none: train and test default to different seeds, "
                f"{DEFAULT_SEEDS}) or another --out")


def scene_seed(seed: int, i: int) -> int:
    return int.from_bytes(hashlib.sha256(f"{seed}/{i}".encode()).digest()[:4], "little")


def scene_record(key: str, spec: dict, images: np.ndarray, depths: np.ndarray,
                 materials: np.ndarray, intrinsics: np.ndarray) -> dict:
    """A chunk record (the pixelSplat structure plus our extra keys) for a rendered scene."""
    c2w = torch.tensor(np.asarray(spec["cameras"]["c2w"]), dtype=torch.float64)
    v = len(images)
    k = torch.tensor(intrinsics, dtype=torch.float32).expand(v, 3, 3)
    return {
        "key": key,
        "url": "",
        "timestamps": torch.arange(v, dtype=torch.int64),
        "cameras": matrices_to_cameras(c2w, k),
        "images": [encode_image(im, "png") for im in images],
        "depths": torch.from_numpy(depths.astype(np.float16)),
        "materials": torch.from_numpy(materials),
        "near_far": torch.tensor(spec["near_far"], dtype=torch.float32),
        "tags": list(spec["tags"]),
        "mitsuba": spec,
    }


def _preview(path: Path, images: np.ndarray, depths: np.ndarray) -> None:
    picks = np.linspace(0, len(images) - 1, min(6, len(images))).round().astype(int)
    top = np.concatenate([images[i] / 255.0 for i in picks], 1)
    bottom = np.concatenate([colorize_depth(np.where(np.isfinite(depths[i]), depths[i], 0.0),
                                            np.isfinite(depths[i]).astype(np.float64))
                             for i in picks], 1)
    save_png(path, np.concatenate([top, bottom], 0))


def _render_scene(job: tuple) -> tuple:
    """``render_spec`` of one scene (a top-level function, so worker processes can run it).
    Only arrays come back: the records are built from this process's own descriptions, so
    the pickled chunk does not depend on which process rendered (pickle's sharing of equal
    strings does)."""
    spec, resolution, spp, seed, backend = job
    return render_spec(spec, resolution, spp=spp, seed=seed, backend=backend)


def _rendered(jobs_list: list[tuple], jobs: int):
    """Rendered scenes in order, from this process or from ``jobs`` worker processes."""
    if jobs <= 1 or len(jobs_list) <= 1:
        yield from map(_render_scene, jobs_list)
        return
    # spawn: a forked Dr.Jit/Mitsuba runtime (threads, JIT state) is not safe to reuse.
    with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
        yield from pool.map(_render_scene, jobs_list)


def synthesize(out: str | os.PathLike, scenes: int, frames: int,
               resolution: tuple[int, int], seed: int | None = None, kinds: tuple[str, ...] = KINDS,
               spp: int | None = None, backend: str = "llvm", stage: str = "test",
               previews: int = 8, progress: bool = True, jobs: int = 1,
               chunk_scenes: int | None = None, appearance: str = "diffuse") -> dict:
    """Render ``scenes`` procedural scenes of ``frames`` frames each (kinds round-robin) and
    write them as a dataset under ``out``. Deterministic: the same arguments give the same
    bytes on the LLVM backend, for any ``jobs`` (scenes rendered by that many worker
    processes, for machines where one Mitsuba process does not keep every core busy).
    Chunks hold up to 100 MB of scenes, and at most ``chunk_scenes`` scenes when given
    (training shards by scene, so any number of chunks feeds any number of ranks).
    ``appearance``: ``"diffuse"``, ``"view-dependent"`` (shiny surfaces, a structured sky,
    path tracing: ``usplat_dr.data.synth.scenes``) or ``"rough-glossy"`` (the same with rough
    shiny surfaces: broad highlights); the same seed gives the same geometry and cameras in
    all three. ``spp``: Mitsuba samples per pixel (None: ``DEFAULT_SPP`` of the
    appearance: path tracing's noise on shiny surfaces needs 256 to stay below what changes
    with the viewpoint; train/studies/LOG.md, "The view-dependent appearance, version
    2"). ``seed``: None takes the stage's own (``DEFAULT_SEEDS``); a given seed makes the
    same bytes whatever the stage. The test stage's metadata goes into ``out``, any other
    stage's into ``out/<stage>`` (``metadata_folder``); a stage whose scenes another stage
    of ``out`` already holds is a ``ValueError`` (``check_stages_disjoint``). Returns the
    split summary (split -> number of scenes in it).

    Examples:
        >>> import tempfile
        >>> summary = synthesize(tempfile.mkdtemp(), scenes=1, frames=4, resolution=(8, 8),
        ...                      spp=2, progress=False)
        >>> summary["standard"]
        1
    """
    if stage not in STAGES:
        raise ValueError(f"stage must be one of {STAGES}, got {stage!r}")
    seed = default_seed(stage) if seed is None else seed
    if scenes < 1 or frames < 3:
        raise ValueError(f"scenes must be >= 1 and frames >= 3, got {scenes} and {frames}")
    h, w = resolution
    if h < 4 or w < 4:
        raise ValueError(f"resolution must be at least 4x4, got {resolution}")
    for k in kinds:
        if k not in KINDS:
            raise ValueError(f"kinds must be among {KINDS}, got {k!r}")
    if jobs < 1:
        raise ValueError(f"jobs must be >= 1 (worker processes), got {jobs}")
    if appearance not in APPEARANCES:
        raise ValueError(f"appearance must be one of {APPEARANCES}, got {appearance!r}")
    spp = DEFAULT_SPP[appearance] if spp is None else spp
    if spp < 1:
        raise ValueError(f"spp must be >= 1 (Mitsuba samples per pixel), got {spp}")
    if chunk_scenes is not None and chunk_scenes < 1:
        raise ValueError(f"chunk_scenes must be >= 1 (or None: chunks of up to 100 MB), got "
                         f"{chunk_scenes}")
    out = Path(out)
    keys = [scene_key(kinds[i % len(kinds)], seed, i, appearance) for i in range(scenes)]
    check_stages_disjoint(out, stage, keys)
    meta = metadata_folder(out, stage)
    splits: dict[str, dict] = {s: {} for s in SPLITS}
    measurements = {}
    bar = None
    if progress:
        bar = tqdm(total=scenes, desc="usplat synth", unit="scene")
    seeds = [scene_seed(seed, i) for i in range(scenes)]
    specs = [make_spec(kinds[i % len(kinds)], s, frames, appearance)
             for i, s in enumerate(seeds)]
    work = [(spec, (h, w), spp, s, backend) for spec, s in zip(specs, seeds)]
    with ChunkWriter(out, stage, chunk_bytes=100_000_000, chunk_scenes=chunk_scenes) as writer:
        for i, (spec, s, rendered) in enumerate(zip(specs, seeds, _rendered(work, jobs))):
            images, depths, materials, intr = rendered
            kind, key = spec["kind"], keys[i]
            writer.add(scene_record(key, spec, images, depths, materials, intr))
            entries, stats = scene_splits(np.asarray(spec["cameras"]["c2w"]), intr, depths,
                                          materials, np.random.default_rng(s))
            for name, entry in entries.items():
                splits[name][key] = entry
            measurements[key] = {"kind": kind, "tags": spec["tags"], **stats}
            if i < previews:
                _preview(meta / "previews" / f"{key}.png", images, depths)
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()
    for name, index in splits.items():
        write_json(meta / f"evaluation_index_{name}.json", index)
    summary = {name: sum(e is not None for e in index.values()) for name, index in splits.items()}
    write_json(meta / "splits.json", {"scenes_per_split": summary, "scenes": measurements})
    arguments = {"scenes": scenes, "frames": frames, "resolution": [h, w], "seed": seed,
                 "kinds": list(kinds), "spp": spp, "stage": stage}
    if chunk_scenes is not None:  # (absent by default: earlier sets keep their bytes)
        arguments["chunk_scenes"] = chunk_scenes
    if appearance != "diffuse":  # (likewise)
        arguments["appearance"] = appearance
    write_json(meta / "synth.json", arguments)
    log.info("wrote %d scenes to %s; scenes per split: %s", scenes, out, summary)
    return summary
