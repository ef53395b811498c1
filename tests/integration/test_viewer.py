"""The live map viewer (``sogm-service view``): the web server's guards and the page in a real
headless browser (Debian's chromium + chromedriver through selenium).

The browser tests share one map server process, one viewer process and one browser (module
fixtures, in file order); the last one kills the map server and starts another on the same
endpoint.  Every wait is a bounded wait for a condition (WebDriverWait), never a timed assertion.
"""

from __future__ import annotations

import http.client
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sogm_service.client.mapclient import MapClient
from sogm_service.client.session import free_tcp_endpoint, wait_listening
from sogm_service.core.geometry import Pose2D
from tests.conftest import ServerProcess, start_server, wait_until
from tests.unit.apps.viewer.test_tiles import CHAIR, OBSTACLE, RES

pytestmark = pytest.mark.integration

CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path(shutil.which("chromedriver") or "/usr/bin/chromedriver")
UNKNOWN_RGB = (70, 110, 150)  # apps/render.py UNKNOWN_BGR, as the page shows it


# -- the viewer process and a map server ---------------------------------------------------------
@dataclass
class Stack:
    """A map server process, a viewer process connected to it, and a publishing client."""

    tmp: Path
    server: ServerProcess
    viewer: subprocess.Popen[bytes]
    viewer_log: Path
    url: str
    client: MapClient

    @property
    def endpoint(self) -> str:
        return self.server.endpoint

    def state(self) -> dict[str, Any]:
        with urllib.request.urlopen(self.url + "api/state", timeout=5) as r:
            result: dict[str, Any] = json.loads(r.read())
            return result

    def restart_server(self) -> None:
        """SIGKILL the map server (ours) and start a fresh one on the same endpoint."""
        self.server.proc.kill()
        self.server.proc.wait(10)
        self.server = start_server(self.tmp, endpoint=self.server.endpoint, name="server2")

    def viewer_output(self) -> str:
        return self.viewer_log.read_text(errors="replace")


def _start_viewer(tmp: Path, endpoint: str) -> tuple[subprocess.Popen[bytes], Path, str]:
    port = int(free_tcp_endpoint().rsplit(":", 1)[1])
    log_path = tmp / "viewer.log"
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "sogm_service.apps.viewer", "--connect", endpoint,
             "--http", f"127.0.0.1:{port}", "--refresh", "0.3", "--poll", "0.3"],
            stdout=log, stderr=subprocess.STDOUT, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        wait_listening(f"tcp/127.0.0.1:{port}", 30, lambda: proc.poll() is not None,
                       lambda: log_path.read_text(errors="replace"))
    except BaseException:
        proc.kill()
        proc.wait(5)
        raise
    return proc, log_path, f"http://127.0.0.1:{port}/"


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    for module in ("starlette", "uvicorn", "websockets"):
        pytest.importorskip(module, reason="the viewer needs starlette, uvicorn, websockets "
                                           "(the [viewer] extra)")
    tmp = tmp_path_factory.mktemp("viewer")
    servers = [start_server(tmp)]
    viewer: subprocess.Popen[bytes] | None = None
    client: MapClient | None = None
    try:
        viewer, log_path, url = _start_viewer(tmp, servers[0].endpoint)
        client = MapClient.connect(servers[0].endpoint, timeout=5.0)
        s = Stack(tmp, servers[0], viewer, log_path, url, client)
        assert wait_until(lambda: s.state()["connected"], 20), s.viewer_output()
        yield s
        servers.append(s.server)  # a test may have replaced it
    finally:
        if client is not None:
            client.close()
        if viewer is not None and viewer.poll() is None:
            viewer.send_signal(signal.SIGTERM)
            try:
                viewer.wait(20)
            except subprocess.TimeoutExpired:
                viewer.kill()
                viewer.wait(5)
        for srv in servers:
            if srv.proc.poll() is None:
                srv.terminate()


