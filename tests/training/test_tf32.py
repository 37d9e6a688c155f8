"""The ``tf32`` training option: torch's float32 precision switches for cuDNN convolutions and
CUDA matrix products, set through torch's per-backend ``fp32_precision`` (the legacy
``allow_tf32`` flags mixed with it are an error in torch), and the config's checked values."""

import pytest
import torch

from usplat_dr.config import ConfigError
from usplat_dr.training.config import RootCfg
from usplat_dr.training.distributed import set_tf32


@pytest.fixture
def restore_precision():
    conv, matmul = torch.backends.cudnn.conv, torch.backends.cuda.matmul
    before = conv.fp32_precision, matmul.fp32_precision
    yield conv, matmul
    conv.fp32_precision, matmul.fp32_precision = before


@pytest.mark.parametrize("tf32, expected", [(False, "ieee"), (True, "tf32")])
def test_sets_both_backends(restore_precision, tf32, expected):
    conv, matmul = restore_precision
    set_tf32(tf32)
    assert (conv.fp32_precision, matmul.fp32_precision) == (expected, expected)


def test_none_leaves_torch_as_it_was(restore_precision):
    conv, matmul = restore_precision
    conv.fp32_precision, matmul.fp32_precision = "ieee", "tf32"  # a user's own choice
    set_tf32(None)
    assert (conv.fp32_precision, matmul.fp32_precision) == ("ieee", "tf32")


def test_config_takes_null_true_false_and_rejects_text():
    assert RootCfg.load({}).tf32 is None
    assert RootCfg.load({"tf32": False}).tf32 is False
    with pytest.raises(ConfigError, match="tf32"):
        RootCfg.load({"tf32": "off"})
