"""What the viewer shows (``usplat view``): viser's cameras as OpenCV cameras and back, one
rendered ``View``, and the scenes that render one: ``ModelScene`` (a model and its context
views: every camera a target with its own Gaussians) and ``PlyScene`` (a 3DGS PLY, no model).

Viser's camera (``viser.CameraHandle``): ``wxyz`` is the rotation camera -> world with OpenCV
camera axes (+X right, +Y down, +Z forward: the data's convention), ``position`` the centre in
world coordinates, ``fov`` the vertical field of view in radians, ``aspect`` the canvas'
width / height. The background image is stretched over the whole canvas, so it is rendered with
the canvas' fields of view, whatever its pixel size.
"""

import logging
import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from usplat_dr.geometry.quaternions import matrix_to_quat_wxyz, quat_xyzw_to_matrix
from usplat_dr.io.images import colorize_depth, to_uint8
from usplat_dr.render import RasterSettings, rasterize

log = logging.getLogger(__name__)

#: What the page can show: the rendered colour, depth (inverse-depth colours, black where
#: nothing is drawn) or accumulated opacity.
CHANNELS = ("colour", "depth", "opacity")
#: Where opacity is below this, the depth view is black (depth there is ~0 and means nothing).
DEPTH_ALPHA = 0.05
#: A PLY has no image shape of its own.
PLY_IMAGE_SHAPE = (256, 256)
VIEWER_HINT = ("usplat view needs the viser package (the 'view' extra): pip install -c "
               "constraints.txt -e '.[view]', or bash scripts/run.sh setup")


# ---- Cameras -----------------------------------------------------------------------------

def c2w_from_viser(wxyz, position) -> np.ndarray:
    """The OpenCV camera-to-world matrix [4, 4] (float64) of a viser camera: ``wxyz`` (4,) is
    its rotation camera -> world, real part first, OpenCV camera axes; ``position`` (3,) its
    centre. The quaternion need not be unit (the formula divides its norm out).

    Examples:
        >>> c2w_from_viser([0.0, 1.0, 0.0, 0.0], [1.0, 2.0, 3.0]).round(6).tolist()
        [[1.0, 0.0, 0.0, 1.0], [0.0, -1.0, 0.0, 2.0], [0.0, 0.0, -1.0, 3.0], [0.0, 0.0, 0.0, 1.0]]
    """
    q = np.asarray(wxyz, dtype=np.float64).reshape(4)
    if not np.isfinite(q).all() or not q.any():
        raise ValueError(f"wxyz must be a non-zero finite quaternion, got {q.tolist()}")
    # 1e-30: the helper's eps is there for Gaussians' unnormalised quaternions; here it would
    # be an error of 1e-8 in a unit quaternion's rotation, which the round trip would see.
    rot = quat_xyzw_to_matrix(torch.from_numpy(q[[1, 2, 3, 0]]), eps=1e-30).numpy()
    c2w = np.eye(4)
    c2w[:3, :3] = rot
    c2w[:3, 3] = np.asarray(position, dtype=np.float64).reshape(3)
    return c2w


def viser_from_c2w(c2w) -> tuple[np.ndarray, np.ndarray]:
    """``(wxyz, position)`` of viser's camera for an OpenCV camera-to-world matrix [4, 4]
    (``c2w_from_viser``'s inverse; ``wxyz`` with w >= 0).

    Examples:
        >>> wxyz, position = viser_from_c2w(np.eye(4))
        >>> wxyz.tolist(), position.tolist()
        ([1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    """
    m = np.asarray(c2w, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"c2w must have shape (4, 4), got {m.shape}")
    q = matrix_to_quat_wxyz(m[None, :3, :3])[0]
    return q * (1.0 if q[0] >= 0 else -1.0), m[:3, 3].copy()