def publish_pattern(client: MapClient, occupied: float = 0.9, free: float = 0.1) -> None:
    """Layer obstacle: 4 x 2 m at (1, 1): left half ``occupied``, right half ``free``.
    Layer chair: 2 x 2 m at (3, 1) (over the obstacle's free half) at 0.97."""
    a = np.zeros((40, 80), np.float32)
    a[:, :40] = occupied
    a[:, 40:] = free
    client.publish_ism("ism/r1/laser/obstacle", a, resolution=RES, origin=Pose2D(1.0, 1.0),
                       robot="r1")
    client.publish_ism("ism/r1/cam/chair", np.full((40, 40), 0.97, np.float32),
                       resolution=RES, origin=Pose2D(3.0, 1.0), robot="r1")


def grey(p: float) -> tuple[int, int, int]:
    """What a probability looks like on the page: free white, occupied black."""
    g = round((1.0 - p) * 255)
    return (g, g, g)


def logit(p: float) -> float:
    return math.log(p / (1 - p))


def sigmoid(l: float) -> float:
    return 1 / (1 + math.exp(-l))


def test_page_and_socket_answer_only_their_own_host_and_origin(stack: Stack) -> None:
    port = int(stack.url.rsplit(":", 1)[1].strip("/"))

    def get(host: str) -> int:
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
        try:
            conn.request("GET", "/", headers={"Host": host})
            return conn.getresponse().status
        finally:
            conn.close()

    assert get(f"127.0.0.1:{port}") == 200
    assert get(f"localhost:{port}") == 200  # what an SSH tunnel's browser sends
    assert get("attacker.example") == 400  # DNS rebinding
    page = urllib.request.urlopen(stack.url, timeout=5)
    assert "script-src 'self'" in page.headers["Content-Security-Policy"]
    assert b"static/viewer.js" in page.read()
    assert urllib.request.urlopen(stack.url + "static/viewer.js", timeout=5).status == 200
    with pytest.raises(urllib.error.HTTPError):
        urllib.request.urlopen(stack.url + "static/../__init__.py", timeout=5)

    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    ws_url = stack.url.replace("http://", "ws://") + "ws"
    with pytest.raises(InvalidStatus):
        connect(ws_url, origin="http://attacker.example", open_timeout=5).close()  # type: ignore[arg-type]
    with connect(ws_url, origin=stack.url.rstrip("/"), open_timeout=5) as ws:  # type: ignore[arg-type]
        hello = json.loads(ws.recv(timeout=5))
        assert hello["type"] == "hello" and hello["status"]["connected"] is True
        # bad requests get a specific code and leave the connection usable
        replies = {}
        for request in ("not json", json.dumps([1]), json.dumps({"type": "format c:"}),
                        json.dumps({"type": "view", "xmin": "nan"}),
                        json.dumps({"type": "probe", "x": 1e300, "y": 0}), "x" * 20000):
            ws.send(request)
            while True:
                msg = json.loads(ws.recv(timeout=5))
                if msg["type"] == "error":
                    replies[request[:20]] = msg["code"]
                    break
        assert sorted(replies.values()) == sorted(
            ["bad_json", "bad_json", "unknown_request", "bad_view", "bad_number", "too_large"])
        ws.send(json.dumps({"type": "view", "xmin": 0, "ymin": 0, "xmax": 10, "ymax": 10,
                            "px_per_m": 50, "mode": "class"}))
        while (msg := json.loads(ws.recv(timeout=5)))["type"] != "view_ack":
            pass
        assert msg["signature"] == "class"


def test_start_viewer_serves_in_a_thread_for_the_demo(stack: Stack) -> None:
    from sogm_service.apps.viewer import start_viewer

    running = start_viewer(["--connect", stack.endpoint, "--http", "127.0.0.1:0",
                            "--poll", "0.2"])
    try:
        assert running.url.startswith("http://127.0.0.1:") and not running.url.endswith(":0/")

        def connected() -> bool:
            with urllib.request.urlopen(running.url + "api/state", timeout=5) as r:
                return bool(json.loads(r.read())["connected"])

        assert wait_until(connected, 20)
    finally:
        running.stop()
    assert not running.thread.is_alive()


