"""The small Mitsuba-rendered sets the tests train and evaluate on, by name, and the tiny
training configuration they train with.

``synthetic_set(name, folder)`` renders one with ``usplat_dr.data.synth.synthesize``; tests take
them as the session fixtures ``trainer_set`` and ``protocol_set`` (``tests/conftest.py``),
rendered once per test run and read only (a test that changes files renders its own). A machine
without Mitsuba (a GPU image that runs ``scripts/run.sh gpu-check``) uses the same set rendered
beforehand elsewhere, under ``$USPLAT_TEST_DATA/<name>``; without either the test skips::

    python -m tests.synth_sets DIR     # render every set into DIR/<name> (needs Mitsuba)
"""

import os
import sys
from pathlib import Path

import pytest

#: name -> list of ``synthesize`` calls (one per stage): every set is 2 indoor scenes of 10
#: frames at 32x32, 4 spp.
SETS = {
    "trainer": [{"stage": "train", "seed": 0}, {"stage": "test", "seed": 1}],
    "protocol": [{"stage": "test", "seed": 3}],
}
COMMON = {"scenes": 2, "frames": 10, "resolution": (32, 32), "spp": 4, "previews": 0,
          "progress": False, "kinds": ("indoor",)}


def render(name: str, root: Path) -> Path:
    from usplat_dr.data.synth import synthesize

    for call in SETS[name]:
        synthesize(root, **COMMON, **call)
    return root


def synthetic_set(name: str, folder: Path) -> Path:
    """The set ``name``, rendered into ``folder`` (Mitsuba) or pre-rendered; skips otherwise."""
    try:
        import mitsuba  # noqa: F401
    except ImportError:
        prebuilt = Path(os.environ.get("USPLAT_TEST_DATA", "/nonexistent")) / name
        if all((prebuilt / call["stage"] / "index.json").is_file() for call in SETS[name]):
            return prebuilt  # every stage rendered (an interrupted pre-render is not used)
        pytest.skip(f"no Mitsuba to render the {name!r} set, and no $USPLAT_TEST_DATA/{name} "
                    f"(python -m tests.synth_sets DIR renders it on a machine with Mitsuba)")
    return render(name, folder)


#: What every tiny training run of the tests shares: 32x32 images, two targets, context views
#: at most 6 frames apart (the sets have 10), no progress bar and no validation.
TINY_TRAINING = ("dataset.image_shape=[32, 32]", "train.progress=false",
                 "train.validate_every=100000",
                 "dataset.view_sampler.max_distance_between_context_views=6",
                 "dataset.view_sampler.initial_max_distance_between_context_views=6",
                 "dataset.view_sampler.num_target_views=2")


def tiny_training_config(config: str | Path, root: Path, out: Path, steps: int,
                         *overrides: str) -> dict:
    """The configuration ``config`` (a name under ``configs/`` or a path) with
    ``TINY_TRAINING``, on ``root``, writing to ``out``, for ``steps`` steps; ``overrides`` last
    (they win)."""
    from usplat_dr.config import load_config

    return load_config([config], [f"dataset.roots=[{root}]", f"output_dir={out}",
                                  f"train.steps={steps}", *TINY_TRAINING, *overrides])


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: python -m tests.synth_sets DIR")
    import usplat_dr  # noqa: F401  (libLLVM before Mitsuba imports drjit)

    for set_name in SETS:
        render(set_name, Path(sys.argv[1]) / set_name)
        print(f"rendered {set_name} into {Path(sys.argv[1]) / set_name}")
