"""``usplat view``: the camera conversion against independent references (a look-at camera
built by hand, scipy's quaternions, viser's own), the throttle, one view's render (the model's
own ``predict``; a PLY through our rasteriser), the arguments, and the viewer in a real browser:
headless Chromium driven over the Chrome DevTools Protocol through a websocket (no Selenium)."""

import argparse
import base64
import doctest
import io
import json
import math
import os
import shutil
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request

import numpy as np
import pytest
import torch
from PIL import Image
from scipy.spatial.transform import Rotation

import usplat_dr
from tests.data.test_importers import Truth
from usplat_dr.cli import main
from usplat_dr.data.user_views import context_views, read_cameras
from usplat_dr.jobs import view
from usplat_dr.model.ply import write_ply
from usplat_dr.viewer import scene as viewer_scene
from usplat_dr.viewer import server as viewer_server


def parse(*argv: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    view.add_arguments(p)
    return p.parse_args(list(argv))


@pytest.fixture(scope="module")
def truth(tmp_path_factory):
    t = Truth(tmp_path_factory.mktemp("scene"))
    t.write_colmap_binary(t.root / "sparse" / "0")
    return t


def own_args(truth, *extra: str) -> argparse.Namespace:
    images = [str(truth.root / "images" / truth.names[i]) for i in (1, 3)]
    return parse("--images", *images, "--cameras",
                 str(truth.root / "sparse" / "0"), *extra)


@pytest.fixture(scope="module")
def scene(truth):
    """The default model (full-64) and its default comparison (baseline-64) on two of the
    truth's views, at 64x64."""
    return view.scene_from_args(own_args(truth, "--image-shape", "64", "64"))


# ---- Cameras -----------------------------------------------------------------------------

def look_at(position, target, up) -> np.ndarray:
    """OpenCV camera-to-world of a camera at ``position`` looking at ``target``, built by hand:
    +Z towards the target, +X right, +Y down (minus ``up``, made orthogonal)."""
    z = (target - position) / np.linalg.norm(target - position)
    x = np.cross(z, up)  # forward x up = right, for a right-handed frame with y down
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([x, y, z], 1)
    c2w[:3, 3] = position
    return c2w


def project(c2w, k, point) -> np.ndarray:
    """Normalised image coordinates (u, v) of a world point: the pinhole model by hand."""
    cam = np.linalg.inv(c2w) @ np.append(point, 1.0)
    return (k @ (cam[:3] / cam[2]))[:2]


@pytest.mark.parametrize("seed", range(5))
def test_a_camera_looking_at_a_point_sees_it_at_the_image_centre(seed):
    rng = np.random.default_rng(seed)
    position, target = rng.normal(size=3) * 3, rng.normal(size=3)
    up = np.array([0.0, 0.0, 1.0])
    truth = look_at(position, target, up)
    # viser's camera as the browser reports it: the quaternion from scipy (x, y, z, w; our
    # own conversion is not used to make the input)
    x, y, z, w = Rotation.from_matrix(truth[:3, :3]).as_quat()
    fov, aspect = math.radians(rng.uniform(30, 90)), rng.uniform(0.5, 2.0)
    c2w, k = viewer_scene.camera_from_viser([w, x, y, z], position, fov, aspect)
    # 1e-9: float64 arithmetic on numbers of order 10
    np.testing.assert_allclose(c2w, truth, atol=1e-9)
    np.testing.assert_allclose(project(c2w, k, target), [0.5, 0.5], atol=1e-9)
    # the edges of the fields of view: half the vertical fov up is the top edge (v = 0, image
    # +Y is down), aspect times the tangent to the right is the right edge (u = 1)
    d = np.linalg.norm(target - position)
    right, down = truth[:3, 0], truth[:3, 1]
    top = target - down * d * math.tan(fov / 2)
    np.testing.assert_allclose(project(c2w, k, top), [0.5, 0.0], atol=1e-9)
    edge = target + right * d * math.tan(fov / 2) * aspect
    np.testing.assert_allclose(project(c2w, k, edge), [1.0, 0.5], atol=1e-9)
    assert viewer_scene.fov_from_intrinsics(k) == pytest.approx((fov, aspect), abs=1e-12)


def test_c2w_round_trips_through_viser_and_matches_scipy_quaternions():
    rng = np.random.default_rng(0)
    for rot in Rotation.random(50, random_state=1):
        c2w = np.eye(4)
        c2w[:3, :3] = rot.as_matrix()
        c2w[:3, 3] = rng.normal(size=3) * 10
        wxyz, position = viewer_scene.viser_from_c2w(c2w)
        x, y, z, w = rot.as_quat()
        ref = np.array([w, x, y, z]) * np.sign(w)  # q and -q are one rotation: w >= 0
        np.testing.assert_allclose(wxyz, ref, atol=1e-9)
        np.testing.assert_allclose(viewer_scene.c2w_from_viser(wxyz, position), c2w, atol=1e-6)


def test_viser_reads_our_quaternions_as_the_same_rotation():
    tf = pytest.importorskip("viser.transforms", reason="viser is not installed (the view "
                             "extra)")
    for rot in Rotation.random(20, random_state=2):
        wxyz, _ = viewer_scene.viser_from_c2w(np.block([[rot.as_matrix(), np.zeros((3, 1))],
                                                [np.zeros((1, 3)), np.ones((1, 1))]]))
        np.testing.assert_allclose(tf.SO3(wxyz).as_matrix(), rot.as_matrix(), atol=1e-9)


def test_the_docstring_examples_run():
    for module in (viewer_scene, viewer_server):
        result = doctest.testmod(module)
        assert result.attempted >= 1 and not result.failed, module.__name__


@pytest.mark.parametrize("fov, aspect, message", [
    (0.0, 1.0, "fov_y must be in"), (math.pi, 1.0, "fov_y must be in"),
    (1.0, 0.0, "aspect > 0"), (1.0, float("nan"), "aspect > 0")])
def test_bad_fields_of_view_are_errors(fov, aspect, message):
    with pytest.raises(ValueError, match=message):
        viewer_scene.intrinsics_from_fov(fov, aspect)


def test_a_zero_quaternion_is_an_error():
    with pytest.raises(ValueError, match="wxyz must be a non-zero"):
        viewer_scene.c2w_from_viser([0, 0, 0, 0], [0, 0, 0])


# ---- Throttling --------------------------------------------------------------------------

def test_while_a_render_runs_only_the_newest_camera_waits():
    done, release = [], threading.Event()

    def work(key, job):
        if job == "boom":
            raise RuntimeError("a failed view")
        if not done:
            release.wait(10)  # the first job holds the worker while the others arrive
        done.append((key, job))

    queue = viewer_server.LatestOnly(work)
    try:
        queue.submit("a", 0)
        time.sleep(0.2)  # the worker has taken job 0
        for job in range(1, 6):
            queue.submit("a", job)
        queue.submit("b", 0)
        release.set()
        assert queue.wait_idle(10.0)
        assert done == [("a", 0), ("a", 5), ("b", 0)]
        queue.submit("a", "boom")  # logged, and the worker goes on
        queue.submit("b", 1)
        assert queue.wait_idle(10.0)
        assert done[-1] == ("b", 1)
    finally:
        queue.close()
    assert not queue.thread.is_alive()


# ---- One view ----------------------------------------------------------------------------

def test_own_photographs_open_with_the_128x128_c(truth):
    # no --checkpoint and no --image-shape: own images get the largest shipped (c), beside the
    # (a) with a user name nearest its size (the 128x128 (a) has none)
    wide = view.scene_from_args(own_args(truth))
    assert wide.labels == ["(c) UniqueSplat: full-128", "(a) primary network: baseline-64"]
    v = wide.render(wide.labels[0], *wide.start())
    assert v.color.shape == (128, 128, 3) and v.gaussians == 2 * 128 * 128


def test_a_view_is_what_predict_renders_for_that_camera(scene, truth):
    assert scene.labels == ["(c) UniqueSplat: full-64", "(a) primary network: baseline-64"]
    c2w, k = scene.start()
    c2w = c2w.copy()
    c2w[:3, 3] += 0.3 * c2w[:3, 0]  # a step to the right of the first context camera
    v = scene.render(scene.labels[0], c2w, k)
    assert v.color.shape == (64, 64, 3) and v.alpha.shape == v.depth.shape == (64, 64)
    assert v.gaussians == 2 * 64 * 64  # pixel-aligned: one per context pixel
    assert v.seconds > 0

    model = usplat_dr.load("full-64")
    views = context_views([truth.root / "images" / truth.names[i] for i in (1, 3)],
                          read_cameras(truth.root / "sparse" / "0"), (64, 64))
    pred = model.predict(views.images, intrinsics=views.intrinsics,
                         extrinsics=views.extrinsics, target_intrinsics=torch.tensor(k).float(),
                         target_extrinsics=torch.tensor(c2w).float(), near=views.near,
                         far=views.far)
    assert np.array_equal(v.color, pred.color[0].permute(1, 2, 0).numpy())
    assert np.array_equal(v.depth, pred.depth[0].numpy())

    lo, hi = viewer_scene.depth_range(v)
    assert 0 < lo < hi
    images = {c: viewer_scene.to_image(v, c, (lo, hi)) for c in viewer_scene.CHANNELS}
    assert all(im.shape == (64, 64, 3) and im.dtype == np.uint8 for im in images.values())
    np.testing.assert_array_equal(images["opacity"][..., 0],
                                  (np.clip(v.alpha, 0, 1) * 255 + 0.5).astype(np.uint8))
    assert not images["depth"][v.alpha < viewer_scene.DEPTH_ALPHA].any()  # black where nothing is
    with pytest.raises(ValueError, match="channel must be one of"):
        viewer_scene.to_image(v, "normals", (lo, hi))

    # the same Gaussians as a 3DGS PLY, drawn without the model, give the same view
    write_ply(truth.root / "g.ply", pred.gaussians[0])
    ply = view.scene_from_args(parse("--ply", str(truth.root / "g.ply"), "--image-shape",
                                     "64", "64"))
    p = ply.render(ply.labels[0], c2w, k)
    # 1e-5: float32 SH through the basis change to 3DGS's and back (measured 3e-7)
    np.testing.assert_allclose(p.color, v.color, atol=1e-5)
    np.testing.assert_allclose(p.alpha, v.alpha, atol=1e-5)
    assert p.gaussians == v.gaussians and ply.labels == ["PLY: g.ply"]


def test_a_dataset_scene_seen_from_its_context_cameras_shows_their_images(protocol_set):
    """--data: each context camera, passed through viser's camera (wxyz, position, fov,
    aspect) and back, renders its own image and not the other one."""
    scene = view.scene_from_args(parse("--checkpoint", "study/tiny_full", "--data",
                                       str(protocol_set), "--compare", "none"))
    assert scene.labels == ["(c) UniqueSplat: study/tiny_full"] and scene.image_shape == (64, 64)
    images = scene.images.permute(0, 2, 3, 1).numpy()
    for i, (c2w, k) in enumerate(scene.frustums()):
        wxyz, position = viewer_scene.viser_from_c2w(c2w)
        c2w_v, k_v = viewer_scene.camera_from_viser(wxyz, position,
                                                    *viewer_scene.fov_from_intrinsics(k))
        np.testing.assert_allclose(k_v, k, atol=1e-6)  # the data's intrinsics are float32
        color = scene.render(scene.labels[0], c2w_v, k_v).color
        psnr = [-10 * np.log10(((color - im) ** 2).mean()) for im in images]
        # measured 30.3 and 25.7 dB at its own camera, 15.4 and 15.6 at the other
        assert psnr[i] > 22 and psnr[i] > psnr[1 - i] + 5, (i, psnr)


# ---- Arguments ---------------------------------------------------------------------------

@pytest.mark.parametrize("argv, message", [
    ([], "give --data (a dataset in the chunk format) or --images"),
    (["--checkpoint", "full-64"], "give --data (a dataset in the chunk format) or --images"),
    (["--checkpoint", "tiny_full", "--data", "d", "--images", "a", "b"], "one of them"),
    (["--ply", "g.ply", "--checkpoint", "tiny_full"], "give --ply FILE alone"),
    # without --cameras the photos are posed first (usplat pose): named when missing
    (["--checkpoint", "tiny_full", "--images", "a", "b"], "photo a does not exist"),
    (["--checkpoint", "tiny_full", "--images", "a", "b", "--cameras", "c", "--near", "1"],
     "give both --near and --far"),
    (["--checkpoint", "tiny_full", "--port", "70000"], "--port must be in 0..65535"),
])
def test_mistakes_name_the_argument(capsys, argv, message):
    assert main(["-q", "view", *argv]) == 2
    assert message in capsys.readouterr().err


def test_without_viser_the_error_names_the_extra(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "viser", None)  # what a missing package raises
    assert main(["-q", "view", "--ply", "g.ply"]) == 2
    assert "needs the viser package (the 'view' extra)" in capsys.readouterr().err


def test_the_shipped_full_model_is_compared_with_the_shipped_baseline():
    assert view.compare_checkpoint(parse("--checkpoint", "full-64")) == "baseline-64"
    assert view.compare_checkpoint(parse("--checkpoint", "baseline-64")) is None
    assert view.compare_checkpoint(parse("--checkpoint", "study/tiny_full")) is None
    assert view.compare_checkpoint(parse("--checkpoint", "full-64", "--compare",
                                         "none")) is None
    assert view.compare_checkpoint(parse("--checkpoint", "baseline-64", "--compare",
                                         "study/tiny_agnostic")) == "study/tiny_agnostic"


# ---- In a real browser -------------------------------------------------------------------

#: Debian's packages: chromium (/usr/bin/chromium), chromium-headless-shell.
BROWSERS = ("chromium", "chromium-headless-shell", "chromium-browser", "google-chrome")
#: The page's 3D canvas below the GUI panels (right) and the notices (left), and left of the
#: axes gizmo: where the rendered view is seen whole, as fractions of the viewport.
CLEAR = (slice(0.45, 0.95), slice(0.15, 0.95))


def browser() -> str | None:
    return next((p for name in BROWSERS if (p := shutil.which(name))), None)


class DevTools:
    """A page of a browser, driven over the Chrome DevTools Protocol (JSON over a websocket:
    a command carries an id, its reply the same id; events in between are skipped)."""

    def __init__(self, url: str):
        from websockets.sync.client import connect

        self.ws = connect(url, max_size=None, open_timeout=20)
        self.next_id = 0

    def call(self, method: str, **params) -> dict:
        self.next_id += 1
        self.ws.send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        while True:
            reply = json.loads(self.ws.recv(timeout=30))
            if reply.get("id") == self.next_id:
                assert "error" not in reply, reply
                return reply["result"]

    def screenshot(self) -> np.ndarray:
        data = self.call("Page.captureScreenshot", format="png")["data"]
        return np.asarray(Image.open(io.BytesIO(base64.b64decode(data))).convert("RGB"))

    def text(self) -> str:
        return self.call("Runtime.evaluate", expression="document.body.innerText",
                         returnByValue=True)["result"]["value"]

    def drag(self, start: tuple[int, int], end: tuple[int, int], steps: int = 10) -> None:
        """A left-button mouse drag, as a user's (pressed, moved in steps, released)."""
        (x0, y0), (x1, y1) = start, end
        self.call("Input.dispatchMouseEvent", type="mousePressed", x=x0, y=y0,
                  button="left", buttons=1, clickCount=1)
        for i in range(1, steps + 1):
            self.call("Input.dispatchMouseEvent", type="mouseMoved",
                      x=x0 + (x1 - x0) * i / steps, y=y0 + (y1 - y0) * i / steps,
                      button="left", buttons=1)
            time.sleep(0.03)
        self.call("Input.dispatchMouseEvent", type="mouseReleased", x=x1, y=y1,
                  button="left", buttons=0, clickCount=1)

    def close(self) -> None:
        self.ws.close()


def clear_area(image: np.ndarray) -> np.ndarray:
    h, w = image.shape[:2]
    rows, cols = CLEAR
    return image[int(rows.start * h):int(rows.stop * h), int(cols.start * w):int(cols.stop * w)]


def likeness(screenshot: np.ndarray, shown: np.ndarray) -> float:
    """Correlation of the page's clear area with the image the server sent, stretched over
    the viewport as the page stretches its background."""
    h, w = screenshot.shape[:2]
    sent = np.asarray(Image.fromarray(shown).resize((w, h), Image.BILINEAR))
    a = clear_area(screenshot).astype(float).mean(2).ravel()
    b = clear_area(sent).astype(float).mean(2).ravel()
    return float(np.corrcoef(a, b)[0, 1]) if a.std() > 0 and b.std() > 0 else 0.0


def wait_for(condition, timeout: float, what: str):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if value := condition():
            return value
        time.sleep(0.2)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


@pytest.fixture
def chromium(tmp_path):
    """Start headless Chromium at a URL: ``start(url) -> DevTools`` of its page."""
    path = browser()
    if path is None:
        pytest.skip(f"no Chromium ({', '.join(BROWSERS)}): apt-get install chromium (bash "
                    f"scripts/run.sh setup installs it as root)")
    procs, tools = [], []

    def start(url: str) -> DevTools:
        profile = tmp_path / "chromium"
        args = [path, "--headless=new", "--remote-debugging-port=0", f"--user-data-dir={profile}",
                "--window-size=800,600", "--no-first-run", "--no-default-browser-check",
                "--disable-dev-shm-usage",
                # WebGL without a GPU: SwiftShader, which Chromium >= 137 uses only when asked
                "--use-angle=swiftshader", "--enable-unsafe-swiftshader", url]
        if hasattr(os, "geteuid") and os.geteuid() == 0:
            args.insert(1, "--no-sandbox")  # Chromium refuses to run as root with its sandbox
        log = open(tmp_path / "chromium.log", "w")  # noqa: SIM115 (closed with the process)
        procs.append((subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=log), log))
        port_file = profile / "DevToolsActivePort"  # Chromium writes its port there

        def ready():
            if procs[-1][0].poll() is not None:
                output = (tmp_path / "chromium.log").read_text()[-2000:]
                raise AssertionError(f"Chromium exited: {output}")
            return port_file.is_file() and port_file.read_text().split()
        port = int(wait_for(ready, 30, "Chromium's DevTools port")[0])
        pages = json.load(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list",
                                                 timeout=10))
        page = next(p for p in pages if p["type"] == "page")
        tools.append(DevTools(page["webSocketDebuggerUrl"]))
        return tools[-1]

    yield start
    for t in tools:
        t.close()
    for proc, log in procs:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()