# -- the page in a real browser ----------------------------------------------------------------
needs_browser = pytest.mark.skipif(
    not (CHROMIUM.exists() and CHROMEDRIVER.exists()),
    reason="needs Debian's chromium and chromium-driver (apt-get install chromium "
           "chromium-driver) for the browser tests")


@pytest.fixture(scope="module")
def browser(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    if not (CHROMIUM.exists() and CHROMEDRIVER.exists()):
        pytest.skip("needs /usr/bin/chromium and chromedriver (apt-get install chromium "
                    "chromium-driver)")
    webdriver = pytest.importorskip("selenium.webdriver", reason="needs selenium")
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = str(CHROMIUM)
    profile = tmp_path_factory.mktemp("chromium-profile")
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                 "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--disable-dev-shm-usage",
                 "--disable-smooth-scrolling",
                 f"--user-data-dir={profile}", "--window-size=1200,800",
                 "--force-device-scale-factor=1"):
        opts.add_argument(flag)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=opts)
    driver.set_script_timeout(10)
    try:
        yield driver
    finally:
        driver.quit()


@pytest.fixture(scope="module")
def console(browser: Any) -> list[dict[str, Any]]:
    """Every browser console entry of the module (chromedriver hands each out once)."""
    return []


def read_console(browser: Any, console: list[dict[str, Any]]) -> list[dict[str, Any]]:
    console.extend(browser.get_log("browser"))
    return [e for e in console if e["level"] == "SEVERE"]


def wait_for(browser: Any, condition: Any, timeout: float = 20.0, what: str = "") -> Any:
    from selenium.webdriver.support.ui import WebDriverWait

    return WebDriverWait(browser, timeout, poll_frequency=0.1).until(
        lambda d: condition(d), message=what)


def js(browser: Any, script: str, *args: Any) -> Any:
    return browser.execute_script(script, *args)


def pixel(browser: Any, x: float, y: float) -> tuple[int, int, int]:
    rgba = js(browser, "return window.sogmViewer.pixelAt(arguments[0], arguments[1]);", x, y)
    return (rgba[0], rgba[1], rgba[2])


def near(a: tuple[int, int, int], b: tuple[int, int, int], tol: int = 3) -> bool:
    return all(abs(int(p) - int(q)) <= tol for p, q in zip(a, b, strict=True))


def wait_pixel(browser: Any, x: float, y: float, rgb: tuple[int, int, int],
               timeout: float = 20.0, tol: int = 3) -> None:
    seen: list[tuple[int, int, int]] = []

    def ok(d: Any) -> bool:
        seen.append(pixel(d, x, y))
        return near(seen[-1], rgb, tol)

    wait_for(browser, ok, timeout, f"pixel at ({x}, {y}) never became {rgb}; last {seen[-3:]}")


@needs_browser
def test_page_loads_live_with_no_console_errors(stack: Stack, browser: Any,
                                                console: list[dict[str, Any]]) -> None:
    publish_pattern(stack.client)
    stack.client.publish_pose("r1", 2.0, 2.0, 0.0)
    browser.get(stack.url)
    wait_for(browser, lambda d: d.find_element("id", "status").get_attribute("data-state")
             == "connected", what="the page never showed the map server as connected")
    wait_for(browser, lambda d: js(d, "return window.sogmViewer.state.info !== null && "
             "window.sogmViewer.state.info.layers.length") == 2, what="no info with 2 layers")
    legend = browser.find_element("id", "legend").text
    assert OBSTACLE in legend and CHAIR in legend and "unknown" in legend
    wait_for(browser, lambda d: js(d, "return window.sogmViewer.state.tilesReceived") > 0,
             what="no tile reached the page")
    # the stats charts: samples arrive and the ISM rate chart has a line drawn on it
    wait_for(browser, lambda d: js(d, "return window.sogmViewer.state.stats.some("
             "s => s.isms_per_s > 0);"), what="no stats sample with an ISM rate")
    drawn = js(browser, "const c = document.getElementById('chart-isms'); "
               "const a = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; "
               "let n = 0; for (let k = 3; k < a.length; k += 4) if (a[k] > 0) n++; return n;")
    assert drawn > 50
    assert read_console(browser, console) == []


