"""Streaming the field's datasets (RealEstate10K, ACID, DTU, our synthetic sets) into examples.

``ChunkDataset`` is a torch ``IterableDataset`` over pixelSplat chunks, split across distributed
ranks and DataLoader workers ("global workers": ``ranks x workers`` of them). One process
without workers reads every chunk in turn. With several global workers the data is sharded
by scene, like torch's ``DistributedSampler``: the scenes of ``index.json`` are listed chunk by
chunk (in training, chunk order and the scenes inside each chunk are shuffled with a seed that
depends on the epoch, ``set_epoch``, identical on every rank), the list is padded by wrapping
around to a multiple of the global workers, and global worker ``g`` takes the ``g``-th
contiguous block. So every worker gets examples whatever the number of chunks (a one-chunk set
trains on 8 ranks), no scene is seen twice in an epoch except the fewer than ``ranks x
workers`` padding repeats, every worker yields the same number of examples (so every rank
takes the same number of batches an epoch), and a worker reads only the chunks its block spans
(at most two of them shared with another worker). Evaluation stages are not padded (no scene
counted twice).

Bad data never stops a run and is never silently lost: an unreadable chunk, a malformed
record, a corrupt image, a scene missing from ``index.json``, a camera with NaN or a singular
rotation, an evaluation-index entry naming frames the scene does not have are each skipped
with one warning naming the file and scene (tests/test_fuzz.py), and counted in the
summary logged at the end of every pass (``ChunkDataset.last_summary`` in the main process).
Expected skips (too few frames for the sampler, a null evaluation-index entry, FOV over
``max_fov``, unexpected image shape) are counted without a warning; in the test stage
(evaluation) the scenes the sampler gave no views (no index entry, too few frames) are also
warned about, once per pass, with their count and the first of them. A skipped scene shortens
its worker's pass by one example: the training stream (``usplat_dr.training.batches.Batches``)
is endless, so a rank whose pass ends early starts its next epoch early, never waits.
"""

import collections
import dataclasses
import functools
import hashlib
import logging
import math
import os
import typing
from dataclasses import dataclass, field
from pathlib import Path

import torch
import torch.distributed
from torch import Tensor
from torch.utils.data import IterableDataset, get_worker_info

