"""train/studies/branch_meter.py: its examples (the within/between spread by hand) and a
training stage's scenes scored as test scenes without links that leave their root."""

import doctest
import importlib.util
from pathlib import Path

SCRIPT = Path(__file__).parents[2] / "train" / "studies" / "branch_meter.py"
spec = importlib.util.spec_from_file_location("branch_meter", SCRIPT)
meter = importlib.util.module_from_spec(spec)
spec.loader.exec_module(meter)


def test_examples_run():
    result = doctest.testmod(meter)
    assert result.attempted > 0 and result.failed == 0


def test_a_train_stage_becomes_a_test_root(tmp_path):
    train = tmp_path / "set" / "train"
    train.mkdir(parents=True)
    (train / "000000.torch").write_bytes(b"chunk")
    (train / "evaluation_index_standard.json").write_text("{}")
    (train / "previews").mkdir()
    root = meter.as_test_root(train, tmp_path / "roots")
    assert sorted(p.name for p in (root / "test").iterdir()) == [
        "000000.torch", "evaluation_index_standard.json"]
    assert not (root / "test" / "000000.torch").is_symlink()
    assert (root / "test" / "000000.torch").read_bytes() == b"chunk"
    assert meter.as_test_root(tmp_path / "roots" / "set", tmp_path / "x") == root  # has test/
