"""Files in and out: atomic writes (``atomic``), PNGs and contact sheets (``images``), videos
(``video``). The atomic writers are re-exported: ``from usplat_dr.io import write_json``."""

from usplat_dr.io.atomic import atomic_open, torch_save, write_json

__all__ = ["atomic_open", "torch_save", "write_json"]
