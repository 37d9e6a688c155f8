"""Kernel-shaping settings of the rasteriser (Python values baked into the compiled kernels)."""

from dataclasses import dataclass
from typing import Literal

#: Tile edge of the reference rasteriser (3DGS / pixelSplat / MVSplat ``BLOCK_X``/``BLOCK_Y``).
REFERENCE_TILE = 16


@dataclass(frozen=True)
class RasterSettings:
    """How the rasteriser cuts and composites; every choice keeps the reference's output.

    Parameter ``tile_size`` (``int`` or ``None``): edge of the tiles whose pixels share one
    depth-sorted list: 4, 8 or 16. ``None`` picks 4 on the LLVM backend (a 4x4 tile is one
    16-lane SIMD packet: 4.4x fewer evaluated pairs than 16x16, docs/rasteriser_notes.md
    "Tiles, records and the benchmark scene") and 16 on CUDA.
    Membership always follows the reference's 16x16 rule, so every tile size renders the same
    image; smaller tiles only skip work the reference's own ``alpha < 1/255`` rule would skip.

    Parameter ``opacity_cull`` (``bool``): drop a Gaussian from a tile when the ellipse on which
    ``opacity * G >= 1/255`` misses the tile (pixels there would skip it anyway). Exact.

    Parameter ``sh_basis`` (``"3dgs"`` or ``"mvsplat"``): ``"3dgs"`` is the standard basis of the
    3DGS CUDA rasteriser; ``"mvsplat"`` the e3nn-matched basis of
    diff-gaussian-rasterization-modified that MVSplat renders with (standard basis at the permuted
    direction (z, x, y), with its coefficient-14 anomaly). Both evaluate degrees 0..3 only.

    Parameter ``clamp_gradient`` (``"exact"`` or ``"reference"``): ``"exact"`` differentiates the
    forward function (zero gradient through an active ``alpha = 0.99`` clamp); ``"reference"``
    passes the gradient through the clamp as the 3DGS backward does.

    Parameter ``projection`` (``"intrinsics"`` or ``"render_cuda"``): ``"intrinsics"`` projects
    with the given intrinsics, principal point included (geometrically right).
    ``"render_cuda"`` projects as pixelSplat/MVSplat's ``render_cuda`` does: it turns the
    intrinsics into fields of view (``get_fov``: the angles between the rays through the
    midpoints of opposite image edges), builds a symmetric projection from ``tan(fov / 2)``
    and so puts the principal point at the image centre, whatever cx and cy are. The two
    agree when cx = cy = 0.5 and there is no skew; use ``"render_cuda"`` to reproduce
    official renders and numbers on data with an off-centre principal point.

    Parameter ``backward_scatter`` (``"packet"``, ``"lanes"`` or ``None``): how the backward adds
    each pair's ten gradients to its Gaussian. ``"packet"``: one scatter-add of a 16-float
    gradient record per pair into a per-thread copy (``ReduceMode.Expand``: a vector
    read-modify-write, no atomics; its target size is baked into the kernel, so the Gaussian
    count is padded to a bucket, ``composite.padded_count``). ``"lanes"``: ten scalar
    scatter-adds (``ReduceMode.Local``: Dr.Jit's helper walks a packet's lanes one by one on
    LLVM; atomics on CUDA). ``None`` picks ``"packet"`` on LLVM and ``"lanes"`` on CUDA. Both
    give the same gradients up to the order of float additions.

    Parameter ``freeze_forward`` (``bool``, default ``False``): the torch entry renders calls
    without gradients with the forward recorded once per input shape and replayed
    (``dr.freeze``, a fixed pair capacity; ``render.frozen.FrozenForward``); the images are the
    traced ones, bit for bit. Opt-in: 0.89x the traced forward at 64x64 and no gain at 256x256
    on the CPU, and where the shapes change from call to call (evaluation splits with other
    target counts, Gaussian budgets) it records again instead of replaying.
    """

    tile_size: int | None = None
    opacity_cull: bool = True
    sh_basis: Literal["3dgs", "mvsplat"] = "3dgs"
    clamp_gradient: Literal["exact", "reference"] = "exact"
    projection: Literal["intrinsics", "render_cuda"] = "intrinsics"
    backward_scatter: Literal["packet", "lanes"] | None = None
    freeze_forward: bool = False

    def __post_init__(self):
        if self.tile_size not in (None, 4, 8, 16):
            raise ValueError(f"tile_size must be 4, 8, 16 or None, got {self.tile_size!r}")
        if self.sh_basis not in ("3dgs", "mvsplat"):
            raise ValueError(f"sh_basis must be '3dgs' or 'mvsplat', got {self.sh_basis!r}")
        if self.clamp_gradient not in ("exact", "reference"):
            raise ValueError(
                f"clamp_gradient must be 'exact' or 'reference', got {self.clamp_gradient!r}"
            )
        if self.projection not in ("intrinsics", "render_cuda"):
            raise ValueError(f"projection must be 'intrinsics' or 'render_cuda', got "
                             f"{self.projection!r}")
        if self.backward_scatter not in (None, "packet", "lanes"):
            raise ValueError(f"backward_scatter must be 'packet', 'lanes' or None, got "
                             f"{self.backward_scatter!r}")
        if not isinstance(self.freeze_forward, bool):
            raise ValueError(f"freeze_forward must be True or False, got "
                             f"{self.freeze_forward!r}")

    @staticmethod
    def reference() -> "RasterSettings":
        """The reference's own work decomposition: 16x16 tiles, no opacity culling (slower)."""
        return RasterSettings(tile_size=REFERENCE_TILE, opacity_cull=False)

    def resolved_backward_scatter(self, is_cuda: bool) -> str:
        """The backward's scatter on this backend: ``"packet"`` is LLVM's (its per-thread
        copies are what ``ReduceMode.Expand`` means there; untested on CUDA, so refused)."""
        if self.backward_scatter == "packet" and is_cuda:
            raise ValueError("backward_scatter='packet' is for the LLVM backend (CPU); on CUDA "
                             "use 'lanes' or None")
        if self.backward_scatter is not None:
            return self.backward_scatter
        return "lanes" if is_cuda else "packet"

    def resolved_tile_size(self, is_cuda: bool) -> int:
        if self.tile_size is not None:
            return self.tile_size
        return REFERENCE_TILE if is_cuda else 4
