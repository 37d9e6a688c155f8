"""``usplat view``: an interactive viewer in the browser (viser), where every camera the user
moves to is a target view: UniqueSplat predicts that view's own Gaussians and renders them.

The scene is a checkpoint with two context views, from a dataset (``--data``) or the user's own
images and camera file (``--images A B --cameras FILE``), or a 3DGS PLY (``--ply FILE``, drawn
by our rasteriser, no model). For each camera a browser reports (``client.camera.on_update``),
the viewer turns viser's camera into an OpenCV camera-to-world matrix and normalised
intrinsics (``camera_from_viser``), predicts and renders that one view (``ModelScene.render``)
and shows the chosen channel (colour, depth, opacity) as the page's background image, with the
Gaussian count and the time per view. Renders run on one worker thread (``LatestOnly``): while
one runs, only the newest camera of each browser waits. ``--compare`` adds a second model, (a)
beside (c), switched in the page.

Viser's camera (``viser.CameraHandle``): ``wxyz`` is the rotation camera -> world with OpenCV
camera axes (+X right, +Y down, +Z forward: the data's convention), ``position`` the centre in
world coordinates, ``fov`` the vertical field of view in radians, ``aspect`` the canvas'
width / height. The background image is stretched over the whole canvas, so it is rendered with
the canvas' fields of view, whatever its pixel size.
"""

import argparse
import asyncio
import ipaddress
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from usplat_dr.data.types import model_inputs
from usplat_dr.geometry.quaternions import matrix_to_quat_wxyz, quat_xyzw_to_matrix
from usplat_dr.io.images import colorize_depth, to_uint8
from usplat_dr.jobs.arguments import (
    CHECKPOINT_HELP,
    DATASET_HELP,
    DATASETS,
    DEVICE_HELP,
    add_image_shape_argument,
    add_own_views_arguments,
    add_trust_argument,
    check_own_views,
    fit_checkpoint,
    one_example,
    own_views,
)
from usplat_dr.model.ply import read_ply
from usplat_dr.model.uniquesplat import VARIANTS
from usplat_dr.render import RasterSettings, rasterize
from usplat_dr.training.loader import load
from usplat_dr.training.registry import canonical_name, shipped_models

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


# ---- Throttling --------------------------------------------------------------------------

