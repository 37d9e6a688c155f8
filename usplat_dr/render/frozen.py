"""The forward render recorded once and replayed (``dr.freeze``), for calls without gradients.

``rasterize_drjit`` traces its Python code into kernels at every call; at 64x64 that tracing and
the host work between launches are about half the forward's time (docs/rasteriser_notes.md).
``FrozenForward`` records the forward with a fixed pair capacity (``bin_gaussians(capacity=)``:
nothing read back to the host inside, which recording requires) and replays the recorded
kernels on later calls of the same shapes. The first call of a shape is traced as usual and
measures the pair lanes the scene needs; the capacity is a sixteenth more, rounded up a little.
After each replay two numbers come back to the host (pairs needed and kept); where a scene
needed more lanes than the capacity, the capacity grows to fit and the call is made again, so
the images are always the traced ones, bit for bit.

Opt-in (``RasterSettings(freeze_forward=True)``): 0.89x the traced forward at 64x64 on a CPU,
none at 256x256, and where shapes change from call to call it records instead of replaying;
after ``MAX_TOTAL_RECORDINGS`` it traces every call.

Gradients: a frozen function does not carry them through the rasteriser's ``dr.CustomOp``
(measured with Dr.Jit 1.5.0: every gradient came back zero, silently), so ``FrozenForward``
refuses inputs that need gradients; the differentiable path stays the traced one.
"""

import logging

import drjit as dr

from usplat_dr.render.pipeline import rasterize_drjit
from usplat_dr.render.settings import RasterSettings

log = logging.getLogger(__name__)

#: Recorded configurations kept (least recently used dropped).
MAX_RECORDINGS = 8
#: Recordings after which a ``FrozenForward`` traces every call instead: a run whose shapes or
#: capacities keep changing records more than it replays. (The demo's evaluation and budget
#: benchmark, 2026-11-29: 24 recordings, 7 cached, Dr.Jit reporting that dry runs of a recording
#: had failed at least 17 times.)
MAX_TOTAL_RECORDINGS = 32


class FrozenForward:
    """``rasterize_drjit`` without gradients, recorded per input shape and replayed.

    Parameter ``image_shape`` (``tuple[int, int]``) and ``settings`` (``RasterSettings``): fixed
    for the object, as the torch entry's wrapped function fixes them. Call it with the nine
    tensor arguments of ``rasterize_drjit`` (all but ``image_shape``; ``TensorXf``, no
    gradients); it returns
    ``(color, alpha, depth, radii, num_pairs)`` as the torch entry's wrapped function does.
    ``recordings`` counts the recordings made (one per new shape or capacity).
    """

    def __init__(self, image_shape: tuple[int, int], settings: RasterSettings | None = None):
        self.image_shape = tuple(image_shape)
        self.settings = settings or RasterSettings()
        self.capacity: dict[tuple, int] = {}  # pair lanes per shape key
        self.gave_up = False  # too many recordings: every call traced (MAX_TOTAL_RECORDINGS)
        # Widths are baked into recorded kernels (dr.width becomes a literal), so every size the
        # body depends on is part of the configuration's key: another shape records anew.
        self._frozen = dr.freeze(self._body, state_fn=lambda capacity, *t: (
            capacity, tuple(tuple(x.shape) for x in t)), limit=MAX_RECORDINGS,
            warn_after=MAX_TOTAL_RECORDINGS + 1)  # this class says it once, below

    @property
    def recordings(self) -> int:
        return self._frozen.n_recordings

    def _body(self, capacity, extrinsics, intrinsics, near, far, background_color, means,
              covariances, sh_coefficients, opacities):
        out = rasterize_drjit(extrinsics, intrinsics, near, far, self.image_shape,
                              background_color, means, covariances, sh_coefficients, opacities,
                              self.settings, check=False, pair_capacity=capacity)
        return (out.color, out.alpha, out.depth, out.aux["radii"], out.aux["pairs_kept"],
                out.aux["pairs_needed"])

    def __call__(self, *tensors):
        if len(tensors) != 9:
            raise TypeError(f"FrozenForward takes the 9 tensor arguments of rasterize_drjit "
                            f"(image_shape and settings are the object's), got {len(tensors)}")
        if any(dr.grad_enabled(t) for t in tensors):
            raise ValueError("FrozenForward renders without gradients (a frozen function drops "
                             "them); use rasterize_drjit for inputs with gradients enabled")
        key = tuple(tuple(t.shape) for t in tensors)
        b, g = tensors[5].shape[:2]
        if b * g == 0:
            raise ValueError("FrozenForward needs at least one Gaussian (means has shape "
                             f"{tuple(tensors[5].shape)}); render empty scenes unfrozen")
        capacity = self.capacity.get(key)
        if self.recordings >= MAX_TOTAL_RECORDINGS:
            if not self.gave_up:
                log.warning("FrozenForward: %d recordings for %s images, more than it replays; "
                            "tracing every call from now on", self.recordings, self.image_shape)
                self.gave_up = True
            capacity = None
        if capacity is None:  # a new shape: traced once, which measures the pairs it needs
            out = rasterize_drjit(*tensors[:4], self.image_shape, *tensors[4:], self.settings,
                                  check=False)
            self.capacity[key] = _room_for(out.aux["pairs_needed"])
            return out.color, out.alpha, out.depth, out.aux["radii"], out.aux["num_pairs"]
        while True:
            color, alpha, depth, radii, kept, needed = self._frozen(capacity, *tensors)
            need = int(needed[0])  # host reads after the replay: did every pair find a lane?
            if need <= capacity:
                return color, alpha, depth, radii, int(kept[0])
            capacity = self.capacity[key] = _room_for(need)


def _room_for(pairs: int) -> int:
    """The capacity for a scene needing ``pairs`` lanes: a sixteenth more (plus 1,024), rounded
    up to 64 steps per power of two (at most 1.6 % more), so that scenes needing a few percent
    more than the first still replay its recording. Lanes beyond the need cost pair generation
    and sorting: with a quarter more, rounded to 4 steps per power of two (up to 56 % more),
    the replayed forward at 256x256 was 1.05x the traced one (train/bench/README.md)."""
    want = pairs + pairs // 16 + 1024
    step = 1 << max(want.bit_length() - 6, 0)
    return -(-want // step) * step
