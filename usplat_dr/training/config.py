"""The training configuration's sections turned into objects: the model a ``model`` section
describes (the datasets' ``dataset_from_section`` lives in ``usplat_dr.data.dataset``)."""

import dataclasses

from usplat_dr.config import ConfigError, check_keys
from usplat_dr.model import UniqueSplat
from usplat_dr.model.uniquesplat import PRESETS, UniqueSplatCfg
from usplat_dr.training.checkpoints import init_from_checkpoint

SECTIONS = {"seed", "output_dir", "device", "threads", "model", "dataset", "data_loader",
            "optimizer", "loss", "train", "name"}


def model_from_config(mcfg: dict) -> UniqueSplat:
    """The model a config's ``model`` section describes: a preset, a variant, overrides of the
    preset's fields, and weights to start from (``init_mvsplat``: an MVSplat checkpoint;
    ``init_from``: a usplat checkpoint of (a), the paper's protocol)."""
    check_keys(mcfg, {"preset", "variant", "overrides", "init_mvsplat", "init_from"}, "model")
    preset = mcfg.get("preset", "tiny")
    if preset not in PRESETS:
        raise ConfigError(f"model.preset must be one of {sorted(PRESETS)}, got {preset!r}")
    base = dataclasses.asdict(PRESETS[preset])
    over = dict(mcfg.get("overrides") or {})
    if "primary" in over:
        base["primary"] = {**base["primary"], **over.pop("primary")}
    cfg = UniqueSplatCfg.from_dict({**base, **over, "variant": mcfg.get("variant", "full")})
    model = UniqueSplat(cfg)
    if mcfg.get("init_mvsplat") and mcfg.get("init_from"):
        raise ConfigError("model.init_mvsplat and model.init_from both set: choose one")
    if mcfg.get("init_mvsplat"):
        model.load_mvsplat(mcfg["init_mvsplat"])
    if mcfg.get("init_from"):
        init_from_checkpoint(model, mcfg["init_from"])
    return model