class LatestOnly:
    """Runs ``work(key, job)`` on one worker thread, the newest job per key: a job submitted
    while another waits for the same key replaces it, so a browser that moves faster than the
    model renders sees its latest camera next, not a queue of stale ones. Keys take turns."""

    def __init__(self, work: Callable[[object, object], None]):
        self.work = work
        self.pending: dict = {}  # key -> newest job not started yet (insertion order = turns)
        self.running = False
        self.cond = threading.Condition()
        self.closed = False
        self.thread = threading.Thread(target=self._loop, name="usplat-view-render",
                                       daemon=True)
        self.thread.start()

    def submit(self, key, job) -> None:
        with self.cond:
            self.pending.pop(key, None)  # to the back of the turns
            self.pending[key] = job
            self.cond.notify_all()

    def drop(self, key) -> None:
        with self.cond:
            self.pending.pop(key, None)

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Whether every submitted job finished within ``timeout`` seconds."""
        with self.cond:
            return self.cond.wait_for(lambda: not self.pending and not self.running, timeout)

    def close(self) -> None:
        with self.cond:
            self.closed = True
            self.pending.clear()
            self.cond.notify_all()
        self.thread.join(timeout=10)

    def _loop(self) -> None:
        while True:
            with self.cond:
                self.cond.wait_for(lambda: self.pending or self.closed)
                if self.closed:
                    return
                key = next(iter(self.pending))
                job = self.pending.pop(key)
                self.running = True
            try:
                self.work(key, job)
            except Exception:  # one bad view must not stop the viewer
                log.exception("usplat view: rendering a view failed")
            finally:
                with self.cond:
                    self.running = False
                    self.cond.notify_all()


# ---- The server --------------------------------------------------------------------------

@dataclass
class Job:
    """What one browser asked for: a camera, the model label and the channel."""

    c2w: np.ndarray
    intrinsics: np.ndarray
    label: str
    channel: str

    def same_camera(self, other: "Job | None") -> bool:
        # 1e-9: viser echoes back the camera it was sent; any real move is far larger.
        return (other is not None and self.label == other.label
                and np.allclose(self.c2w, other.c2w, rtol=0, atol=1e-9)
                and np.allclose(self.intrinsics, other.intrinsics, rtol=0, atol=1e-9))


class Viewer:
    """A running viewer: the viser server on ``host``:``port`` (0: any free port) showing
    ``scene``. ``history[client_id]`` lists the jobs rendered for each browser, in order, and
    ``shown[client_id]`` is the image it was sent last (what the tests read); ``stop()`` ends
    it."""

    def __init__(self, scene, host: str = "127.0.0.1", port: int = 8080):
        try:
            import viser  # the optional view extra: a clear error without it
        except ImportError:
            raise ValueError(VIEWER_HINT) from None
        self.scene = scene
        start_c2w, start_k = scene.start()
        self.start_view = scene.render(scene.labels[0], start_c2w, start_k)
        self.depth_range = depth_range(self.start_view)
        self.server = viser.ViserServer(host=host, port=port, label="usplat view",
                                        verbose=False)
        self.history: dict[int, list[Job]] = {}
        self.shown: dict[int, np.ndarray] = {}
        self.state: dict[int, dict] = {}
        self.lock = threading.Lock()
        self.queue = LatestOnly(self._render)
        self._set_scene(start_c2w, start_k)
        self.refused: list[str] = []  # origins refused (``_check_origin``)
        self.server._websock_server.on_client_connect(self._check_origin)
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)

    @property
    def url(self) -> str:
        """The page's address (on this machine, where it serves every interface)."""
        host = self.server.get_host()
        host = "127.0.0.1" if host in ("0.0.0.0", "::", "") else host
        return f"http://{host}:{self.server.get_port()}"

    def _set_scene(self, c2w: np.ndarray, k: np.ndarray) -> None:
        """The opening camera (its look-at point at the median depth it sees, the orbit's
        centre) and the context cameras as frustums."""
        fov_y, _ = fov_from_intrinsics(k)
        up = -c2w[:3, 1]  # OpenCV: +Y is down
        valid = self.start_view.depth[self.start_view.alpha >= DEPTH_ALPHA]
        focus = float(np.median(valid)) if valid.size else sum(self.depth_range) / 2
        self.server.scene.set_up_direction(up)
        cam = self.server.initial_camera
        cam.position = c2w[:3, 3]
        cam.look_at = c2w[:3, 3] + focus * c2w[:3, 2]
        cam.up = up
        cam.fov = fov_y
        cam.near, cam.far = 0.01 * focus, 100.0 * focus
        # Wireframes without the context images: from the opening camera, the first frustum's
        # image would fill the view and hide the render behind it.
        for i, (e, ki) in enumerate(self.scene.frustums()):
            wxyz, position = viser_from_c2w(e)
            fov, aspect = fov_from_intrinsics(ki)
            self.server.scene.add_camera_frustum(
                f"/context/{i}", fov=fov, aspect=aspect, scale=0.15 * focus, wxyz=wxyz,
                position=position, thickness=2.0, thickness_units="screen",
                color=(230, 120, 20))

    @staticmethod
    def origin_allowed(origin: str | None, host: str | None) -> bool:
        """Whether a websocket whose page is ``origin`` (its ``Origin`` header) may connect
        to this viewer reached as ``host`` (its ``Host`` header): the same origin (the page
        this server served, however the user reached it: 127.0.0.1, localhost, or the
        machine's address with ``--host 0.0.0.0``), reached by an IP address or localhost (a
        domain name could be an attacker's, rebound to 127.0.0.1). No Origin: a program, not
        a page; allowed.

        Examples:
            >>> Viewer.origin_allowed("http://127.0.0.1:8080", "127.0.0.1:8080")
            True
            >>> Viewer.origin_allowed("https://evil.example", "127.0.0.1:8080")
            False
            >>> Viewer.origin_allowed("http://evil.example:8080", "evil.example:8080")
            False
        """
        if origin is None:
            return True
        if host is None or origin != f"http://{host}":
            return False
        name = host.rsplit(":", 1)[0].strip("[]")
        if name == "localhost":
            return True
        try:
            ipaddress.ip_address(name)
        except ValueError:
            return False
        return True

    def _check_origin(self, connection) -> None:
        """Called by viser's websocket server (1.x; its ``on_client_connect`` at the socket
        level, in its event loop) as each websocket opens, before the client is served: a
        page of another origin is closed with 1008. A browser always sends its page's
        origin; a local program may send none."""
        socket = self.server._websock_server._live_connections.get(connection.client_id)
        if socket is None:
            return
        origin, host = socket.request.headers.get("Origin"), socket.request.headers.get("Host")
        if not self.origin_allowed(origin, host):
            log.warning("refused a viewer connection from the page %r (not this viewer's "
                        "page)", origin)
            self.refused.append(origin)
            asyncio.ensure_future(socket.close(1008, "origin not allowed"))

    def _connect(self, client) -> None:
        if self.server._websock_server._live_connections.get(client.client_id) is None:
            return  # closed (another origin) before viser finished serving it
        labels = self.scene.labels
        gui = {"readout": client.gui.add_markdown("rendering ...")}
        if len(labels) > 1:
            gui["model"] = client.gui.add_dropdown("model", labels, initial_value=labels[0])
            gui["model"].on_update(lambda _: self.request(client.client_id))
        gui["channel"] = client.gui.add_dropdown("show", CHANNELS, initial_value=CHANNELS[0])
        gui["channel"].on_update(lambda _: self.request(client.client_id))
        with self.lock:
            self.state[client.client_id] = {"client": client, "gui": gui, "last": None,
                                            "view": None}
            self.history.setdefault(client.client_id, [])
        client.camera.on_update(lambda _: self.request(client.client_id))
        self.request(client.client_id)

    def _disconnect(self, client) -> None:
        self.queue.drop(client.client_id)
        with self.lock:
            self.state.pop(client.client_id, None)

    def request(self, client_id: int) -> None:
        """Queue a render of a browser's current camera and choices."""
        with self.lock:
            state = self.state.get(client_id)
        if state is None:
            return
        cam, gui = state["client"].camera, state["gui"]
        try:
            c2w, k = camera_from_viser(cam.wxyz, cam.position, cam.fov, cam.aspect)
        except (ValueError, ZeroDivisionError) as e:  # a canvas of size 0 while it loads
            log.debug("usplat view: camera not usable yet: %s", e)
            return
        label = gui["model"].value if "model" in gui else self.scene.labels[0]
        self.queue.submit(client_id, Job(c2w, k, label, gui["channel"].value))

    def _render(self, client_id: int, job: Job) -> None:
        with self.lock:
            state = self.state.get(client_id)
        if state is None:
            return
        view = state["view"]
        if view is None or not job.same_camera(state["last"]):
            view = self.scene.render(job.label, job.c2w, job.intrinsics)
        image = to_image(view, job.channel, self.depth_range)
        state["client"].scene.set_background_image(image, format="png")
        state["gui"]["readout"].content = (
            f"**{job.label}**  \n{view.gaussians:,} Gaussians for this view, "
            f"{view.seconds * 1e3:.0f} ms per view ({view.color.shape[0]}x"
            f"{view.color.shape[1]})")
        with self.lock:
            state["last"], state["view"] = job, view
            self.history.setdefault(client_id, []).append(job)
            self.shown[client_id] = image

    def stop(self) -> None:
        self.queue.close()
        self.server.stop()