@needs_browser
def test_canvas_shows_the_published_layer_in_its_colours(stack: Stack, browser: Any) -> None:
    js(browser, "window.sogmViewer.setView(3.0, 2.0, 40.0);")
    js(browser, f"window.sogmViewer.setMode('layer', {{layer: '{OBSTACLE}'}});")
    wait_pixel(browser, 1.525, 2.025, grey(0.9))  # occupied half: dark
    wait_pixel(browser, 4.525, 2.025, grey(0.1))  # free half: light
    assert near(pixel(browser, 0.5, 0.5), UNKNOWN_RGB)  # never observed: the unknown colour
    assert near(pixel(browser, 6.0, 2.0), UNKNOWN_RGB)
    # the class view: the obstacle's colour where it is above 0.5, the chair's over its square
    js(browser, "window.sogmViewer.setMode('class');")
    palette = js(browser, "return window.sogmViewer.state.info.palette;")
    obstacle_rgb = tuple(int(palette[0][k:k + 2], 16) for k in (1, 3, 5))
    scale = 0.4 + 0.6 * (0.9 - 0.5) / 0.5  # hue of layer 0, brightness from p = 0.9
    occupied = tuple(round(c * scale) for c in obstacle_rgb)
    wait_pixel(browser, 1.525, 2.025, occupied, tol=4)  # type: ignore[arg-type]
    chair = pixel(browser, 3.525, 2.025)  # the chair's square: another class colour
    assert not near(chair, occupied, 20) and not near(chair, UNKNOWN_RGB, 20)  # type: ignore[arg-type]
    # zoomed out, the coarser pyramid level still shows the pattern
    js(browser, "window.sogmViewer.setView(3.0, 2.0, 5.0);")
    js(browser, f"window.sogmViewer.setMode('layer', {{layer: '{OBSTACLE}'}});")
    wait_for(browser, lambda d: js(d, "const r = window.sogmViewer.state.lastRefresh; "
             "return r && r.level;") == 2, what="no refresh at pyramid level 2")
    wait_pixel(browser, 1.6, 2.0, grey(0.9), tol=12)
    wait_pixel(browser, 4.4, 2.0, grey(0.1), tol=12)


@needs_browser
def test_drag_pans_wheel_zooms_and_the_scale_bar_follows(stack: Stack, browser: Any) -> None:
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.actions.wheel_input import ScrollOrigin

    js(browser, "window.sogmViewer.setView(3.0, 2.0, 40.0);")
    wait_for(browser, lambda d: d.find_element("id", "scale-label").text == "2 m")
    width = browser.find_element("id", "scale-bar").value_of_css_property("width")
    assert width == "80px"  # 2 m at 40 px/m
    overlay = browser.find_element("id", "overlay")
    ActionChains(browser).move_to_element(overlay).click_and_hold().move_by_offset(80, -40) \
        .release().perform()
    view = js(browser, "return window.sogmViewer.view;")
    assert view["cx"] == pytest.approx(3.0 - 80 / 40, abs=0.05)  # dragged right: map moves right
    assert view["cy"] == pytest.approx(2.0 - 40 / 40, abs=0.05)  # dragged up: map moves up
    ActionChains(browser).scroll_from_origin(ScrollOrigin.from_element(overlay), 0, 1500).perform()
    wait_for(browser, lambda d: js(d, "return window.sogmViewer.view.z;") < 10,
             what="the wheel did not zoom out")
    wait_for(browser, lambda d: js(d, "const r = window.sogmViewer.state.lastRefresh; "
             "return r && r.level;") >= 2, what="no refresh at a coarser level after zooming")
    assert browser.find_element("id", "scale-label").text in ("5 m", "10 m", "20 m")


