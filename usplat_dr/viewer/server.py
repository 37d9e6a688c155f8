"""The viewer's server (``usplat view``): a viser server whose every browser camera is a
target view of a scene (``usplat_dr.viewer.scene``), rendered on one worker thread
(``LatestOnly``: while one runs, only the newest camera of each browser waits), shown as the
page's background image with the Gaussian count and the time per view; its page is served only
to its own origin.
"""

import asyncio
import errno
import ipaddress
import logging
import socket
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from usplat_dr.viewer.scene import (
    CHANNELS,
    DEPTH_ALPHA,
    VIEWER_HINT,
    camera_from_viser,
    depth_range,
    fov_from_intrinsics,
    to_image,
    viser_from_c2w,
)

log = logging.getLogger(__name__)



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


#: How many ports after a taken ``--port`` the viewer tries.
PORT_TRIES = 100


def listening_port(host: str, port: int) -> int:
    """The port the viewer will serve on: ``port`` (0: any free one) or, where it is taken,
    the next free one of the ``PORT_TRIES`` after it, said; a ``ValueError`` naming the host
    where this machine has no such address, or the ports where none is free.

    Examples:
        >>> listening_port("127.0.0.1", 0)
        0
    """
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    if port == 0:
        candidates = [0]
    else:
        candidates = range(port, min(port + PORT_TRIES, 65535) + 1)
    for candidate in candidates:
        try:
            s = socket.socket(family, socket.SOCK_STREAM)
        except OSError as e:  # an IPv6 address on a machine without IPv6
            raise ValueError(f"--host {host}: this machine cannot listen on such an address "
                             f"({e.strerror}): give 127.0.0.1 or 0.0.0.0") from None
        with s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind((host, candidate))
            except socket.gaierror as e:
                raise ValueError(f"--host {host!r} is not an address ({e.strerror}): give "
                                 f"127.0.0.1, 0.0.0.0 or an address of this machine") from None
            except OSError as e:
                if e.errno == errno.EADDRINUSE:
                    continue
                raise ValueError(f"--host {host}: cannot listen there ({e.strerror}): give "
                                 f"127.0.0.1, 0.0.0.0 or an address of this machine") from None
        if candidate != port:
            log.warning("port %d is taken: serving on %d (--port to choose)", port, candidate)
        return candidate
    raise ValueError(f"--port {port}: it and the {len(candidates) - 1} ports after it are "
                     f"taken: give another --port, or 0 for any free one")


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
        port = listening_port(host, port)  # before viser: it would wait on an address it
        self.server = viser.ViserServer(host=host, port=port, label="usplat view",  # cannot
                                        verbose=False)  # bind, or count past port 65535
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