from usplat_dr.config import (
    ConfigError,
    check_keys,
    load_config,
    load_typed,
    typed_value,
    where_set,
)
from usplat_dr.data.chunks import (
    MAX_IMAGE_PIXELS,
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
    FramesNotInSceneError,
    NullEntryError,
    StepTracker,
    ViewSamplerBoundedCfg,
    ViewSamplerCfg,
    ViewSamplerEvaluation,
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
    # Test stage: each scene is used this many times, as example ``<key>_00``, ``<key>_01``,
    # ... (MVSplat's ``test_times_per_scene``: its DTU evaluation index names scan1_train_00
    # .. scan1_train_03 for the one record scan1_train). 1: the key as it is.
    test_times_per_scene: int = 1


# docs/field_protocol.md, "Data": RE10K and ACID near 1 / far 100 with 360x640 JPEGs; DTU near
# 2.125 / far 4.525 (depth 425-905 scaled by 1/200), PNGs of any shape; synthetic sets carry
# per-scene bounds.
DATASET_PRESETS = {
    "re10k": dict(near=1.0, far=100.0, skip_bad_shape=True, original_image_shape=(360, 640)),
    "acid": dict(near=1.0, far=100.0, skip_bad_shape=True, original_image_shape=(360, 640)),
    "dtu": dict(near=2.125, far=4.525, skip_bad_shape=False, test_times_per_scene=4),
    "synth": dict(near=None, far=None, skip_bad_shape=False),
}

#: Each preset's packaged dataset config (``usplat_dr/configs/``): its training view sampler
#: is written there once, for configs and ``dataset_cfg`` alike (``preset_view_sampler``).
PRESET_CONFIGS = {"re10k": "dataset/re10k.yaml", "acid": "dataset/acid.yaml",
                  "dtu": "dataset/dtu.yaml", "synth": "dataset/synthetic.yaml"}


@functools.cache
def preset_view_sampler(name: str) -> ViewSamplerCfg:
    """The training view sampler of preset ``name``, read from its packaged config
    (``PRESET_CONFIGS``): the synthetic sets' frame gaps (4 to 8 frames between the context
    views) or MVSplat's RE10K/ACID ones (``ViewSamplerBoundedCfg``'s defaults).

    Examples:
        >>> s = preset_view_sampler("synth")
        >>> s.min_distance_between_context_views, s.max_distance_between_context_views
        (4, 8)
    """
    cfg = load_config(PRESET_CONFIGS[name])
    section = load_typed(DatasetSectionCfg, cfg["dataset"], "dataset", cfg.origins)
    assert section.name == name, (name, section.name)  # PRESET_CONFIGS names the wrong file
    return section.view_sampler


def dataset_cfg(name: str, roots, **overrides) -> DatasetCfg:
    """A ``DatasetCfg`` with the field's settings for ``name`` (re10k, acid, dtu, synth), and
    its training view sampler (``preset_view_sampler``) unless ``overrides`` names one.

    Examples:
        >>> cfg = dataset_cfg("dtu", ["datasets/dtu"])
        >>> cfg.near, cfg.far, cfg.skip_bad_shape
        (2.125, 4.525, False)
    """
    if name not in DATASET_PRESETS:
        raise ValueError(f"name must be one of {sorted(DATASET_PRESETS)}, got {name!r}")
    if isinstance(roots, (str, Path)):
        roots = [roots]
    return DatasetCfg(roots=tuple(str(r) for r in roots), name=name,
                      **{"view_sampler": preset_view_sampler(name), **DATASET_PRESETS[name],
                         **overrides})


#: Scene near/far planes outside this range are skipped: depth is sampled in disparity from
#: 1/far to 1/near, and Gaussian means reach ``far`` x the ray length, so values like 1e-30
#: or 1e30 (finite, but absurd) overflow float32 in the model. The field's: RE10K 1/100,
#: DTU 2.125/4.525; a scene in millimetres fits too.
NEAR_FAR_RANGE = (1e-6, 1e6)


class Summary(collections.Counter):
    """Counts of examples and skip reasons over one pass, and the first scene skipped for
    each reason (``first``)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.first: dict[str, str] = {}

    WARN = ("unreadable chunk", "malformed scene", "bad camera", "corrupt image",
            "not in index.json", "missing chunk file", "bad depth", "not in its chunk",
            "chunk not in index.json", "frames not in scene", "duplicate key")

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
        self._chunk_set = set(self.chunks)
        self.index: dict[str, Path] = {}
        self.missing_chunks: list[tuple[str, Path]] = []
        for root in cfg.roots:
            stage_dir = Path(root) / self.data_stage
            for key, name in read_index(stage_dir).items():
                path = stage_dir / name
                if key in self.index:
                    log.warning("scene %s is in the index of %s and of an earlier root (%s): "
                                "read once, from %s", key, stage_dir, self.index[key], path)
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

    def _global_worker(self) -> tuple[int, int]:
        """This process's global worker id and the number of global workers (ranks x
        DataLoader workers)."""
        rank, world = _distributed()
        rank = self.rank if self.rank is not None else rank
        world = self.world_size if self.world_size is not None else world
        info = get_worker_info()
        wid, nworkers = (info.id, info.num_workers) if info is not None else (0, 1)
        return rank * nworkers + wid, world * nworkers

    def shard(self, gid: int, total: int) -> list[tuple[Path, set[str] | None, bool]]:
        """What global worker ``gid`` of ``total`` reads this epoch, chunk by chunk:
        ``(chunk, keys, reports)`` with the scene keys it takes from the chunk (``None``: all)
        and whether it reports the chunk's own faults (unreadable, records of no scene in
        ``index.json``), so that each is reported once. See the module docstring.

        Examples:
            >>> ds = ChunkDataset.__new__(ChunkDataset)  # a 5-scene, 2-chunk set, by hand
            >>> ds.stage, ds.epoch, ds.chunks = "test", 0, [Path("a.torch"), Path("b.torch")]
            >>> ds.index = {"s0": Path("a.torch"), "s1": Path("a.torch"), "s2": Path("a.torch"),
            ...             "s3": Path("b.torch"), "s4": Path("b.torch")}
            >>> [(c.name, sorted(k)) for c, k, _ in ds.shard(1, 2)]  # blocks of 3: s0-s2 | s3 s4
            [('b.torch', ['s3', 's4'])]
        """
        chunks = list(self.chunks)
        if self.stage == "train":
            perm = torch.randperm(len(chunks), generator=torch.Generator().manual_seed(
                _seed(self.cfg.seed, self.epoch)))
            chunks = [chunks[i] for i in perm]
        if total == 1:  # every chunk, whole (and the order of runs before scene sharding)
            return [(c, None, True) for c in chunks]
        by_chunk = collections.defaultdict(list)
        for key, path in self.index.items():
            by_chunk[path].append(key)
        scenes: list[tuple[Path, str]] = []
        reporter: dict[Path, int] = {}  # chunk -> the block holding its first scene
        per = -(-sum(len(by_chunk[c]) for c in chunks) // total)  # scenes per worker
        for c in chunks:
            keys = sorted(by_chunk[c])
            if self.stage == "train":
                perm = torch.randperm(len(keys), generator=torch.Generator().manual_seed(
                    _seed(self.cfg.seed, self.epoch, c.name)))
                keys = [keys[i] for i in perm]
            if keys:
                reporter[c] = len(scenes) // per
            scenes += [(c, k) for k in keys]
        if self.stage == "train" and scenes:
            # DistributedSampler's padding: wrap around, so every worker takes ``per`` scenes
            scenes = [scenes[i % len(scenes)] for i in range(per * total)]
        block = scenes[gid * per:(gid + 1) * per]
        wanted: dict[Path, set[str]] = {}
        for c, key in block:  # in block order; a key is in a block at most once (per <= S)
            wanted.setdefault(c, set()).add(key)
        return [(c, keys, reporter[c] == gid) for c, keys in wanted.items()]

    def __iter__(self):
        gid, total = self._global_worker()
        gen = torch.Generator().manual_seed(_seed(self.cfg.seed, self.epoch, gid, self.stage))
        summary = Summary()
        summary["missing chunk file"] = len(self.missing_chunks) if gid == 0 else 0
        if total > 1 and gid == 0:
            indexed = set(self.index.values())
            for c in (c for c in self.chunks if c not in indexed):
                log.warning("skipping chunk %s: it holds no scene of index.json", c)
                summary["chunk not in index.json"] += 1
        for chunk_path, wanted, reports in self.shard(gid, total):
            try:
                scenes = read_chunk(chunk_path)
            except BadChunkError as e:
                if reports:
                    log.warning("skipping chunk: %s", e)
                    summary["unreadable chunk"] += 1
                continue
            order = (torch.randperm(len(scenes), generator=gen).tolist()
                     if self.stage == "train" else range(len(scenes)))
            seen: set[str] = set()
            for i in order:
                scene = scenes[i]
                key = scene.get("key") if isinstance(scene, dict) else None
                if isinstance(key, str) and key in seen:
                    log.warning("skipping scene %s in %s: duplicate key (a second record of it "
                                "in the same chunk)", key, chunk_path)
                    summary["duplicate key"] += 1
                    continue
                seen.add(key)
                if wanted is not None:
                    key = scene.get("key") if isinstance(scene, dict) else None
                    if isinstance(key, str) and key in wanted:
                        wanted.discard(key)
                    elif not (reports and not (isinstance(key, str) and key in self.index)):
                        continue  # another worker's scene (or another chunk's, by the index)
                for run in self._runs(scene):
                    example = self._example(scene, chunk_path, gen, summary, run)
                    if example is not None:
                        summary["examples"] += 1
                        yield example
            for key in sorted(wanted or ()):
                log.warning("skipping scene %s: index.json places it in %s, which does not "
                            "hold it", key, chunk_path)
                summary["not in its chunk"] += 1
        self.last_summary = summary
        worker = f" (worker {gid} of {total})" if total > 1 else ""
        log.info("%s %s epoch %d%s: %s", self.cfg.name, self.stage, self.epoch, worker,
                 summary.line())
        if self.stage == "test" and summary["sampler: no views"]:
            # Evaluation scores only the scenes the sampler gives views for: a key missing
            # from the evaluation index (another preset's keys, DTU's runs) scores nothing.
            log.warning("%s test%s: the view sampler gave no views for %d scene(s) (first: %s;"
                        " not in the evaluation index, or too few frames): not scored",
                        self.cfg.name, worker, summary["sampler: no views"],
                        summary.first["sampler: no views"])

    def run_names(self, key: str) -> list[str]:
        """The example names scene ``key`` goes by: the key, or in the test stage with
        ``test_times_per_scene`` = T > 1, ``<key>_00`` .. ``<key>_(T-1)`` (MVSplat's DTU
        index names the runs of ``scan1_train`` so) - unless the evaluation index has an entry
        for the key itself: data whose keys already name the runs is scored as it is."""
        times = self.cfg.test_times_per_scene if self.stage == "test" else 1
        if times <= 1 or (isinstance(self.view_sampler, ViewSamplerEvaluation)
                          and key in self.view_sampler.index):
            return [key]
        return [f"{key}_{t:02d}" for t in range(times)]

    def _runs(self, scene: object) -> list[str | None]:
        """The example keys a scene gives (``run_names``): ``[None]`` for its own key."""
        key = scene.get("key") if isinstance(scene, dict) else None
        if not isinstance(key, str):
            return [None]
        names = self.run_names(key)
        return [None] if names == [key] else names

    def _example(self, scene: object, chunk_path: Path, gen: torch.Generator,
                 summary: Summary, run: str | None = None) -> dict | None:
        """One example of ``scene``, or None when it is skipped (counted in ``summary``, with a
        warning for the reasons in ``Summary.WARN``); ``run``: the key it goes by
        (``_runs``), default the scene's own."""
        key = scene.get("key", "?") if isinstance(scene, dict) else "?"
        try:
            extrinsics, intrinsics = self._cameras(scene, key, chunk_path)
            ctx, tgt = self._frames(run or key, extrinsics.shape[0], intrinsics, gen)
            near, far = self._near_far(scene)
            images, shape = self._images(scene, sorted(set(ctx.tolist()) | set(tgt.tolist())))
            example = {"context": _side(scene, extrinsics, intrinsics, images, ctx, near, far),
                       "target": _side(scene, extrinsics, intrinsics, images, tgt, near, far),
                       "scene": run or key}
            _check_maps(scene, shape)
            return self._finish(example, gen)
        except _Skip as e:
            summary[e.reason] += 1
            summary.first.setdefault(e.reason, str(run or key))
            if e.reason in Summary.WARN:
                log.warning("skipping scene %s in %s: %s%s", key, chunk_path, e.reason,
                            f" ({e.detail})" if e.detail else "")
            return None

    def _cameras(self, scene: object, key: object, chunk_path: Path) -> tuple[Tensor, Tensor]:
        """The scene's checked record and cameras: (extrinsics [V, 4, 4], intrinsics);
        ``key`` as the record holds it (a bad record may hold anything)."""
        try:
            check_scene(scene)
        except BadSceneError as e:
            raise _Skip("malformed scene", str(e)) from None
        if key not in self.index:
            raise _Skip("not in index.json")
        if self.index[key] != chunk_path and self.index[key] in self._chunk_set:
            # the copy index.json points to is read too (an index naming a missing chunk is
            # answered by the copy that exists)
            raise _Skip("duplicate key", f"index.json places this key in {self.index[key]}")
        try:
            return cameras_to_matrices(scene["cameras"].float())
        except BadSceneError as e:
            raise _Skip("bad camera", str(e)) from None

    def _frames(self, run: str, num_views: int, intrinsics: Tensor, gen: torch.Generator
               ) -> tuple[Tensor, Tensor]:
        """The sampler's context and target frames of scene ``run``."""
        try:
            ctx, tgt = self.view_sampler.sample(run, num_views, gen)
        except FramesNotInSceneError as e:
            raise _Skip("frames not in scene", str(e)) from None
        except NullEntryError:  # the index's own "not evaluated"
            raise _Skip("null in evaluation index") from None
        except ViewSamplingError:  # too few frames for the bounded sampler, no index entry
            raise _Skip("sampler: no views") from None
        if (fov_degrees(intrinsics) > self.cfg.max_fov).any():
            raise _Skip("fov over max_fov")
        return ctx, tgt

    def _near_far(self, scene: dict) -> tuple[float, float]:
        """The config's near/far, else the scene's ``near_far`` record, checked."""
        if self.cfg.near is not None and self.cfg.far is not None:
            return self.cfg.near, self.cfg.far
        if "near_far" not in scene:
            raise _Skip("malformed scene", "no near/far in the config or the scene")
        try:
            near, far = (float(x) for x in scene["near_far"])
        except (TypeError, ValueError, RuntimeError) as e:
            raise _Skip("malformed scene", f"near_far is not two numbers ({e})") from None
        if not (NEAR_FAR_RANGE[0] <= near < far <= NEAR_FAR_RANGE[1]):
            raise _Skip("malformed scene", f"near_far must be {NEAR_FAR_RANGE[0]:g} <= near < "
                                           f"far <= {NEAR_FAR_RANGE[1]:g}, got {near}, {far}")
        return near, far

    def _images(self, scene: dict, needed: list[int]) -> tuple[dict, tuple[int, int]]:
        """The frames ``needed``, decoded ({frame: uint8 [3, H, W]}), and their one shape."""
        images = {}
        for i in needed:
            try:
                images[i] = decode_image(scene["images"][i])
            except BadSceneError as e:
                raise _Skip("corrupt image", f"frame {i}: {e}") from None
        shapes = {tuple(im.shape[1:]) for im in images.values()}
        if len(shapes) != 1:
            raise _Skip("malformed scene", f"frames have different shapes {sorted(shapes)}")
        if self.cfg.skip_bad_shape and shapes != {tuple(self.cfg.original_image_shape)}:
            raise _Skip("unexpected image shape")  # the field's: other shapes are skipped
        return images, shapes.pop()

    def _finish(self, example: dict, gen: torch.Generator) -> dict:
        """The field's shims: the baseline made 1 (when configured), the training stage's
        flip, the crop to ``image_shape``, images as floats in [0, 1]."""
        if self.cfg.make_baseline_1:
            try:
                example, _ = normalize_baseline(example, self.cfg.baseline_scale_bounds)
            except ValueError:
                raise _Skip("baseline below 1e-3") from None
        if self.stage == "train" and self.cfg.augment:
            example = augment_flip(example, gen)
        for side in ("context", "target"):
            try:
                v = crop_views(example[side], self.cfg.image_shape)
            except ValueError as e:
                raise _Skip("malformed scene", str(e)) from None
            v["image"] = v["image"].float() / 255.0
            example[side] = v
        return example


