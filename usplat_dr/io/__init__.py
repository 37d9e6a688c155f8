"""Files in and out: atomic writes (``atomic``), safe reading of torch files
(``checkpoint_files``), PNGs and contact sheets (``images``), videos (``video``). The atomic
writers and the safe reader are re-exported: ``from usplat_dr.io import write_json``."""

from usplat_dr.io.atomic import atomic_open, save_figure, torch_save, write_json
from usplat_dr.io.checkpoint_files import UntrustedCheckpointError, load_torch_file

__all__ = ["UntrustedCheckpointError", "atomic_open", "load_torch_file", "save_figure",
           "torch_save", "write_json"]
