"""train/studies/gpu_prepare.sh (``scripts/run.sh gpu-prepare``), run at a tiny size: it renders
the sets, packs them where gpu_train.sh looks for them, keeps what it rendered for the next
call, and refuses a carry over the limit."""

import io
import json
import lzma
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from usplat_dr.data.chunks import decode_image

ROOT = Path(__file__).parents[2]
SCRIPT = ROOT / "train" / "studies" / "gpu_prepare.sh"


@pytest.mark.slow
def test_the_gpu_sets_are_rendered_packed_and_weighed(tmp_path):
    pytest.importorskip("mitsuba", reason="gpu_prepare.sh renders its sets with Mitsuba")
    packed = tmp_path / "gpudata"
    env = {**os.environ, "PYTHON": sys.executable, "SIZE": "32", "TRAIN_SCENES": "1",
           "HELDOUT_SCENES": "1", "FRAMES": "10", "JOBS": "1", "WHEEL": "0",
           "SYNTH_ARGS": "--spp 4 --kind indoor", "DATA": str(tmp_path / "data"),
           "GPUDATA": str(packed)}

    def prepare(**more):
        return subprocess.run(["bash", str(SCRIPT)], env={**env, **more}, capture_output=True,
                              text=True, timeout=600, check=False)

    proc = prepare()
    log = proc.stdout[-3000:] + proc.stderr[-3000:]
    assert proc.returncode == 0, log
    # where gpu_train.sh looks: GPUDATA/train (a train stage) and GPUDATA/heldout (a test root)
    assert (packed / "train" / "train" / "000000.torch.xz").is_file(), log
    assert (packed / "heldout" / "test" / "000000.torch.xz").is_file(), log
    assert list((packed / "heldout").glob("evaluation_index_*.json")), log
    assert "ready" in proc.stdout and "MB travel" in proc.stdout
    scenes = torch.load(io.BytesIO(lzma.decompress(
        (packed / "train" / "train" / "000000.torch.xz").read_bytes())), weights_only=False)
    assert len(scenes) == 1 and len(scenes[0]["images"]) == 10
    assert decode_image(scenes[0]["images"][0]).shape[-2:] == (32, 32)

    again = prepare(LIMIT_MB="1")  # the sets are kept; a 1 MB limit is below the tracked files
    assert "is there" in again.stdout, again.stdout[-2000:]
    assert again.returncode == 1 and "too much to carry" in again.stdout


def test_it_deletes_nothing_it_did_not_make(tmp_path):
    # a held-out set of another size where the script would render, and a folder of the
    # user's where it would pack: both refused by name, both left as they were, before any
    # rendering
    data = tmp_path / "data"
    other = data / "test5000"
    (other / "test").mkdir(parents=True)
    (other / "synth.json").write_text(json.dumps({"stage": "test", "scenes": 60, "seed": 5000,
                                                  "frames": 24, "resolution": [128, 128]}))
    mine = tmp_path / "my_results"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    env = {**os.environ, "PYTHON": sys.executable, "SIZE": "32", "TRAIN_SCENES": "1",
           "HELDOUT_SCENES": "1", "FRAMES": "10", "WHEEL": "0", "DATA": str(data)}

    def prepare(**more):
        return subprocess.run(["bash", str(SCRIPT)], env={**env, **more}, capture_output=True,
                              text=True, timeout=120, check=False)

    proc = prepare(GPUDATA=str(mine))
    assert proc.returncode == 2 and f"GPUDATA {mine} exists and is not a pack" in proc.stderr
    assert (mine / "notes.txt").read_text() == "keep me"
    proc = prepare(GPUDATA=str(tmp_path / "pack"))
    assert proc.returncode == 2 and f"{other} holds another set than this one" in proc.stderr
    assert (other / "synth.json").is_file() and (other / "test").is_dir()
    assert not (tmp_path / "pack").exists()