@needs_browser
def test_a_pose_published_after_load_moves_the_robot_marker(stack: Stack, browser: Any) -> None:
    js(browser, "window.sogmViewer.setView(3.0, 2.0, 40.0);")
    wait_for(browser, lambda d: (js(d, "return window.sogmViewer.state.markers.r1") or {})
             .get("x") == 2.0, what="the first pose never showed")
    before = js(browser, "return window.sogmViewer.state.markers.r1")
    stack.client.publish_pose("r1", 4.5, 3.0, 1.2)
    wait_for(browser, lambda d: (js(d, "return window.sogmViewer.state.markers.r1") or {})
             .get("x") == 4.5, what="the marker never moved")
    after = json.loads(browser.find_element("id", "overlay").get_attribute("data-robots"))["r1"]
    assert after["y"] == 3.0 and after["yaw"] == pytest.approx(1.2) and before["x"] == 2.0
    # drawn where the map point is on screen (the page's own transform, read with the marker:
    # the first pose may have been drawn before the view settled)
    wait_for(browser, lambda d: js(d, "return window.sogmViewer.worldToScreen(4.5, 3.0);") == [
        pytest.approx(json.loads(d.find_element("id", "overlay").get_attribute("data-robots"))
                      ["r1"][k], abs=0.01) for k in ("sx", "sy")], what="marker off its point")
    left = js(browser, "return window.sogmViewer.worldToScreen(2.0, 2.0);")
    right = js(browser, "return window.sogmViewer.worldToScreen(4.5, 3.0);")
    assert right[0] - left[0] == pytest.approx(2.5 * 40, abs=0.01)  # 40 px/m
    assert left[1] - right[1] == pytest.approx(1.0 * 40, abs=0.01)
    assert js(browser, "return window.sogmViewer.view.z;") == 40.0
    assert "r1: 4.50, 3.00 m" in browser.find_element("id", "robots").text


@needs_browser
def test_ism_footprints_reach_the_page(stack: Stack, browser: Any) -> None:
    before = js(browser, "return window.sogmViewer.state.footprintsReceived;")
    # p = 0.5 everywhere: a footprint that changes no cell and adds no layer
    stack.client.publish_ism("ism/r1/laser/obstacle", np.full((10, 10), 0.5, np.float32),
                             resolution=RES, origin=Pose2D(2.0, 2.0, 0.5))
    wait_for(browser, lambda d: js(d, "return window.sogmViewer.state.footprintsReceived;")
             > before, what="no footprint reached the page")


@needs_browser
def test_switching_to_the_fused_view_changes_the_picture(stack: Stack, browser: Any) -> None:
    js(browser, "window.sogmViewer.setView(3.0, 2.0, 40.0);")
    js(browser, f"window.sogmViewer.setMode('layer', {{layer: '{OBSTACLE}'}});")
    point = (3.525, 2.025)  # obstacle says free (0.1), chair says 0.97
    wait_pixel(browser, *point, grey(0.1))
    js(browser, "window.sogmViewer.setMode('fused', {method: 'bayes', layers: arguments[0]});",
       [OBSTACLE, CHAIR])
    # P_B: sum of the log-odds (Eq. 6), as the map stores them after one update each
    wait_pixel(browser, *point, grey(sigmoid(logit(0.1) + logit(0.97))))
    js(browser, "window.sogmViewer.setMode('fused', {method: 'max', layers: arguments[0]});",
       [OBSTACLE, CHAIR])
    wait_pixel(browser, *point, grey(0.97))  # P_M: the largest