# ---- The command -------------------------------------------------------------------------

def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--checkpoint", help=CHECKPOINT_HELP)
    p.add_argument("--compare", metavar="CHECKPOINT",
                   help="a second model to switch to in the page, e.g. baseline-64 beside "
                   "full-64; 'none' for one model (default: with a shipped (c), the shipped "
                   "(a) trained nearest its size, else none)")
    data = p.add_argument_group("context views from a dataset")
    data.add_argument("--data", help="dataset root (chunk format)")
    data.add_argument("--dataset", default="synth", choices=DATASETS,
                      help=DATASET_HELP)
    data.add_argument("--index", help="evaluation index JSON (default: the synthetic set's "
                      "standard split)")
    data.add_argument("--scene", help="scene key (default: the first of the index)")
    add_own_views_arguments(p)
    p.add_argument("--ply", help="a 3DGS PLY to look at instead of a model (rendered by our "
                   "rasteriser at --image-shape, default 256 256)")
    add_image_shape_argument(p)
    add_trust_argument(p)
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help=DEVICE_HELP)
    p.add_argument("--host", default="127.0.0.1",
                   help="address to serve on (0.0.0.0: every network interface)")
    p.add_argument("--port", type=int, default=8080,
                   help="port to serve on (the next free one if taken; 0: any)")


