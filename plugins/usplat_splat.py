"""The ``usplat_splat`` Mitsuba integrator: the scene's Gaussians, held by Mitsuba
``ellipsoids`` shapes, rasterised by usplat-dr's Dr.Jit rasteriser from the scene's
perspective sensor.
"""

import drjit as dr
import mitsuba as mi
import numpy as np

from usplat_dr.plugins.convert import ellipsoids_as_gaussians, sensor_camera
from usplat_dr.render.settings import RasterSettings

DOC = r"""
.. _integrator-usplat_splat:

Gaussian splatting through usplat-dr (:monosp:`usplat_splat`)
-------------------------------------------------------------

.. pluginparameters::

 * - background
   - |rgb|
   - Colour behind the Gaussians, in the primitives' colour space. (Default: 0)
 * - srgb_primitives
   - |bool|
   - The SH coefficients give sRGB colours (as 3DGS and ``volprim_rf_basic`` assume): the
     rendered colour is converted to linear RGB for Mitsuba's film. (Default: true)
 * - sh_basis
   - |string|
   - ``3dgs`` (also ``dr.sh_eval``'s basis, as ``volprim_rf_basic`` reads ``sh_coeffs``) or
     ``mvsplat`` (MVSplat's e3nn-matched basis). (Default: ``3dgs``)
 * - tile_size
   - |int|
   - Rasteriser tile edge in pixels: 0 (automatic: 4 on the LLVM backend, 16 on CUDA), 4, 8
     or 16. Every choice renders the same image. (Default: 0)

Renders every ``ellipsoids`` shape of the scene (with ``opacities`` and ``sh_coeffs``
attributes; other shapes are ignored) with the 3DGS rasteriser's rules: EWA projection,
depth-sorted front-to-back alpha compositing, colour = SH + 0.5 clamped at 0. The sensor must
be ``perspective``; its field of view (any ``fov_axis``), ``to_world``, film size, crop window
and principal point offsets are honoured, and ``near_clip`` plays the rasteriser's near
plane (Gaussians closer than 0.2 near are culled). Deterministic: ``spp`` and ``seed`` change
nothing. The output has the film's crop size and 3 channels (4 with an ``rgba`` film: alpha
= 1 - transmittance).

Differentiable: ``dr.backward`` through ``mi.render`` gives gradients on the ellipsoids'
``data`` (centres, scales, quaternions), ``opacities`` and ``sh_coeffs`` exposed by
``mi.traverse``, so the standard inverse-rendering loop (``mi.ad.Adam``, ``params.update``)
works unchanged.

.. tabs::

    .. code-tab:: python

        import mitsuba as mi
        mi.set_variant("llvm_ad_rgb")
        import usplat_dr.plugins  # registers usplat_splat
        scene = mi.load_dict({"type": "scene",
                              "integrator": {"type": "usplat_splat"},
                              "sensor": {"type": "perspective", ...},
                              "gaussians": usplat_dr.plugins.gaussians_to_ellipsoids(...)})
        image = mi.render(scene)
"""


