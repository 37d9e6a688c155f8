"""The own-data path as the README walks it, on a generated COLMAP project (the synthetic
truth of tests/data/test_importers.py): import a training stage and a held-out stage into one
root, train on it, evaluate on it; each stage keeps its own evaluation index, and an
evaluation that scores nothing fails."""

import json

from usplat_dr.cli import main


def test_import_train_and_test_stages_then_train_and_evaluate(user_scene, tmp_path, capsys):
    sparse, data = str(user_scene.root / "sparse" / "0"), tmp_path / "mydata"
    assert main(["-q", "import", "--colmap", sparse, "--out", str(data), "--stage", "train",
                 "--image-shape", "64", "64"]) == 0
    assert main(["-q", "import", "--colmap", sparse, "--out", str(data), "--stage", "test",
                 "--image-shape", "64", "64", "--key", "heldout"]) == 0
    # each stage's index beside its own metadata: the train import did not overwrite the
    # test stage's (evaluation reads the root's)
    test_index = json.loads((data / "evaluation_index_standard.json").read_text())
    train_index = json.loads((data / "train" / "evaluation_index_standard.json").read_text())
    assert list(test_index) == ["heldout"]
    assert len(train_index) == 1 and "heldout" not in train_index
    run = tmp_path / "run"
    assert main(["-q", "train", "--config", "synthetic_tiny.yaml", f"dataset.roots=[{data}]",
                 f"output_dir={run}", "train.steps=2", "train.checkpoint_every=1",
                 "train.validate_every=2", "threads=1"]) == 0
    capsys.readouterr()
    assert main(["-q", "eval", "--checkpoint", str(run / "checkpoints" / "last.ckpt"),
                 "--data", str(data), "--out", str(tmp_path / "eval")]) == 0
    summary = json.loads((tmp_path / "eval" / "summary.json").read_text())
    assert summary["splits"]["standard"]["scenes"] == 1
    # --near/--far override the scene's recorded range (the imported sparse points' 2.55/5.81):
    # a range ten times farther puts every depth candidate behind the scene, another render
    ckpt = str(run / "checkpoints" / "last.ckpt")
    assert main(["-q", "eval", "--checkpoint", ckpt, "--data", str(data), "--near", "25",
                 "--far", "60", "--out", str(tmp_path / "eval_far")]) == 0
    far = json.loads((tmp_path / "eval_far" / "summary.json").read_text())
    assert far["splits"]["standard"]["psnr"] != summary["splits"]["standard"]["psnr"]
    assert main(["-q", "export-ply", "--checkpoint", ckpt, "--data", str(data), "--near", "25",
                 "--far", "60", "--out", str(tmp_path / "far.ply")]) == 0
    capsys.readouterr()
    for command in ("eval", "export-ply"):
        assert main(["-q", command, "--checkpoint", ckpt, "--data", str(data), "--near",
                     "1"]) == 2
        assert "give both --near and --far" in capsys.readouterr().err

    # an index naming scenes the data do not hold: exit 2, one line, not a silent 0 of 1
    (data / "evaluation_index_standard.json").write_text(json.dumps(
        {"elsewhere": {"context": [0, 5], "target": [2, 3]}}))
    capsys.readouterr()
    assert main(["-q", "eval", "--checkpoint", str(run / "checkpoints" / "last.ckpt"),
                 "--data", str(data), "--out", str(tmp_path / "eval2")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("usplat eval: error: --data") and "no scene was scored" in err[-1]