def intrinsics_from_fov(fov_y: float, aspect: float) -> np.ndarray:
    """Normalised intrinsics [3, 3] of an image that spans a vertical field of view ``fov_y``
    (radians) and ``aspect`` times as much horizontally (the tangents' ratio, as a canvas of
    width / height = ``aspect`` with square pixels): fy = 0.5 / tan(fov_y / 2) (half the
    image height over the tangent), fx = fy / aspect, the principal point at the centre.

    Examples:
        >>> intrinsics_from_fov(math.pi / 2, 2.0).round(6).tolist()
        [[0.25, 0.0, 0.5], [0.0, 0.5, 0.5], [0.0, 0.0, 1.0]]
    """
    if not (0 < fov_y < math.pi) or not (aspect > 0 and math.isfinite(aspect)):
        raise ValueError(f"fov_y must be in (0, pi) radians and aspect > 0, got fov_y {fov_y}, "
                         f"aspect {aspect}")
    fy = 0.5 / math.tan(fov_y / 2)
    return np.array([[fy / aspect, 0.0, 0.5], [0.0, fy, 0.5], [0.0, 0.0, 1.0]])


def fov_from_intrinsics(intrinsics) -> tuple[float, float]:
    """``(fov_y, aspect)`` of normalised intrinsics [3, 3] (``intrinsics_from_fov``'s inverse,
    for a principal point at the centre): what viser's camera and frustums take."""
    k = np.asarray(intrinsics, dtype=np.float64)
    return 2 * math.atan(0.5 / k[1, 1]), float(k[1, 1] / k[0, 0])


