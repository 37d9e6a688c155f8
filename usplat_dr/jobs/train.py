"""``usplat train``: train UniqueSplat (any variant) with the field's recipe, on one process or
under ``torchrun`` (DistributedDataParallel). Prints the result as one JSON line per rank
(``step``, ``loss``, ``rank``, ``params_sha256``...). Under torchrun a failing rank ends the run
with one line naming it and the cause; the other ranks exit quietly (status 1). A run stopped
for non-finite steps ends with one line naming its last good checkpoint (status 1); a mistake
in the configuration, the checkpoint to resume, the run folder (held by another run, or a
file) or a full disk with one line naming it and the fix (status 2, by ``usplat_dr.cli``)."""

import argparse
import json
import sys

from usplat_dr.config import load_config
from usplat_dr.training import RankFailed, TrainingStopped, train
from usplat_dr.training.config import RootCfg


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", action="append",
                   help="a YAML file's path, or a packaged config's name (usplat_dr/configs/: "
                   "synthetic_tiny.yaml, synthetic_tiny_depth.yaml, ...); repeat to merge "
                   "several in order (default: synthetic_tiny.yaml)")
    p.add_argument("--resume", action="store_true",
                   help="continue from output_dir/checkpoints/last.ckpt when it exists")
    p.add_argument("overrides", nargs="*", metavar="key.sub=value",
                   help="dotted overrides, e.g. optimizer.lr=1e-4 train.steps=100")


def run(args: argparse.Namespace) -> int:
    # a bad file, key or value: a ConfigError naming it, before anything is built (the CLI
    # prints it as one line, exit status 2)
    cfg = RootCfg.load(load_config(args.config or ["synthetic_tiny.yaml"], args.overrides))
    try:
        result = train(cfg, resume=args.resume)
    except RankFailed as e:  # under torchrun: one message, from the rank that failed
        raise SystemExit(f"usplat train: {e}" if e.own else 1) from None
    except TrainingStopped as e:  # diverged: the message names the last good checkpoint
        raise SystemExit(f"usplat train: {e}") from None
    # one write per line: under torchrun the ranks share the launcher's stdout
    sys.stdout.write(json.dumps(result) + "\n")
    sys.stdout.flush()
    return 0
