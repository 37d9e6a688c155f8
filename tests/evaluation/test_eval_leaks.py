"""``usplat eval`` says when its scores are not what they seem: scenes the checkpoint trained
on, an evaluation index that names no scene of the data, scenes the view sampler gives no
views for."""

import json
import logging

import torch

from tests.data.fakes import fake_scene, write_plain_dataset
from usplat_dr.cli import main
from usplat_dr.data.dataset import dataset_from_section
from usplat_dr.data.synth import synthesize
from usplat_dr.evaluation import evaluate
from usplat_dr.evaluation.provenance import keys_in_training, training_keys
from usplat_dr.model import UniqueSplat


def _warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]


def test_training_keys_are_the_train_stages(tmp_path):
    write_plain_dataset(tmp_path / "a", "train", [[fake_scene("s1", 3, shape=(8, 8))]])
    write_plain_dataset(tmp_path / "b", "train", [[fake_scene("s0", 3, shape=(8, 8))]])
    write_plain_dataset(tmp_path / "b", "test", [[fake_scene("t0", 3, shape=(8, 8))]])
    assert training_keys([tmp_path / "a", tmp_path / "b", tmp_path / "none"]) == ["s0", "s1"]
    assert keys_in_training({"t0", "s1"}, {"train_keys": ["s0", "s1"]}) == ["s1"]
    assert keys_in_training({"s1"}, {"data": {"a": "hash"}}) is None  # an old checkpoint


def test_eval_warns_about_scenes_the_checkpoint_trained_on(tmp_path, caplog):
    root = tmp_path / "data"
    synthesize(root, scenes=1, frames=4, resolution=(32, 32), seed=4, spp=1, stage="test",
               previews=0, progress=False, kinds=("indoor",))
    torch.manual_seed(0)
    model = UniqueSplat.from_preset("tiny", variant="baseline")
    ckpt = tmp_path / "model.ckpt"
    torch.save({"model": model.state_dict(), "model_config": model.cfg.to_dict(), "step": 1,
                "config": {"dataset": {"image_shape": [32, 32]}},
                "provenance": {"train_keys": ["indoor_4_00000", "indoor_9_00000"]}}, ckpt)
    caplog.set_level(logging.WARNING)
    assert main(["-q", "eval", "--checkpoint", str(ckpt), "--data", str(root), "--splits",
                 "standard", "--out", str(tmp_path / "eval")]) == 0
    leaks = [m for m in _warnings(caplog) if "training data" in m]
    assert leaks == [("1 evaluated scene(s) are in the checkpoint's training data (first: "
                      "indoor_4_00000): their scores are not held out")]
    summary = json.loads((tmp_path / "eval" / "summary.json").read_text())
    assert summary["scenes_in_training_data"] == 1

    # A checkpoint from before train_keys: nothing to check, no warning, no count.
    caplog.clear()
    summary = evaluate(model, {"name": "synth", "roots": [str(root)], "image_shape": [32, 32]},
                       {"standard": str(root / "evaluation_index_standard.json")},
                       tmp_path / "old", progress=False, images_per_split=0,
                       provenance={"data": {str(root): "hash"}})
    assert not [m for m in _warnings(caplog) if "training data" in m]
    assert "scenes_in_training_data" not in summary


def test_an_index_matching_no_scene_and_sceneless_samples_are_warnings(tmp_path, caplog):
    # The DTU preset runs each scan as <key>_00.._03; an index naming other scans scores
    # nothing: once silently, now two warnings (the index, the sampler).
    from usplat_dr.evaluation.protocol import warn_unmatched_index

    scenes = [fake_scene(f"scan{i}_train", 10, shape=(64, 80), fmt="png", seed=i, fx=0.9)
              for i in (1, 4)]
    write_plain_dataset(tmp_path, "test", [scenes])
    index = tmp_path / "index.json"
    index.write_text(json.dumps({f"scan{i}_train": {"context": [0, 4], "target": [2]}
                                 for i in (2, 3)}))
    section = {"name": "dtu", "roots": [str(tmp_path)], "image_shape": [32, 32],
               "evaluation_index": str(index)}
    ds = dataset_from_section(section, "test")
    caplog.set_level(logging.WARNING)
    assert list(ds) == []
    warn_unmatched_index(ds, "standard", index)
    (sampler, unmatched) = _warnings(caplog)
    assert "the view sampler gave no views for 8 scene(s) (first: scan1_train_00" in sampler
    assert (f"standard: evaluation index {index} matches no scene of the data (2 keys, e.g. "
            "scan2_train; the data's 8 scenes are named e.g. scan1_train_00)") in unmatched

    # Null entries are the index's own "not evaluated": counted, not warned about; and an
    # index that names the runs matches.
    caplog.clear()
    runs = {f"scan{i}_train_{t:02d}": None for i in (1, 4) for t in range(4)}
    index.write_text(json.dumps(runs))
    ds = dataset_from_section(section, "test")
    assert list(ds) == [] and ds.last_summary["null in evaluation index"] == 8
    warn_unmatched_index(ds, "standard", index)
    assert _warnings(caplog) == []


def test_dtu_data_whose_keys_are_the_index_keys_is_scored(tmp_path, caplog):
    # The DTU preset runs each scan as <key>_00.._03 (MVSplat's index names scan1_train_00 for
    # the record scan1_train). Data whose keys already are the index's keys (the runs written
    # out, or one entry per scan) once scored 0 of 2 scenes; a key with an entry of its own in
    # the index is now used as it is, and the runs of the other scans still apply.
    from usplat_dr.evaluation.protocol import index_coverage, scene_keys, warn_unmatched_index

    scenes = [fake_scene(key, 10, shape=(64, 80), fmt="png", seed=i, fx=0.9)
              for i, key in enumerate(["scan1_train_00", "scan4_train", "scan6_train"])]
    write_plain_dataset(tmp_path, "test", [scenes])
    index = tmp_path / "index.json"
    entries = {"scan1_train_00": {"context": [0, 4], "target": [2]},
               "scan4_train": {"context": [1, 5], "target": [3]},
               **{f"scan6_train_{t:02d}": {"context": [t, t + 4], "target": [t + 2]}
                  for t in range(4)}}
    index.write_text(json.dumps(entries))
    section = {"name": "dtu", "roots": [str(tmp_path)], "image_shape": [32, 32],
               "evaluation_index": str(index)}
    ds = dataset_from_section(section, "test")
    assert ds.cfg.test_times_per_scene == 4
    caplog.set_level(logging.WARNING)
    warn_unmatched_index(ds, "standard", index)
    examples = list(ds)
    scored = [e["scene"] for e in examples]
    assert scored == ["scan1_train_00", "scan4_train", *(f"scan6_train_{t:02d}"
                                                         for t in range(4))]
    assert [e["context"]["index"].tolist() for e in examples[:3]] == [[0, 4], [1, 5], [0, 4]]
    assert _warnings(caplog) == []
    assert index_coverage(index, scored)["coverage"] == "scored 6 of 6 keys: 0 null, 0 failed"
    assert scene_keys(ds, scored) == {"scan1_train_00", "scan4_train", "scan6_train"}