def test_the_viewer_in_a_real_browser_renders_and_follows_a_mouse_drag(truth, chromium):
    """The page loads and shows the view the model rendered for its camera; a mouse drag over
    the page orbits the camera, the model predicts the new view, and the page shows it."""
    pytest.importorskip("viser", reason="viser is not installed (the view extra: pip install "
                        "-c constraints.txt -e '.[view]')")
    # in-process (the server's threads), at 64x64: the readout below counts its Gaussians
    viewer = view.start(own_args(truth, "--port", "0", "--image-shape", "64", "64"))
    try:
        page = chromium(viewer.url)
        # ---- the first view: the first context camera ----
        client = wait_for(lambda: list(viewer.history), 30, "a browser to connect")[0]
        # the page reports a camera or two before it applies the server's opening camera
        start = viewer.scene.start()[0]
        wait_for(lambda: any(np.allclose(j.c2w, start, atol=1e-5)
                             for j in viewer.history[client]), 30,
                 "a view rendered at the first context camera")
        assert viewer.queue.wait_idle(30.0)
        first = viewer.history[client][-1]
        # 1e-5: the pose went to the page and back as three.js computes it (float64, with
        # the scene's up direction applied and removed)
        np.testing.assert_allclose(first.c2w, start, atol=1e-5)
        shown_first = viewer.shown[client].copy()
        wait_for(lambda: likeness(page.screenshot(), shown_first) > 0.8, 20,
                 "the page to show the rendered view")
        before = page.screenshot()
        assert clear_area(before).std() > 10  # a rendered frame, not a blank page
        wait_for(lambda: "8,192 Gaussians for this view" in page.text(), 10, "the readout")

        # ---- a drag orbits the camera around its look-at point ----
        h, w = before.shape[:2]
        rendered = len(viewer.history[client])
        page.drag((int(0.4 * w), int(0.7 * h)), (int(0.4 * w) + 80, int(0.7 * h)))
        moved = wait_for(lambda: [j for j in viewer.history[client][rendered:]
                                  if not np.allclose(j.c2w, first.c2w, atol=1e-3)], 30,
                         "a view predicted for the moved camera")
        centre = viewer.server.initial_camera.look_at
        for job in moved:
            # every camera the page reports still looks at the orbit's centre (a check of
            # viser's camera convention and ours, end to end; 1e-4: float32 in three.js)
            np.testing.assert_allclose(project(job.c2w, job.intrinsics, centre), [0.5, 0.5],
                                       atol=1e-4)
        assert viewer.queue.wait_idle(30.0)
        shown_after = viewer.shown[client].copy()
        after = wait_for(lambda: [s for s in [page.screenshot()]
                                  if likeness(s, shown_after) > 0.8], 20,
                         "the page to show the new view")[0]
        assert likeness(after, shown_after) > likeness(after, shown_first) + 0.2
        assert np.abs(after.astype(float) - before).mean() > 5

        # ---- the (a)/(c) switch, as the page's dropdown sets it ----
        state = viewer.state[client]
        state["gui"]["model"].value = viewer.scene.labels[1]
        wait_for(lambda: viewer.history[client][-1].label == viewer.scene.labels[1], 30,
                 "a view by the other model")
        wait_for(lambda: "(a) primary network: baseline-64" in page.text(), 10,
                 "the readout of the other model")
    finally:
        viewer.stop()


