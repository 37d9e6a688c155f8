"""View samplers: which frames of a scene become context and target views.

Behaviour follows pixelSplat/MVSplat (``src/dataset/view_sampler``; docs/field_protocol.md,
"Data").
A sampler raises ``ViewSamplingError`` when a scene cannot give an example (too few frames, no
entry in the evaluation index); the dataset counts such scenes and moves on.
"""

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
from jaxtyping import Int64
from torch import Tensor

Stage = Literal["train", "val", "test"]


class ViewSamplingError(ValueError):
    """The scene cannot give an example with this sampler (an expected, counted skip)."""


class NullEntryError(ViewSamplingError):
    """The evaluation index's entry for the scene is null: the index's own "not evaluated"
    (counted, no warning; a key missing from the index is a plain ``ViewSamplingError``)."""


class FramesNotInSceneError(ViewSamplingError):
    """An evaluation index names frames the scene does not have: the index and the data
    disagree (a skip with a warning, unlike a scene too short for the bounded sampler)."""


class StepTracker:
    """The global training step, shared with DataLoader worker processes (shared memory), so
    the bounded sampler's gap schedule follows training in every worker."""

    def __init__(self, step: int = 0):
        self._step = torch.tensor([step], dtype=torch.int64).share_memory_()

    def set_step(self, step: int) -> None:
        self._step[0] = step

    def get_step(self) -> int:
        return int(self._step[0])


@dataclass(frozen=True)
class ViewSamplerBoundedCfg:
    """Training sampler. Defaults: MVSplat's RE10K/ACID values (bounded_re10k.yaml)."""

    name: Literal["bounded"] = "bounded"
    num_context_views: int = 2
    num_target_views: int = 4
    min_distance_between_context_views: int = 45
    max_distance_between_context_views: int = 192
    min_distance_to_context_views: int = 0
    warm_up_steps: int = 150_000
    initial_min_distance_between_context_views: int = 25
    initial_max_distance_between_context_views: int = 45
    # False reproduces the field: pixelSplat sets max_gap = min(V - 1, min_gap), so the gap is
    # always the scheduled minimum. True draws the gap from the full [min, max] range.
    full_range: bool = False
    # > 0: targets are drawn from up to this many frames beyond each context view (clipped to
    # the scene's frames) as well as between them: extrapolated targets in training. 0 (the
    # field's sampler): between the context views only.
    max_distance_beyond_context_views: int = 0


@dataclass(frozen=True)
class ViewSamplerEvaluationCfg:
    """Fixed context/target frames per scene from an index JSON (key -> null or
    {"context": [...], "target": [...]})."""

    index_path: str
    name: Literal["evaluation"] = "evaluation"
    num_context_views: int = 2


@dataclass(frozen=True)
class ViewSamplerAllCfg:
    """Every frame is both context and target (visualisation, overfitting checks)."""

    name: Literal["all"] = "all"


ViewSamplerCfg = ViewSamplerBoundedCfg | ViewSamplerEvaluationCfg | ViewSamplerAllCfg


class ViewSamplerBounded:
    """Two context views ``gap`` frames apart, targets drawn uniformly (with replacement)
    between them (or, with ``max_distance_beyond_context_views``, from that many frames
    beyond each context view as well).

    Examples:
        >>> s = ViewSamplerBounded(ViewSamplerBoundedCfg(), "train", StepTracker(0))
        >>> ctx, tgt = s.sample("scene", 100, torch.Generator().manual_seed(0))
        >>> (ctx[1] - ctx[0]).item(), len(tgt)
        (25, 4)
    """

    def __init__(self, cfg: ViewSamplerBoundedCfg, stage: Stage,
                 step_tracker: StepTracker | None = None):
        if cfg.num_context_views != 2:
            raise ValueError("the bounded sampler picks exactly 2 context views "
                             f"(num_context_views=2), got {cfg.num_context_views}")
        self.cfg, self.stage = cfg, stage
        self.step_tracker = step_tracker

    @property
    def global_step(self) -> int:
        return 0 if self.step_tracker is None else self.step_tracker.get_step()

    def schedule(self, initial: int, final: int) -> int:
        fraction = self.global_step / self.cfg.warm_up_steps
        return min(initial + int((final - initial) * fraction), final)

    def gap_range(self, num_views: int) -> tuple[int, int]:
        """The (min, max) context gap for a scene of ``num_views`` frames at the current step."""
        cfg = self.cfg
        if self.stage == "test":
            min_gap = max_gap = cfg.max_distance_between_context_views
        elif cfg.warm_up_steps > 0:
            max_gap = self.schedule(cfg.initial_max_distance_between_context_views,
                                    cfg.max_distance_between_context_views)
            min_gap = self.schedule(cfg.initial_min_distance_between_context_views,
                                    cfg.min_distance_between_context_views)
        else:
            max_gap = cfg.max_distance_between_context_views
            min_gap = cfg.min_distance_between_context_views
        max_gap = min(num_views - 1, max_gap if cfg.full_range else min_gap)
        min_gap = max(2 * cfg.min_distance_to_context_views, min_gap)
        return min_gap, max_gap

    def sample(self, scene: str, num_views: int, generator: torch.Generator
               ) -> tuple[Int64[Tensor, " context"], Int64[Tensor, " target"]]:
        min_gap, max_gap = self.gap_range(num_views)
        if max_gap < min_gap:
            raise ViewSamplingError(f"scene {scene} has {num_views} frames; a context gap of "
                                    f"{min_gap} needs {min_gap + 1}")
        gap = int(torch.randint(min_gap, max_gap + 1, (), generator=generator))
        left = 0 if self.stage == "test" else int(torch.randint(num_views - gap, (),
                                                                generator=generator))
        right = left + gap
        if self.stage == "test":
            target = torch.arange(left, right + 1)
        elif self.cfg.max_distance_beyond_context_views:
            e = self.cfg.max_distance_beyond_context_views
            target = torch.randint(max(0, left - e), min(num_views - 1, right + e) + 1,
                                   (self.cfg.num_target_views,), generator=generator)
        else:
            d = self.cfg.min_distance_to_context_views
            target = torch.randint(left + d, right + 1 - d, (self.cfg.num_target_views,),
                                   generator=generator)
        return torch.tensor([left, right]), target