class _Skip(Exception):
    """A scene ``ChunkDataset`` skips: the ``Summary`` reason and a detail for the warning."""

    def __init__(self, reason: str, detail: str = ""):
        super().__init__(reason)
        self.reason, self.detail = reason, detail


def _side(scene: dict, extrinsics: Tensor, intrinsics: Tensor, images: dict,
          indices: Tensor, near: float, far: float) -> dict:
    """One side of an example (see ``usplat_dr.data.shims`` for the fields), uint8 images."""
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
    if "materials" in scene:  # synthetic sets: material codes, as floats (resizing)
        v["material"] = scene["materials"][indices].float()
    return v


def _check_maps(scene: dict, shape: tuple[int, int]) -> None:
    """Depth and material maps, where the scene has them, of the images' shape."""
    if "depths" in scene and tuple(scene["depths"].shape[1:]) != shape:
        raise _Skip("bad depth", "depth maps and images differ in shape")
    if "materials" in scene and tuple(scene["materials"].shape[1:]) != shape:
        raise _Skip("malformed scene", "material maps and images differ in shape")


@dataclass(frozen=True)
class DatasetSectionCfg:
    """A config's ``dataset`` section (``usplat_dr.config.load_typed`` loads it, with
    ``RootCfg``'s other sections, and ``checked`` checks it once): which preset, where the
    data is, and the ``DatasetCfg`` fields it sets for every stage (``dataset_cfg``).

    Examples:
        >>> section = load_typed(DatasetSectionCfg, {"roots": ["d"], "image_shape": [32, 48]})
        >>> section.roots, section.sampler("train").name, section.dataset_overrides()
        (('d',), 'bounded', {'image_shape': (32, 48)})
        >>> load_typed(DatasetSectionCfg, {"name": "imagenet"}, "dataset")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        usplat_dr.config.ConfigError: dataset.name='imagenet' must be one of ['acid', ...
    """

    name: str = "re10k"  # DATASET_PRESETS: the field's near/far and image-shape settings
    # dataset folders (one, or a list); checked by dataset_from_section, which needs them
    roots: str | tuple[str, ...] = ()
    image_shape: tuple[int, int] | None = None  # views are cropped to it (None: DatasetCfg's)
    view_sampler: ViewSamplerCfg = field(default_factory=ViewSamplerBoundedCfg)  # training's
    overrides: dict = field(default_factory=dict)  # other fields of DatasetCfg
    # outside training: an evaluation index JSON, whose context/target frames replace the
    # view sampler's
    evaluation_index: str | None = None

    @classmethod
    def from_dict(cls, section: dict) -> "DatasetSectionCfg":
        """The section from the plain mapping that evaluation code passes (``name``,
        ``roots``, ``image_shape``, ``evaluation_index``...: folders and files as
        ``os.PathLike`` or ``str``), checked like a config's. Without a ``view_sampler``, the
        preset's (``preset_view_sampler``)."""
        if isinstance(section, dict):
            section = dict(section)
            name = section.get("name", cls.name)
            if "view_sampler" not in section and name in PRESET_CONFIGS:
                section["view_sampler"] = dataclasses.asdict(preset_view_sampler(name))
            roots = section.get("roots")
            if isinstance(roots, os.PathLike):
                section["roots"] = os.fspath(roots)
            elif isinstance(roots, (list, tuple)):
                section["roots"] = [os.fspath(r) if isinstance(r, os.PathLike) else r
                                     for r in roots]
            if isinstance(section.get("evaluation_index"), os.PathLike):
                section["evaluation_index"] = os.fspath(section["evaluation_index"])
        return load_typed(cls, section, "dataset")

    def checked(self, section: str = "dataset",
                origins: dict[str, str] | None = None) -> "DatasetSectionCfg":
        """This section checked without reading the disk, in its normal form (``roots`` a
        tuple, ``overrides`` typed by ``DatasetCfg``'s fields): a preset name, overrides of
        known fields and types, image shapes of at most ``MAX_IMAGE_PIXELS``, and 0 < near <
        far; else a ``ConfigError`` naming the key and, given ``origins``
        (``Config.origins``), the file or override that set it."""
        origins, section = origins or {}, section or "dataset"
        if self.name not in DATASET_PRESETS:
            raise ConfigError(f"{section}.name={self.name!r} must be one of "
                              f"{sorted(DATASET_PRESETS)} "
                              f"(set in {where_set(origins, f'{section}.name')})")
        overrides = self._typed_overrides(section, origins)
        shapes = {f"{section}.overrides.image_shape": overrides.get("image_shape"),
                  f"{section}.image_shape": self.image_shape}
        for key, shape in shapes.items():
            # views are decoded and cropped to these shapes: beyond MAX_IMAGE_PIXELS, a typo
            if shape is not None and not (
                    min(shape) >= 1 and shape[0] * shape[1] <= MAX_IMAGE_PIXELS):
                raise ConfigError(f"{key}={list(shape)} must be two sizes >= 1, at most "
                                  f"{MAX_IMAGE_PIXELS:,} pixels (set in "
                                  f"{where_set(origins, key)})")
        defaults = {f.name: f.default for f in dataclasses.fields(DatasetCfg)
                    if f.name in ("near", "far")}
        bounds = {**defaults, **DATASET_PRESETS[self.name], **overrides}
        near, far = bounds["near"], bounds["far"]
        if near is not None and far is not None and not (
                math.isfinite(near) and math.isfinite(far) and 0 < near < far):
            raise ConfigError(f"{section} near={near}, far={far} must be 0 < near < far (set "
                              f"in {where_set(origins, f'{section}.overrides')})")
        roots = (self.roots,) if isinstance(self.roots, str) else self.roots
        return dataclasses.replace(self, roots=roots, overrides=overrides)

    def _typed_overrides(self, section: str, origins: dict[str, str]) -> dict:
        """``overrides`` checked against ``DatasetCfg``'s fields (``roots``, ``name`` and
        ``view_sampler`` have keys of their own here) and typed by them."""
        key = f"{section}.overrides"
        known = {f.name for f in dataclasses.fields(DatasetCfg)} - {"roots", "name",
                                                                     "view_sampler"}
        check_keys(self.overrides, known, key, origins)
        hints = typing.get_type_hints(DatasetCfg)
        return {k: typed_value(hints[k], v, f"{key}.{k}", origins)
                for k, v in self.overrides.items()}

    def sampler(self, stage: str) -> ViewSamplerCfg:
        """The view sampler of ``stage``: outside training, ``evaluation_index``'s when set."""
        if stage != "train" and self.evaluation_index:
            return ViewSamplerEvaluationCfg(self.evaluation_index)
        return self.view_sampler

    def dataset_overrides(self) -> dict:
        """The ``DatasetCfg`` fields the section sets (``image_shape`` over the same key of
        ``overrides``)."""
        shape = {} if self.image_shape is None else {"image_shape": self.image_shape}
        return {**self.overrides, **shape}


def dataset_from_section(section: DatasetSectionCfg | dict, stage: str, step_tracker=None,
                         rank: int | None = None, world_size: int | None = None):
    """The dataset a config's ``dataset`` section describes for ``stage``: a loaded
    ``DatasetSectionCfg`` (``RootCfg.dataset``), or the plain mapping evaluation code passes
    (``{"name": "synth", "roots": [...], "image_shape": [...]}``, checked here). Outside
    training, ``evaluation_index`` selects the evaluation sampler."""
    if not isinstance(section, DatasetSectionCfg):
        section = DatasetSectionCfg.from_dict(section)
    if not section.roots:
        raise ConfigError("dataset.roots must name at least one dataset folder (e.g. "
                          "dataset.roots=[datasets/re10k]); make a synthetic one with "
                          "`usplat synth --out DIR`")
    cfg = dataset_cfg(section.name, section.roots, view_sampler=section.sampler(stage),
                      **section.dataset_overrides())
    return ChunkDataset(cfg, stage, step_tracker, rank=rank, world_size=world_size)
