"""The demo's run recipes, shared by ``usplat demo``, ``usplat bench`` and the studies in
``train/studies/``: the recipes (``RunRecipe``, ``RECIPES``: data, fine-tuning steps), the size
preset, the training run's config (``training_config``) and the synthetic data
(``ensure_data``). The shipped checkpoints the runs start from are
``usplat_dr.training.checkpoints``'s registry (``BASE``, ``SHIPPED``)."""

import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import torch

from usplat_dr.config import load_config
from usplat_dr.data.synth import synthesize


@dataclass(frozen=True)
class RunRecipe:
    """How much a demo run does: its data and its fine-tuning steps ("recipe", not "budget":
    a Gaussian budget is ``usplat_dr.model.budget.GaussianBudget``)."""

    train_scenes: int  # the brief fine-tuning's training set
    test_scenes: int  # fresh held-out scenes (a seed no checkpoint was trained or tested on)
    frames: int
    size: int
    steps: int  # brief fine-tuning steps per variant
    spp: int
    scratch_steps: int  # `usplat bench`'s presets without a shipped checkpoint: from scratch


RECIPES = {
    "full": RunRecipe(train_scenes=24, test_scenes=48, frames=24, size=64, steps=150, spp=64,
                      scratch_steps=700),
    "quick": RunRecipe(train_scenes=3, test_scenes=3, frames=12, size=32, steps=4, spp=8,
                       scratch_steps=12),
}
#: The demo's size preset: the smallest within 0.3 dB of the best in `usplat bench`
#: (train/bench/README.md, "Speed against accuracy").
PRESET = "tiny"
#: The brief fine-tuning's recipe (the verdict study's, fewer steps).
FINETUNE_LR = 2e-4


#: The packaged config the demo's runs start from (usplat_dr/configs/).
CONFIG = "synthetic_tiny_depth.yaml"


def training_config(data: Path, out: Path, recipe: RunRecipe, variant: str,
                    preset: str = "tiny", init: Path | None = None) -> dict:
    """The demo's training run: with ``init`` (a trained (a)) the paper's fine-tuning
    protocol at ``FINETUNE_LR``; without, from scratch (``usplat bench``'s other presets)."""
    gap_max = max(4, recipe.frames // 3)
    start = ([f"model.init_from={init}", f"optimizer.lr={FINETUNE_LR}",
              "optimizer.warm_up_fraction=0.05"] if init else ["optimizer.lr=1e-3"])
    steps = recipe.steps if init else recipe.scratch_steps
    return load_config([CONFIG], [
        f"dataset.roots=[{data}]", f"dataset.image_shape=[{recipe.size},{recipe.size}]",
        f"output_dir={out}", f"model.variant={variant}", f"model.preset={preset}",
        f"train.steps={steps}", f"train.checkpoint_every={max(steps // 4, 1)}",
        f"train.validate_every={steps}", "train.log_every=5", *start,
        # one job the user waits for: every free core (the config's one thread suits studies
        # that run seeds side by side; here 2 threads fine-tuned in 27 s against 34 s)
        "threads=null",
        "dataset.view_sampler.min_distance_between_context_views=3",
        "dataset.view_sampler.initial_min_distance_between_context_views=3",
        f"dataset.view_sampler.max_distance_between_context_views={gap_max}",
        f"dataset.view_sampler.initial_max_distance_between_context_views={gap_max}"])


def ensure_data(out: Path, recipe: str, seed: int = 0, jobs: int = 0) -> bool:
    """The demo's synthetic train and test sets in ``out/data`` (kept when they match
    ``recipe`` and ``seed``; else remade, and runs trained on older data removed). Returns
    whether it rendered them."""
    b = RECIPES[recipe]
    data = out / "data"
    stamp = data / "demo.json"
    spec = {"recipe": recipe, "seed": seed, **b.__dict__}
    if stamp.is_file() and json.loads(stamp.read_text()) == spec:
        return False
    shutil.rmtree(data, ignore_errors=True)
    for old in [*out.glob("train_*"), *out.glob("eval_*"), out / "bench"]:
        shutil.rmtree(old, ignore_errors=True)
    cores = jobs or min(2, torch.get_num_threads())
    synthesize(data, scenes=b.train_scenes, frames=b.frames, resolution=(b.size, b.size),
               seed=seed, spp=b.spp, stage="train", previews=0, jobs=cores)
    synthesize(data, scenes=b.test_scenes, frames=b.frames, resolution=(b.size, b.size),
               seed=seed + 1000, spp=b.spp, stage="test", previews=4, jobs=cores)
    stamp.write_text(json.dumps(spec))
    return True