@needs_browser
def test_unchanged_tiles_are_not_sent_again_and_a_changed_one_is(stack: Stack,
                                                                  browser: Any) -> None:
    stack.client.publish_ism("ism/r1/laser/obstacle", np.full((20, 20), 0.2, np.float32),
                             resolution=RES, origin=Pose2D(14.0, 1.0))  # tile (1, 0)
    js(browser, "window.sogmViewer.setView(13.0, 3.0, 30.0);")
    js(browser, f"window.sogmViewer.setMode('layer', {{layer: '{OBSTACLE}'}});")
    wait_pixel(browser, 14.5, 1.5, grey(0.2))
    wait_pixel(browser, 1.525, 2.025, grey(0.9))

    def settled() -> tuple[int, int]:
        n = js(browser, "return window.sogmViewer.state.refreshes;")
        wait_for(browser, lambda d: js(d, "return window.sogmViewer.state.refreshes;") >= n + 3,
                 what="the viewer stopped refreshing")
        return n, js(browser, "return window.sogmViewer.state.tilesReceived;")

    settled()
    _, received = settled()
    last = js(browser, "return window.sogmViewer.state.lastRefresh;")
    assert last["tiles"] == 2  # both known tiles are visible and refreshed ...
    _, again = settled()
    assert again == received  # ... but nothing changed, so nothing was sent
    stack.client.publish_ism("ism/r1/laser/obstacle", np.full((20, 20), 0.9, np.float32),
                             resolution=RES, origin=Pose2D(14.0, 1.0))
    wait_pixel(browser, 14.5, 1.5, grey(sigmoid(logit(0.2) + logit(0.9))))
    _, after = settled()
    assert after == received + 1  # only the changed tile


@needs_browser
def test_a_tile_event_appears_in_the_page(stack: Stack, browser: Any) -> None:
    stack.client.publish_pose("r7", 3.0, 3.0)
    stack.client.publish_pose("r7", 20.0, 3.0)  # 7.2 m into tile (1, 0): past the hysteresis
    item = '#events li[data-robot="r7"][data-i="1"][data-j="0"]'
    wait_for(browser, lambda d: d.find_elements("css selector", item),
             what="the tile event never appeared")
    assert "r7 → tile (1, 0)" in browser.find_element("css selector", item).text
    events = js(browser, "return window.sogmViewer.state.events.filter(e => e.robot === 'r7')")
    assert [(e["i"], e["j"]) for e in events][-2:] == [(0, 0), (1, 0)]


@needs_browser
def test_cursor_shows_map_coordinates_and_each_layers_probability(stack: Stack,
                                                                   browser: Any) -> None:
    from selenium.webdriver.common.action_chains import ActionChains

    js(browser, "window.sogmViewer.setView(3.0, 2.0, 40.0);")
    target = (1.525, 2.025)
    sx, sy = js(browser, "return window.sogmViewer.worldToScreen(arguments[0], arguments[1]);",
                *target)
    overlay = browser.find_element("id", "overlay")
    size = overlay.size
    ActionChains(browser).move_to_element_with_offset(
        overlay, round(sx - size["width"] / 2), round(sy - size["height"] / 2)).perform()
    wait_for(browser, lambda d: "x 1.5" in d.find_element("id", "cursor-xy").text,
             what="no cursor coordinates")
    assert "(map)" in browser.find_element("id", "cursor-xy").text
    wait_for(browser, lambda d: js(d, "const p = window.sogmViewer.state.probe; "
             "return p && Math.abs(p.x - 1.525) < 0.05 && p.values.length === 2;"),
             what="no probe answer for the cursor: " + json.dumps(js(browser,
                 "return [window.sogmViewer.state.probe, window.sogmViewer.state.socket]")))
    values = {v["layer"]: v for v in js(browser, "return window.sogmViewer.state.probe.values")}
    assert values[OBSTACLE]["known"] and values[OBSTACLE]["p"] == pytest.approx(0.9, abs=2e-3)
    assert not values[CHAIR]["known"]  # the chair ISM never covered x = 1.5
    text = browser.find_element("id", "cursor-p").text
    assert OBSTACLE in text and "0.900" in text and "unknown" in text


