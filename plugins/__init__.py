"""Mitsuba plugins of usplat-dr (installed as ``usplat_dr.plugins``).

``import usplat_dr.plugins`` registers the ``usplat_splat`` integrator for the current Mitsuba
variant and again whenever the variant changes (``mi.set_variant``); it needs a JIT variant
with AD (``llvm_ad_rgb``, ``cuda_ad_rgb``). Helpers convert between Mitsuba and usplat-dr:
``sensor_camera`` (a perspective sensor as our camera), ``gaussians_to_ellipsoids`` /
``model_gaussians_to_ellipsoids`` (a Mitsuba ``ellipsoids`` shape dict from Gaussians or from
a model's prediction for one target) and ``ellipsoids_to_gaussians`` (back to torch).
The rasteriser itself (``usplat_dr.render``) never imports Mitsuba.
"""

import mitsuba as mi  # noqa: I001
from usplat_dr.plugins.convert import (
    ellipsoids_to_gaussians,
    gaussians_to_ellipsoids,
    model_gaussians_to_ellipsoids,
    sensor_camera,
)
from usplat_dr.plugins.usplat_splat import integrator_class, register

import usplat_dr  # noqa: F401  (points Dr.Jit at a suitable libLLVM before it loads)

__all__ = ["ellipsoids_to_gaussians", "gaussians_to_ellipsoids", "integrator_class",
           "model_gaussians_to_ellipsoids", "register", "sensor_camera"]


def _on_variant(old, new):
    if new is not None and "_ad_" in new:
        register()


if mi.variant() is not None and "_ad_" in mi.variant():
    register()
mi.detail.add_variant_callback(_on_variant)