def test_a_websocket_from_another_page_is_refused(truth):
    """A page elsewhere that the user visits could open ws://127.0.0.1:PORT and receive the
    renders: only this viewer's own page (or a program that sends no Origin) may connect."""
    import viser
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    viewer = view.start(own_args(truth, "--port", "0"))
    try:
        url = f"ws://127.0.0.1:{viewer.server.get_port()}"
        protocol = [f"viser-v{viser.__version__}"]
        with connect(url, subprotocols=protocol, open_timeout=20,
                     additional_headers={"Origin": "http://evil.example"}) as ws, \
                pytest.raises(ConnectionClosed) as closed:
            while True:  # persistent scene messages may come first; then the close
                ws.recv(timeout=20)
        assert closed.value.rcvd is not None and closed.value.rcvd.code == 1008
        assert viewer.refused == ["http://evil.example"] and not viewer.history
        with connect(url, subprotocols=protocol, open_timeout=20,
                     additional_headers={"Origin": viewer.url}) as ws:
            ws.recv(timeout=20)  # served: the scene's persistent messages arrive
        assert viewer.refused == ["http://evil.example"]
    finally:
        viewer.stop()


def test_a_taken_port_moves_on_and_an_address_not_here_is_one_line(caplog):
    import logging
    import socket

    from usplat_dr.viewer.server import listening_port

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with caplog.at_level(logging.WARNING, logger="usplat_dr.viewer.server"):
            chosen = listening_port("127.0.0.1", port)
        assert chosen != port and chosen > port
        assert f"port {port} is taken: serving on {chosen}" in caplog.text
    # 192.0.2.1 (TEST-NET-1) is no address of this machine: refused at once, naming it
    with pytest.raises(ValueError, match=r"--host 192.0.2.1: cannot listen there"):
        listening_port("192.0.2.1", 8080)
    with pytest.raises(ValueError, match="is not an address"):
        listening_port("no such host.invalid", 8080)
    assert listening_port("127.0.0.1", 0) == 0