@needs_browser
def test_supercell_graph_overlay_on_request(stack: Stack, browser: Any) -> None:
    js(browser, "window.sogmViewer.setView(3.0, 2.0, 40.0);")
    assert js(browser, "return window.sogmViewer.state.supercells;") is None
    browser.find_element("id", "show-supercells").click()
    wait_for(browser, lambda d: js(d, "const s = window.sogmViewer.state.supercells; "
             "return s !== null && (s.error !== null || s.nodes.length > 0);"), timeout=60,
             what="no supercell graph")
    sc = js(browser, "return window.sogmViewer.state.supercells;")
    assert sc["error"] is None and len(sc["nodes"]) > 1 and sc["edges"]
    # the obstacle's occupied half holds a node of class 0 (the obstacle layer)
    assert any(n["cls"] == 0 and 1.0 <= n["x"] <= 3.0 and 1.0 <= n["y"] <= 3.0
               for n in sc["nodes"])
    browser.find_element("id", "show-supercells").click()


@needs_browser
def test_the_page_keeps_working_when_the_map_server_restarts(
        stack: Stack, browser: Any, console: list[dict[str, Any]]) -> None:
    js(browser, "window.sogmViewer.setView(3.0, 2.0, 40.0);")
    js(browser, f"window.sogmViewer.setMode('layer', {{layer: '{OBSTACLE}'}});")
    wait_pixel(browser, 4.525, 2.025, grey(0.1))
    status = lambda d: d.find_element("id", "status").get_attribute("data-state")  # noqa: E731
    stack.server.proc.kill()
    stack.server.proc.wait(10)
    wait_for(browser, lambda d: status(d) == "map-down", what="the page never saw the loss")
    assert not browser.find_element("id", "banner").get_attribute("hidden")
    assert near(pixel(browser, 4.525, 2.025), grey(0.1))  # the last picture stays
    stack.server = start_server(stack.tmp, endpoint=stack.server.endpoint, name="server2")
    wait_for(browser, lambda d: status(d) == "connected", timeout=40,
             what=f"the viewer never reconnected:\n{stack.viewer_output()}")
    # the new server's map is empty: the old picture goes ...
    wait_pixel(browser, 4.525, 2.025, tuple(int(c, 16) for c in ("26", "2a", "30")))  # type: ignore[arg-type]
    # ... and what is published to it now shows (inverted pattern: free where it was occupied)
    with MapClient.connect(stack.endpoint, timeout=5.0) as client:
        publish_pattern(client, occupied=0.1, free=0.9)
        wait_pixel(browser, 1.525, 2.025, grey(0.1))
        wait_pixel(browser, 4.525, 2.025, grey(0.9))
        client.publish_pose("r1", 1.0, 1.0, 0.0)
        wait_for(browser, lambda d: (js(d, "return window.sogmViewer.state.markers.r1") or {})
                 .get("x") == 1.0, what="no poses after the restart")
    assert read_console(browser, console) == []
    assert stack.viewer.poll() is None  # the viewer process itself never went down


INTEL = Path(__file__).resolve().parents[2] / "sogm_service" / "data" / "intel-corrected.log.gz"


def _rounds_after(browser: Any, n: int) -> list[dict[str, Any]]:
    rounds: list[dict[str, Any]] = js(browser, "return window.sogmViewer.state.rounds;")
    return [r for r in rounds if r["n"] > n]


def _submaps(client: MapClient) -> int:
    return client.stats().counters.get("queries_submap", 0)