class ViewSamplerEvaluation:
    """Context and target frames read from an evaluation index.

    Examples:
        >>> import tempfile, json, pathlib
        >>> p = pathlib.Path(tempfile.mkdtemp()) / "idx.json"
        >>> _ = p.write_text(json.dumps({"a": {"context": [0, 5], "target": [2, 3]}, "b": None}))
        >>> s = ViewSamplerEvaluation(ViewSamplerEvaluationCfg(str(p)))
        >>> [t.tolist() for t in s.sample("a", 10)]
        [[0, 5], [2, 3]]
    """

    def __init__(self, cfg: ViewSamplerEvaluationCfg, stage: Stage = "test",
                 step_tracker: StepTracker | None = None):
        self.cfg = cfg
        self.index = read_evaluation_index(cfg.index_path)

    def sample(self, scene: str, num_views: int, generator: torch.Generator | None = None
               ) -> tuple[Int64[Tensor, " context"], Int64[Tensor, " target"]]:
        if scene not in self.index:
            raise ViewSamplingError(f"scene {scene} has no entry in {self.cfg.index_path}")
        entry = self.index[scene]
        if entry is None:
            raise NullEntryError(f"scene {scene}'s entry in {self.cfg.index_path} is null")
        last = max(entry["context"] + entry["target"])  # a Python int: any size compares
        if last >= num_views:
            raise FramesNotInSceneError(f"the entry of {scene} in {self.cfg.index_path} names "
                                        f"frame {last}, but the scene has {num_views} frames")
        return torch.tensor(entry["context"]), torch.tensor(entry["target"])


class ViewSamplerAll:
    def __init__(self, cfg: ViewSamplerAllCfg, stage: Stage = "test",
                 step_tracker: StepTracker | None = None):
        self.cfg = cfg

    def sample(self, scene: str, num_views: int, generator: torch.Generator | None = None
               ) -> tuple[Int64[Tensor, " context"], Int64[Tensor, " target"]]:
        all_views = torch.arange(num_views)
        return all_views, all_views


def read_evaluation_index(path: str | os.PathLike) -> dict[str, dict | None]:
    """Read and check an evaluation index (scene key -> null or {"context": [...],
    "target": [...]})."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"evaluation index {path} does not exist (index_path)")
    try:
        index = json.loads(path.read_text(encoding="utf-8"))
    except RecursionError:  # JSON nested deeper than Python's recursion limit
        raise ValueError(f"evaluation index {path} is nested too deeply to be an index"
                         ) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"evaluation index {path} is not valid JSON ({e})") from None
    if not isinstance(index, dict):
        raise ValueError(f"evaluation index {path} must be a JSON object")
    for key, entry in index.items():
        if entry is None:
            continue
        ok = (isinstance(entry, dict) and {"context", "target"} <= set(entry)
              and all(isinstance(entry[k], list) and entry[k] for k in ("context", "target")))
        frames = entry["context"] + entry["target"] if ok else []
        # bool is an int subclass in Python; JSON true/false is not a frame number
        if not ok or not all(isinstance(i, int) and not isinstance(i, bool) and i >= 0
                             for i in frames):
            raise ValueError(f"evaluation index {path}: entry {key!r} must be null or "
                             '{"context": [ints >= 0], "target": [ints >= 0]}, '
                             f"got {entry!r}")
    return index


VIEW_SAMPLERS = {"bounded": ViewSamplerBounded, "evaluation": ViewSamplerEvaluation,
                 "all": ViewSamplerAll}


def get_view_sampler(cfg: ViewSamplerCfg, stage: Stage, step_tracker: StepTracker | None = None):
    return VIEW_SAMPLERS[cfg.name](cfg, stage, step_tracker)
