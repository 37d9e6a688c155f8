"""Streaming the field's datasets (RealEstate10K, ACID, DTU, our synthetic sets) into examples.

``ChunkDataset`` is a torch ``IterableDataset`` over pixelSplat chunks. Chunks are split across
distributed ranks and DataLoader workers without duplicates (chunk ``i`` goes to global worker
``i mod (ranks x workers)``); in training, chunk order and the scenes inside each chunk are
shuffled with a seed that depends on the epoch (``set_epoch``), identical on every rank.

Bad data never stops a run and is never silently lost: an unreadable chunk, a malformed
record, a corrupt image, a scene missing from ``index.json``, a camera with NaN or a singular
rotation are each skipped with one warning naming the file and scene, and counted in the
summary logged at the end of every pass (``ChunkDataset.last_summary`` in the main process).
Expected skips (too few frames for the sampler, no evaluation-index entry, FOV over
``max_fov``, unexpected image shape) are counted without a warning.
"""

import collections
import dataclasses
import hashlib
import logging
from dataclasses import dataclass, field
from pathlib import Path

import torch
import torch.distributed
from torch.utils.data import IterableDataset, get_worker_info

from usplat_dr.config import ConfigError, check_keys
from usplat_dr.data.chunks import (
    BadChunkError,
    BadSceneError,
    cameras_to_matrices,
    check_scene,
    decode_image,
    read_chunk,
    read_index,
    stage_chunks,
)
from usplat_dr.data.shims import augment_flip, crop_views, fov_degrees, normalize_baseline
from usplat_dr.data.view_sampler import (
    StepTracker,
    ViewSamplerAllCfg,
    ViewSamplerBoundedCfg,
    ViewSamplerCfg,
    ViewSamplerEvaluationCfg,
    ViewSamplingError,
    get_view_sampler,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DatasetCfg:
    """Where the data is and how examples are made (pixelSplat's DatasetRE10kCfg)."""

    roots: tuple[str, ...]
    name: str = "re10k"
    image_shape: tuple[int, int] = (256, 256)
    # None: use each scene's own ``near_far`` record (our synthetic sets carry one).
    near: float | None = 1.0
    far: float | None = 100.0
    make_baseline_1: bool = False  # the released MVSplat models use raw poses
    baseline_scale_bounds: bool = False
    augment: bool = True  # horizontal flip (p = 0.5) in the train stage only
    max_fov: float = 100.0  # degrees; wider views are skipped
    skip_bad_shape: bool = True
    original_image_shape: tuple[int, int] = (360, 640)
    view_sampler: ViewSamplerCfg = field(default_factory=ViewSamplerBoundedCfg)
    seed: int = 1234


# docs/field_protocol.md, "Data": RE10K and ACID near 1 / far 100 with 360x640 JPEGs; DTU near
# 2.125 / far 4.525 (depth 425-905 scaled by 1/200), PNGs of any shape; synthetic sets carry
# per-scene bounds.
PRESETS = {
    "re10k": dict(near=1.0, far=100.0, skip_bad_shape=True, original_image_shape=(360, 640)),
    "acid": dict(near=1.0, far=100.0, skip_bad_shape=True, original_image_shape=(360, 640)),
    "dtu": dict(near=2.125, far=4.525, skip_bad_shape=False),
    "synth": dict(near=None, far=None, skip_bad_shape=False),
}


def dataset_cfg(name: str, roots, **overrides) -> DatasetCfg:
    """A ``DatasetCfg`` with the field's settings for ``name`` (re10k, acid, dtu, synth).

    Examples:
        >>> cfg = dataset_cfg("dtu", ["datasets/dtu"])
        >>> cfg.near, cfg.far, cfg.skip_bad_shape
        (2.125, 4.525, False)
    """
    if name not in PRESETS:
        raise ValueError(f"name must be one of {sorted(PRESETS)}, got {name!r}")
    if isinstance(roots, (str, Path)):
        roots = [roots]
    return DatasetCfg(roots=tuple(str(r) for r in roots), name=name,
                      **{**PRESETS[name], **overrides})


class Summary(collections.Counter):
    """Counts of examples and skip reasons over one pass."""

    WARN = ("unreadable chunk", "malformed scene", "bad camera", "corrupt image",
            "not in index.json", "missing chunk file", "bad depth")

    def line(self) -> str:
        skips = ", ".join(f"{n} {k}" for k, n in sorted(self.items()) if k != "examples")
        return f"{self['examples']} examples; skipped: {skips or 'none'}"


def _seed(*parts) -> int:
    return int.from_bytes(hashlib.sha256(repr(parts).encode()).digest()[:8], "little") >> 1


def _distributed() -> tuple[int, int]:
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        return torch.distributed.get_rank(), torch.distributed.get_world_size()
    return 0, 1


class ChunkDataset(IterableDataset):
    """Examples from pixelSplat chunks: ``{"context": views, "target": views, "scene": key}``
    (see ``usplat_dr.data.shims`` for the fields of ``views``).

    ``rank``/``world_size`` default to torch.distributed's when it is initialised.
    """

    def __init__(self, cfg: DatasetCfg, stage: str, step_tracker: StepTracker | None = None,
                 rank: int | None = None, world_size: int | None = None):
        if stage not in ("train", "val", "test"):
            raise ValueError(f"stage must be 'train', 'val' or 'test', got {stage!r}")
        self.cfg, self.stage = cfg, stage
        self.view_sampler = get_view_sampler(cfg.view_sampler, stage, step_tracker)
        # Validation reads the test folder (the field's convention).
        self.data_stage = "train" if stage == "train" else "test"
        self.chunks = stage_chunks(cfg.roots, self.data_stage)
        self.index: dict[str, Path] = {}
        self.missing_chunks: list[tuple[str, Path]] = []
        for root in cfg.roots:
            stage_dir = Path(root) / self.data_stage
            for key, name in read_index(stage_dir).items():
                path = stage_dir / name
                self.index[key] = path
                if not path.is_file():
                    self.missing_chunks.append((key, path))
        for key, path in self.missing_chunks[:5]:
            log.warning("index.json names %s for scene %s, but the file does not exist", path, key)
        self.rank, self.world_size = rank, world_size
        self.epoch = 0
        self.last_summary = Summary()

    def set_epoch(self, epoch: int) -> None:
        """Reshuffle for a new epoch (train stage); the same order on every rank."""
        self.epoch = epoch

    def __len__(self) -> int:
        """Scenes in the index (an upper bound on the examples one pass yields)."""
        return len(self.index)

    def _my_chunks(self) -> tuple[list[Path], int, int]:
        rank, world = _distributed()
        rank = self.rank if self.rank is not None else rank
        world = self.world_size if self.world_size is not None else world
        info = get_worker_info()
        wid, nworkers = (info.id, info.num_workers) if info is not None else (0, 1)
        gid, total = rank * nworkers + wid, world * nworkers
        chunks = list(self.chunks)
        if self.stage == "train":
            perm = torch.randperm(len(chunks),
                                  generator=torch.Generator().manual_seed(_seed(self.cfg.seed,
                                                                                self.epoch)))
            chunks = [chunks[i] for i in perm]
        return chunks[gid::total], gid, total

    def __iter__(self):
        chunks, gid, total = self._my_chunks()
        gen = torch.Generator().manual_seed(_seed(self.cfg.seed, self.epoch, gid, self.stage))
        summary = Summary()
        summary["missing chunk file"] = len(self.missing_chunks) if gid == 0 else 0
        for chunk_path in chunks:
            try:
                scenes = read_chunk(chunk_path)
            except BadChunkError as e:
                log.warning("skipping chunk: %s", e)
                summary["unreadable chunk"] += 1
                continue
            order = (torch.randperm(len(scenes), generator=gen).tolist()
                     if self.stage == "train" else range(len(scenes)))
            for i in order:
                example = self._example(scenes[i], chunk_path, gen, summary)
                if example is not None:
                    summary["examples"] += 1
                    yield example
        self.last_summary = summary
        worker = f" (worker {gid} of {total})" if total > 1 else ""
        log.info("%s %s epoch %d%s: %s", self.cfg.name, self.stage, self.epoch, worker,
                 summary.line())

    def _example(self, scene: dict, chunk_path: Path, gen: torch.Generator,
                 summary: Summary) -> dict | None:
        key = scene.get("key", "?") if isinstance(scene, dict) else "?"

        def skip(reason: str, detail: str = "") -> None:
            summary[reason] += 1
            if reason in Summary.WARN:
                log.warning("skipping scene %s in %s: %s%s", key, chunk_path, reason,
                            f" ({detail})" if detail else "")

        try:
            check_scene(scene)
        except BadSceneError as e:
            return skip("malformed scene", str(e))
        if key not in self.index:
            return skip("not in index.json")
        try:
            extrinsics, intrinsics = cameras_to_matrices(scene["cameras"])
        except BadSceneError as e:
            return skip("bad camera", str(e))
        num_views = extrinsics.shape[0]
        try:
            ctx, tgt = self.view_sampler.sample(key, num_views, gen)
        except ViewSamplingError:
            return skip("sampler: no views")
        if (fov_degrees(intrinsics) > self.cfg.max_fov).any():
            return skip("fov over max_fov")
        if self.cfg.near is None or self.cfg.far is None:
            if "near_far" not in scene:
                return skip("malformed scene", "no near/far in the config or the scene")
            near, far = (float(x) for x in scene["near_far"])
        else:
            near, far = self.cfg.near, self.cfg.far

        needed = sorted(set(ctx.tolist()) | set(tgt.tolist()))
        images = {}
        try:
            for i in needed:
                images[i] = decode_image(scene["images"][i])
        except BadSceneError as e:
            return skip("corrupt image", f"frame {i}: {e}")
        shapes = {tuple(im.shape[1:]) for im in images.values()}
        if self.cfg.skip_bad_shape and shapes != {tuple(self.cfg.original_image_shape)}:
            return skip("unexpected image shape")
        if len(shapes) != 1:
            return skip("malformed scene", f"frames have different shapes {sorted(shapes)}")

        def views(indices: torch.Tensor) -> dict:
            v = {
                "extrinsics": extrinsics[indices],
                "intrinsics": intrinsics[indices],
                "image": torch.stack([images[i] for i in indices.tolist()]),
                "near": torch.full((len(indices),), near),
                "far": torch.full((len(indices),), far),
                "index": indices.to(torch.int64),
            }
            if "depths" in scene:
                v["depth"] = scene["depths"][indices].float()
            return v

        example = {"context": views(ctx), "target": views(tgt), "scene": key}
        if "depths" in scene and tuple(scene["depths"].shape[1:]) != shapes.pop():
            return skip("bad depth", "depth maps and images differ in shape")
        if self.cfg.make_baseline_1:
            try:
                example, _ = normalize_baseline(example, self.cfg.baseline_scale_bounds)
            except ValueError:
                return skip("baseline below 1e-3")
        if self.stage == "train" and self.cfg.augment:
            example = augment_flip(example, gen)
        for side in ("context", "target"):
            v = crop_views(example[side], self.cfg.image_shape)
            v["image"] = v["image"].float() / 255.0
            example[side] = v
        return example


def dataset_from_section(dcfg: dict, stage: str, step_tracker=None, rank: int | None = None,
                         world_size: int | None = None):
    """The dataset a config's ``dataset`` section describes (``name``, ``roots``,
    ``image_shape``, ``view_sampler``, ``overrides``, ``evaluation_index``) for ``stage``;
    outside training, ``evaluation_index`` selects the evaluation sampler."""
    check_keys(dcfg, {"name", "roots", "image_shape", "view_sampler", "overrides",
                      "evaluation_index"}, "dataset")
    if not dcfg.get("roots"):
        raise ConfigError("dataset.roots must name at least one dataset folder (e.g. "
                          "dataset.roots=[datasets/re10k]); make a synthetic one with "
                          "`usplat synth --out DIR`")
    kinds = {"bounded": ViewSamplerBoundedCfg, "evaluation": ViewSamplerEvaluationCfg,
             "all": ViewSamplerAllCfg}
    vs = dict(dcfg.get("view_sampler") or {"name": "bounded"})
    if stage != "train" and dcfg.get("evaluation_index"):
        vs = {"name": "evaluation", "index_path": dcfg["evaluation_index"]}
    name = vs.get("name", "bounded")
    if name not in kinds:
        raise ConfigError(f"dataset.view_sampler.name must be one of {sorted(kinds)}")
    fields = {f.name for f in dataclasses.fields(kinds[name])}
    check_keys(vs, fields, "dataset.view_sampler")
    sampler = kinds[name](**vs)
    over = dict(dcfg.get("overrides") or {})
    if "image_shape" in dcfg:
        over["image_shape"] = tuple(dcfg["image_shape"])
    cfg = dataset_cfg(dcfg.get("name", "re10k"), dcfg["roots"], view_sampler=sampler, **over)
    return ChunkDataset(cfg, stage, step_tracker, rank=rank, world_size=world_size)