@needs_browser
def test_the_intel_replay_shows_whole_in_the_first_round_and_idle_costs_no_submap(
        stack: Stack, browser: Any) -> None:
    """The whole Intel log (910 scans) replayed into the (restarted) server; a fresh page.
    Every visible display tile is drawn by the first round at its view (a count, not a
    speed: the seconds are printed), and rounds over an unchanged map ask no sub-map."""
    import time

    replay = subprocess.run(
        [sys.executable, "-m", "sogm_service", "replay", "carmen", str(INTEL), "--connect",
         stack.endpoint, "--png", str(stack.tmp / "intel.png")],
        capture_output=True, timeout=120, check=False)
    assert replay.returncode == 0, replay.stdout.decode(errors="replace")[-2000:]
    with MapClient.connect(stack.endpoint, timeout=5.0) as client:
        assert wait_until(lambda: len(client.info().tiles) >= 10, 20)
        fused: list[int] = []
        assert wait_until(lambda: fused.append(client.stats().counters.get("isms_fused", 0))
                          or (len(fused) > 3 and fused[-1] == fused[-4]), 30, interval=0.3)
        t0 = time.monotonic()
        browser.get(stack.url)  # a new page: nothing sent to it yet
        wait_for(browser, lambda d: js(d, "return window.sogmViewer.state.info !== null && "
                 "window.sogmViewer.state.info.tile_count") >= 10, what="no info")
        # the whole map at one cell a screen pixel (level 0): all ten lattice tiles visible
        n0 = js(browser, "window.sogmViewer.setView(0.0, -6.4, 20.0); "
                "return window.sogmViewer.state.refreshes;")
        first: list[dict[str, Any]] = []

        def first_round(d: Any) -> bool:
            first[:] = [r for r in _rounds_after(d, n0) if r["level"] == 0
                        and r["signature"] == "class" and r["tiles"] >= 10][:1]
            return bool(first)

        wait_for(browser, first_round, what="no round at level 0 over the whole map")
        tiles = first[0]["tiles"]
        # By the end of the first round at this view the page holds every visible tile: sent
        # in that round, or already by a round of the page's opening view when that was at
        # level 0 too (a tile that view sent may come again with the new view).
        level0 = [r for r in _rounds_after(browser, -1) if r["level"] == 0
                  and r["signature"] == "class" and r["n"] <= first[0]["n"]]
        assert first[0]["checked"] and sum(r["sent"] for r in level0) >= tiles, level0
        wait_for(browser, lambda d: js(d, "return window.sogmViewer.state.tilesReceived;")
                 >= tiles, what="the first round's tiles were not all drawn")
        print(f"\nIntel replay: {tiles} display tiles drawn {time.monotonic() - t0:.2f} s "
              f"after the page opened (load {os.getloadavg()[0]:.2f})")
        # an unchanged map: rounds go on, each with one tiles/changed check, and no sub-map
        # (the pointer off the map first: a cursor over it asks probes, sub-maps of one cell)
        from selenium.webdriver.common.action_chains import ActionChains

        ActionChains(browser).move_to_element(browser.find_element("id", "legend")).perform()
        time.sleep(0.5)  # a probe already asked lands before the count starts
        before, state0 = _submaps(client), stack.state()
        n1 = js(browser, "return window.sogmViewer.state.refreshes;")
        wait_for(browser, lambda d: len(_rounds_after(d, n1)) >= 5, what="rounds stopped")
        state1 = stack.state()
        assert _submaps(client) == before, (state0, state1)
        assert state1["checks"] > state0["checks"] and state1["queries"] == state0["queries"]
        # one ISM inside one lattice tile: that display tile alone is asked and sent again
        received = js(browser, "return window.sogmViewer.state.tilesReceived;")
        client.publish_ism("ism/carmen/laser/obstacle", np.full((20, 20), 0.95, np.float32),
                           resolution=0.05, origin=Pose2D(5.0, 5.0), robot="carmen")
        wait_for(browser, lambda d: js(d, "return window.sogmViewer.state.tilesReceived;")
                 > received, what="the changed tile never came")
        n2 = js(browser, "return window.sogmViewer.state.refreshes;")
        wait_for(browser, lambda d: len(_rounds_after(d, n2)) >= 3, what="rounds stopped")
        assert _submaps(client) - before == 1, (state1, stack.state())
        assert js(browser, "return window.sogmViewer.state.tilesReceived;") == received + 1