class UsplatSplatMethods:
    """The integrator's methods, independent of the Mitsuba variant (parameters: ``DOC``).

    Mitsuba binds ``mi.CppADIntegrator`` to the variant that is set, so
    ``integrator_class()`` makes the class ``UsplatSplatIntegrator(mi.CppADIntegrator)``
    once per variant with these methods copied in. (Not a mixin: nanobind's types accept a
    single base, "nb_type_init(): invalid number of bases"; hence also no zero-argument
    ``super()`` here.)"""

    def __init__(self, props):
        mi.CppADIntegrator.__init__(self, props)
        bg = props.get("background", 0.0)
        bg = np.broadcast_to(np.asarray(bg, dtype=np.float64).reshape(-1), (3,))
        if not np.all(np.isfinite(bg)):
            raise ValueError(f"usplat_splat: 'background' must be finite, got {bg}")
        self.background = [float(v) for v in bg]
        self.srgb_primitives = bool(props.get("srgb_primitives", True))
        self.sh_basis = str(props.get("sh_basis", "3dgs"))
        if self.sh_basis not in ("3dgs", "mvsplat"):
            raise ValueError(f"usplat_splat: 'sh_basis' must be '3dgs' or 'mvsplat', got "
                             f"{self.sh_basis!r}")
        tile = int(props.get("tile_size", 0))
        if tile not in (0, 4, 8, 16):
            raise ValueError(f"usplat_splat: 'tile_size' must be 0 (automatic), 4, 8 or "
                             f"16, got {tile}")
        self.settings = RasterSettings(tile_size=tile or None, sh_basis=self.sh_basis)

    # ---- the image ----
    def _image(self, scene, sensor):
        from usplat_dr.render.pipeline import rasterize_drjit  # on first render (start-up)

        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        cam = sensor_camera(sensor)
        h, w = cam["image_shape"]
        shapes = [s for s in scene.shapes() if s.is_ellipsoids()]
        g = ellipsoids_as_gaussians(shapes)
        n, d = g["count"], g["sh_size"]
        T = mi.TensorXf
        args = (T(mi.Float(cam["extrinsics"].astype(np.float32).ravel()), shape=(1, 4, 4)),
                T(mi.Float(cam["intrinsics"].astype(np.float32).ravel()), shape=(1, 3, 3)),
                T(mi.Float([cam["near"]]), shape=(1,)), T(mi.Float([cam["far"]]), shape=(1,)),
                (h, w), T(mi.Float(self.background), shape=(1, 3)))
        if n == 0:
            gauss = (T(dr.zeros(mi.Float, 0), shape=(1, 0, 3)),
                     T(dr.zeros(mi.Float, 0), shape=(1, 0, 3, 3)),
                     T(dr.zeros(mi.Float, 0), shape=(1, 0, 3, 1)),
                     T(dr.zeros(mi.Float, 0), shape=(1, 0)))
        else:
            gauss = (T(g["means"], shape=(1, n, 3)), T(g["covariances"], shape=(1, n, 3, 3)),
                     T(g["sh"], shape=(1, n, 3, d)), T(g["opacities"], shape=(1, n)))
        out = rasterize_drjit(*args, *gauss, settings=self.settings, check=False)
        channels = sensor.film().base_channels_count()
        color = out.color.array  # [3, H, W] (batch 1), channel-major
        if self.srgb_primitives:
            color = mi.math.srgb_to_linear(color)
        planes = dr.concat([color, out.alpha.array]) if channels == 4 else color
        c = 4 if channels == 4 else 3
        lane = dr.arange(mi.UInt32, h * w * c)
        src = (lane % c) * (h * w) + lane // c  # [H, W, C] from [C, H, W]
        return mi.TensorXf(dr.gather(mi.Float, planes, src), shape=(h, w, c))

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if not develop:
            raise ValueError("usplat_splat renders developed images only (develop=True)")
        with dr.suspend_grad():
            return self._image(scene, sensor)

    def render_forward(self, scene, params, sensor=0, seed=0, spp=0):
        with dr.resume_grad():
            image = self._image(scene, sensor)
            dr.forward_to(image)
            return dr.grad(image)

    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        with dr.resume_grad():
            image = self._image(scene, sensor)
            dr.backward_from(image * grad_in)

    # ---- Mitsuba plugin conventions ----
    def aov_names(self):
        return []

    def traverse(self, callback):
        callback.put("background", self.background, mi.ParamFlags.NonDifferentiable)

    def parameters_changed(self, keys):
        self.background = [float(v) for v in np.broadcast_to(
            np.asarray(self.background, dtype=np.float64).reshape(-1), (3,))]

    def to_string(self):
        return (f"UsplatSplatIntegrator[\n  background = {self.background},\n"
                f"  srgb_primitives = {self.srgb_primitives},\n"
                f"  sh_basis = {self.sh_basis!r},\n"
                f"  tile_size = {self.settings.tile_size or 'automatic'}\n]")


_CLASSES: dict[str, type] = {}


def integrator_class():
    """The integrator class for the current Mitsuba variant (made once per variant)."""
    variant = mi.variant()
    if variant is None:
        raise RuntimeError("set a Mitsuba variant before using usplat_splat, e.g. "
                           "mi.set_variant('llvm_ad_rgb') (or 'cuda_ad_rgb' on a GPU)")
    if "_ad_" not in variant:
        raise RuntimeError(f"usplat_splat needs a JIT variant ('llvm_ad_rgb' or "
                           f"'cuda_ad_rgb'), the current one is {variant!r}")
    if variant not in _CLASSES:
        methods = {k: v for k, v in vars(UsplatSplatMethods).items()
                   if k not in ("__dict__", "__weakref__")}
        _CLASSES[variant] = type("UsplatSplatIntegrator", (mi.CppADIntegrator,),
                                 {**methods, "__doc__": DOC})
    return _CLASSES[variant]


def register() -> None:
    """Register ``usplat_splat`` for the current variant (``import usplat_dr.plugins`` does)."""
    cls = integrator_class()
    mi.register_integrator("usplat_splat", lambda props: cls(props))