def compare_checkpoint(args: argparse.Namespace) -> str | None:
    """``--compare``, or its default: with a shipped user (c) (``--checkpoint``'s, after
    ``fit_checkpoint``), the shipped user (a) trained nearest its size; else none."""
    if args.compare is not None:
        return None if args.compare.lower() == "none" else args.compare
    models = shipped_models()
    name = canonical_name(args.checkpoint) if not Path(args.checkpoint).is_file() else None
    if name is None or models[name].kind != "user" or models[name].variant != "full":
        return None
    size = models[name].size or 64
    baselines = [m for m in models.values() if m.kind == "user" and m.variant == "baseline"
                 and m.size]
    if not baselines:
        return None
    return min(baselines, key=lambda m: (abs(math.log2(m.size / size)), -m.size)).name


def label(model, checkpoint: str) -> str:
    """"(c) UniqueSplat: full-64": the model's variant and where it came from (a shipped
    model's name, or a file's name)."""
    shipped = not Path(checkpoint).is_file() and canonical_name(checkpoint) is not None
    return f"{VARIANTS[model.cfg.variant]}: {checkpoint if shipped else Path(checkpoint).name}"


def check_arguments(args: argparse.Namespace) -> None:
    """The mistakes that need no file read: one scene source, and what goes with it."""
    if not 0 <= args.port <= 65535:
        raise ValueError(f"--port must be in 0..65535, got {args.port}")
    if args.ply is not None:
        if args.checkpoint or args.data or args.images:
            raise ValueError("give --ply FILE alone, or --data or --images (with a model: "
                             "--checkpoint, default the shipped (c)); a PLY is drawn without "
                             "a model")
        return
    if (args.data is None) == (args.images is None):
        raise ValueError("give --data (a dataset in the chunk format) or --images A B "
                         "--cameras FILE (your own images), one of them")
    if args.images is not None:
        check_own_views(args)


def scene_from_args(args: argparse.Namespace):
    """The ``ModelScene`` or ``PlyScene`` that the arguments name."""
    check_arguments(args)
    if args.ply is not None:
        return PlyScene(read_ply(args.ply), tuple(args.image_shape or PLY_IMAGE_SHAPE),
                        f"PLY: {Path(args.ply).name}")
    fit_checkpoint(args)
    compare = compare_checkpoint(args)
    if args.data is not None:
        model, batch = one_example(args)
        inputs = model_inputs(batch, torch.device(args.device))
        images, e, k = inputs.images[0], inputs.extrinsics[0], inputs.intrinsics[0]
        near, far = float(inputs.near[0].min()), float(inputs.far[0].max())
    else:
        model = load(args.checkpoint, args.device, args.trust_checkpoint)
        views, near, far = own_views(args, model.trained_depth_range)
        images, e, k = views.images, views.extrinsics, views.intrinsics
    models = {label(model, args.checkpoint): model}
    if compare is not None:
        other = load(compare, args.device, args.trust_checkpoint)
        models[label(other, compare)] = other
    return ModelScene(models, images.cpu(), e.cpu(), k.cpu(), float(near), float(far))


def start(args: argparse.Namespace) -> Viewer:
    """The viewer of the arguments, serving (its own threads); ``stop()`` ends it."""
    check_arguments(args)
    try:
        import viser  # noqa: F401  (before the seconds of loading a model)
    except ImportError:
        raise ValueError(VIEWER_HINT) from None
    return Viewer(scene_from_args(args), args.host, args.port)


def run(args: argparse.Namespace) -> int:
    viewer = start(args)
    print(f"usplat view: open {viewer.url} in a browser (Ctrl+C stops)", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()
    return 0