@pytest.mark.slow
def test_view_ply_starts_under_a_memory_limit_and_serves_only_its_own_files(tmp_path):
    # containers and shared nodes cap the address space: `usplat view --ply` must start
    # under 4 GiB (it once asked for its 4 GiB PLY bound at once), listen on 127.0.0.1 only,
    # and serve no file outside its client by any spelling of a path
    import socket

    from tests.model.test_ply import random_gaussians
    from usplat_dr.model.ply import write_ply

    pytest.importorskip("viser", reason="usplat view needs the view extra")
    ply = write_ply(tmp_path / "g.ply", random_gaussians(50))
    (tmp_path / "secret.txt").write_text("not for the page")
    limit = 4 * 2**30
    capped = (f"import resource, sys; resource.setrlimit(resource.RLIMIT_AS, ({limit}, {limit}))"
              f"; from usplat_dr.cli import main; sys.exit(main(sys.argv[1:]))")

    with socket.socket() as s:  # a free port for it
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-c", capped, "view", "--ply", str(ply),
                             "--image-shape", "32", "32", "--port", str(port)],
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    try:
        deadline = time.monotonic() + 120
        line = ""
        while "open http" not in line and time.monotonic() < deadline:
            line = proc.stdout.readline()
            assert line or proc.poll() is None, "the viewer ended before serving"
        assert f"open http://127.0.0.1:{port}" in line, line
        page = urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=20).read()
        assert b"<html" in page.lower()
        for spelling in ("../secret.txt", "%2e%2e/secret.txt", "..%2fsecret.txt",
                         str(tmp_path / "secret.txt"), "%2fetc%2fpasswd"):
            try:
                body = urllib.request.urlopen(f"http://127.0.0.1:{port}/{spelling}",
                                              timeout=20).read()
            except urllib.error.HTTPError:
                continue  # refused
            assert b"not for the page" not in body and b"root:" not in body, spelling
        # 127.0.0.1 only: the machine's other addresses do not answer
        other = socket.gethostbyname(socket.gethostname())
        if other != "127.0.0.1" and not other.startswith("127."):
            with socket.socket() as s, pytest.raises(OSError):
                s.settimeout(5)
                s.connect((other, port))
    finally:
        proc.kill()
        proc.wait()
