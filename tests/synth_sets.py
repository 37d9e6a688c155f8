"""The small Mitsuba-rendered sets the tests train and evaluate on, by name.

``synthetic_set(name, folder)`` renders one with ``usplat_dr.data.synth.synthesize``. A machine
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


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: python -m tests.synth_sets DIR")
    import usplat_dr  # noqa: F401  (libLLVM before Mitsuba imports drjit)

    for set_name in SETS:
        render(set_name, Path(sys.argv[1]) / set_name)
        print(f"rendered {set_name} into {Path(sys.argv[1]) / set_name}")