def camera_from_viser(wxyz, position, fov_y: float, aspect: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """``(c2w [4, 4], intrinsics [3, 3])`` of a viser camera: a target view for the model."""
    return c2w_from_viser(wxyz, position), intrinsics_from_fov(fov_y, aspect)


# ---- One view ----------------------------------------------------------------------------

@dataclass
class View:
    """One rendered view: ``color`` [H, W, 3] in [0, 1], ``alpha`` [H, W], ``depth`` [H, W]
    (expected depth, ~0 where nothing is drawn), ``gaussians`` drawn, ``seconds`` taken."""

    color: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray
    gaussians: int
    seconds: float


def to_image(view: View, channel: str, depth_range: tuple[float, float]) -> np.ndarray:
    """The ``channel`` (``CHANNELS``) of ``view`` as a uint8 [H, W, 3] image; depth coloured
    between ``depth_range`` (near, far), fixed per scene so that it does not flicker."""
    if channel == "colour":
        rgb = view.color
    elif channel == "depth":
        rgb = colorize_depth(view.depth, near=depth_range[0], far=depth_range[1])
        rgb = np.where((view.alpha >= DEPTH_ALPHA)[..., None], rgb, 0.0)
    elif channel == "opacity":
        rgb = np.repeat(view.alpha[..., None], 3, axis=2)
    else:
        raise ValueError(f"channel must be one of {CHANNELS}, got {channel!r}")
    return to_uint8(rgb)


def depth_range(view: View) -> tuple[float, float]:
    """(2nd, 98th) percentile of a view's depth where it is drawn (as ``usplat render``)."""
    valid = view.depth[(view.alpha >= DEPTH_ALPHA) & np.isfinite(view.depth)
                       & (view.depth > 0)]
    if not valid.size:
        return 1.0, 2.0
    lo, hi = float(np.percentile(valid, 2)), float(np.percentile(valid, 98))
    return lo, max(hi, lo * 1.01)


class ModelScene:
    """Context views and one or more models; ``render`` predicts one target view's Gaussians
    and renders them. ``models``: {label: UniqueSplat}; ``images`` [V, 3, H, W] (uint8 or
    float in [0, 1]); ``extrinsics`` [V, 4, 4] OpenCV camera-to-world; ``intrinsics``
    [V, 3, 3] normalised; ``near``/``far`` in scene units."""

    def __init__(self, models: dict, images: torch.Tensor, extrinsics: torch.Tensor,
                 intrinsics: torch.Tensor, near: float, far: float):
        if not models:
            raise ValueError("models must hold at least one model")
        self.models = models
        self.images, self.intrinsics, self.extrinsics = images, intrinsics, extrinsics
        self.near, self.far = float(near), float(far)
        self.labels = list(models)
        self.image_shape = tuple(images.shape[-2:])

    def render(self, label: str, c2w: np.ndarray, intrinsics: np.ndarray) -> View:
        """The view of camera ``c2w`` [4, 4] with ``intrinsics`` [3, 3] (normalised) by the
        model ``label``: its own Gaussians, predicted for this target."""
        start = time.perf_counter()
        pred = self.models[label].predict(
            self.images, intrinsics=self.intrinsics, extrinsics=self.extrinsics,
            target_intrinsics=torch.as_tensor(intrinsics, dtype=torch.float32)[None],
            target_extrinsics=torch.as_tensor(c2w, dtype=torch.float32)[None],
            near=self.near, far=self.far)
        seconds = time.perf_counter() - start
        return View(pred.color[0].permute(1, 2, 0).cpu().numpy(), pred.alpha[0].cpu().numpy(),
                    pred.depth[0].cpu().numpy(), len(pred.gaussians[0]), seconds)

    def frustums(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """(c2w [4, 4], intrinsics [3, 3]) of each context view."""
        return [(e.double().numpy(), k.double().numpy())
                for e, k in zip(self.extrinsics.cpu(), self.intrinsics.cpu())]

    def start(self) -> tuple[np.ndarray, np.ndarray]:
        """The camera the page opens at: the first context camera."""
        return (self.extrinsics[0].double().cpu().numpy(),
                self.intrinsics[0].double().cpu().numpy())


class PlyScene:
    """The Gaussians of a 3DGS PLY (``read_ply``'s dict), drawn by our rasteriser at
    ``image_shape`` in the 3DGS SH basis; no model, so one label."""

    def __init__(self, gaussians: dict, image_shape: tuple[int, int], name: str = "PLY"):
        if not len(gaussians["means"]):
            raise ValueError(f"{name} holds no Gaussians: nothing to view")
        self.gaussians = gaussians
        self.labels = [name]
        self.image_shape = tuple(image_shape)
        means = gaussians["means"].double()
        self.centre = means.median(0).values.numpy()
        # The scene's size: 90% of the Gaussians lie within it of their median (robust to the
        # floaters that trained 3DGS scenes keep far away).
        distance = (means - means.median(0).values).norm(dim=1).numpy()
        self.extent = max(float(np.percentile(distance, 90)), 1e-6)
        self.near, self.far = 1e-3 * self.extent, 1e3 * self.extent

    def render(self, label: str, c2w: np.ndarray, intrinsics: np.ndarray) -> View:
        g = self.gaussians
        start = time.perf_counter()
        with torch.no_grad():
            out = rasterize(torch.as_tensor(c2w, dtype=torch.float32)[None],
                            torch.as_tensor(intrinsics, dtype=torch.float32)[None],
                            torch.tensor([self.near]), torch.tensor([self.far]),
                            self.image_shape, torch.zeros(1, 3), g["means"][None],
                            g["covariances"][None], g["harmonics"][None], g["opacities"][None],
                            RasterSettings(sh_basis="3dgs"))
        seconds = time.perf_counter() - start
        alpha = out.alpha[0].numpy()
        return View(out.color[0].clamp(0, 1).permute(1, 2, 0).numpy(), alpha,
                    out.depth[0].numpy() / np.maximum(alpha, 1e-3), len(g["means"]), seconds)

    def frustums(self) -> list:
        return []

    def start(self) -> tuple[np.ndarray, np.ndarray]:
        """A camera 2.5 extents before the centre, looking along +Z with -Y up (COLMAP-made
        scenes are often so; the page's mouse moves it from there)."""
        c2w = np.eye(4)
        c2w[:3, 3] = self.centre - np.array([0.0, 0.0, 2.5 * self.extent])
        return c2w, intrinsics_from_fov(math.radians(60), 1.0)
