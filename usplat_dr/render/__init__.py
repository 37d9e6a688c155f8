"""The Dr.Jit Gaussian rasteriser.

``rasterize`` (torch tensors in, ``RenderOutput`` out) lives in ``bridge.py``, the one module
that imports both torch and drjit; it is loaded on first use so that the Dr.Jit core
(``rasterize_drjit`` and its stages) can be used without torch.
"""

from usplat_dr.render.settings import RasterSettings

__all__ = ["RasterSettings", "RenderOutput", "RenderOutputDr", "rasterize", "rasterize_drjit"]


def __getattr__(name):
    if name in ("rasterize", "RenderOutput"):
        from usplat_dr.render import bridge  # torch + drjit on first use (see above)

        return getattr(bridge, name)
    if name in ("rasterize_drjit", "RenderOutputDr"):
        from usplat_dr.render import pipeline as core  # drjit on first use (see above)

        return getattr(core, name)
    raise AttributeError(f"module 'usplat_dr.render' has no attribute {name!r}")
