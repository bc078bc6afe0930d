"""`quasisim view RUN_DIR --web`: the viser viewer of a finished run, driven from headless Chromium over the
DevTools protocol (skipped without /usr/bin/chromium; without viser too, except under CI, where `make setup`
installs it). Every wait has a timeout."""

from __future__ import annotations

import base64
import io
import json
import re
import select
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

from helpers import CHROMIUM, UNDER_CI, ctrl_c_restored
from quasisim.cli import main

WAIT = 180.0  # s, the longest any one wait may take (a loaded CI machine renders WebGL in software slowly)


def _need_viser() -> None:
    try:
        import viser  # noqa: F401
    except ImportError:
        if UNDER_CI:
            pytest.fail("CI needs viser (make setup installs .[viewer])", pytrace=False)
        pytest.skip("viser not installed (pip install 'quasisim[viewer]')")


def _need_chromium() -> None:
    import os

    if not os.access(CHROMIUM, os.X_OK):
        pytest.skip(f"{CHROMIUM} not found (apt-get install chromium to check the web viewer in a browser)")


def _wait(what: str, done: Callable[[], Any], timeout: float = WAIT, every: float = 0.1) -> Any:
    """Poll ``done`` until it returns something truthy (returned); fail naming ``what`` after ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        got = done()
        if got:
            return got
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(every)


def _cli(args: list[str]) -> Any:
    return CliRunner().invoke(main, args)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished run of the synthetic cube lift (20 frames, kinematic, judged in MuJoCo), its demo beside it."""
    d = tmp_path_factory.mktemp("web_view")
    for args in (
        ["example", "--out", str(d), "--name", "cube_lift", "--frames", "20"],
        ["transfer", str(d / "cube_lift.npz"), "--hand", "shadow", "--method", "kinematic", "--target", "mujoco",
         "--no-render", "--out", str(d / "run")],
    ):  # fmt: skip
        r = _cli(args)
        assert r.exit_code == 0, r.output
    return d / "run"


# ---- without a browser -------------------------------------------------------------------------


def test_without_viser_says_how_to_install(run_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "viser", None)  # `import viser` raises ImportError
    r = _cli(["view", str(run_dir), "--web"])
    assert r.exit_code == 2 and r.stderr.splitlines() == [
        "error: the web viewer needs viser, which is not installed: pip install 'quasisim[viewer]'"
    ]


def _one_line_error(args: list[str]) -> str:
    r = _cli(args)
    lines = r.stderr.splitlines()
    assert r.exit_code == 2 and len(lines) == 1 and lines[0].startswith("error: "), (r.exit_code, r.output)
    return lines[0]


def test_bad_input_is_one_line(run_dir: Path, tmp_path: Path) -> None:
    _need_viser()
    missing = tmp_path / "nothing"
    assert f"{missing}: expected a finished run folder" in _one_line_error(["view", str(missing), "--web"])
    # a folder without the run's files (the example's folder holds the demo, not a run)
    assert "scene.xml of a finished run folder" in _one_line_error(["view", str(run_dir.parent), "--web"])
    # a run whose files changed after its manifest was written: unfinished (interrupted, or still running)
    copy = tmp_path / "copy"
    shutil.copytree(run_dir, copy)
    (copy / "trajectory.npz").write_bytes((copy / "trajectory.npz").read_bytes() + b"\0")
    assert "manifest.json: expected the file list of a finished run" in _one_line_error(["view", str(copy), "--web"])
    with socket.socket() as s:  # a port something else listens on
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        err = _one_line_error(["view", str(run_dir), "--web", "--port", str(port)])
    assert f"127.0.0.1:{port}: option '--port': expected a free port" in err and "in use" in err
    assert "--port only with --web" in _one_line_error(["view", str(run_dir), "--port", "9000"])


def test_the_demo_is_found_by_its_recorded_name_and_hash(
    run_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from quasisim.errors import InputError
    from quasisim.eval.web_view import find_demo

    demo, note = find_demo(run_dir, None, 20)  # checkpoints/run.json: cube_lift; the file lies beside the run
    assert demo is not None and demo.n_frames == 20 and note == f"demo: {run_dir.parent / 'cube_lift.npz'}"
    monkeypatch.setenv("QUASISIM_DATA", str(tmp_path / "no-data"))
    alone = tmp_path / "elsewhere" / "run"
    shutil.copytree(run_dir, alone)
    other = _cli(["example", "--out", str(alone.parent), "--name", "cube_lift", "--frames", "12"])
    assert other.exit_code == 0, other.output  # a cube_lift.npz beside it, but not the run's (another hash)
    assert find_demo(alone, None, 20) == (None, (
        "demo: cube_lift.npz not found beside the run or in $QUASISIM_DATA (pass --demo DEMO.npz to show it)"
    ))  # fmt: skip
    with pytest.raises(InputError, match=r"field 'right_joints': expected the run's 20 frames, got 12 frames"):
        find_demo(alone, alone.parent / "cube_lift.npz", 20)  # --demo of another length
    (alone / "checkpoints" / "run.json").unlink()  # as in a `quasisim batch` clip's folder: controls.npz's hash
    data = tmp_path / "data"
    shutil.copytree(run_dir.parent, data)  # the run's demo (with its mesh, for the content hash) in $QUASISIM_DATA
    monkeypatch.setenv("QUASISIM_DATA", str(data))
    assert find_demo(alone, None, 20)[1] == f"demo: {data / 'cube_lift.npz'}"
    (alone / "controls.npz").unlink()  # as in a folder written by `quasisim evaluate`
    assert find_demo(alone, None, 20)[1] == "demo: not recorded in the run folder (pass --demo DEMO.npz to show it)"
    assert find_demo(alone, run_dir.parent / "cube_lift.npz", 20)[0] is not None  # --demo


def _line(stream: Any, timeout: float) -> str:
    """One line from a subprocess pipe, or "" after ``timeout`` s."""
    if not select.select([stream], [], [], timeout)[0]:
        return ""
    return stream.readline()


def test_cli_prints_the_url_and_serves_until_ctrl_c(run_dir: Path) -> None:
    _need_viser()
    cmd = [sys.executable, "-m", "quasisim.cli", "view", str(run_dir), "--web", "--port", "0"]
    p = subprocess.Popen(ctrl_c_restored(cmd), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        url = _line(p.stdout, WAIT).strip()
        assert re.fullmatch(r"http://127\.0\.0\.1:\d+", url), (url, p.poll())
        hint = _line(p.stderr, WAIT)
        port = url.rsplit(":", 1)[1]
        assert f"ssh -L {port}:localhost:{port}" in hint and "demo: " in hint
        with urllib.request.urlopen(url, timeout=WAIT) as page:  # viser's client, served by the command
            assert page.status == 200 and b"<html" in page.read(4096)
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=WAIT)
        assert p.returncode == 0 and out == "" and "Traceback" not in err, (p.returncode, out, err)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(timeout=10)


def test_frames_pose_the_scene(run_dir: Path) -> None:
    """Server side: the model's geoms are in the scene; a frame moves the hand and steps clip at the ends."""
    _need_viser()
    from quasisim.eval.web_view import WebView

    view = WebView(run_dir, "127.0.0.1", 0)
    try:
        assert view.n_frames == 20 and len(view.mesh_nodes) >= 20  # the hand's links, the object, table, floor
        assert all(view.server.scene.get_handle_by_name(n) is not None for n in view.mesh_nodes)
        assert view.demo is not None and view.demo_note == f"demo: {run_dir.parent / 'cube_lift.npz'}"
        assert all(len(c) for c in view.frames.contacts[:3])  # the cube rests on the table
        palm = min(view.bodies)
        start = np.array(view.bodies[palm].position)
        view.set_frame(19)
        assert view.frame == 19 and view.slider.value == 19
        assert np.linalg.norm(np.array(view.bodies[palm].position) - start) > 0.02
        view.step(1)
        assert view.frame == 19
        view.step(-1)
        assert view.frame == 18 and "frame 18 / 19" in view.readout.content
    finally:
        view.stop()


# ---- in headless Chromium ----------------------------------------------------------------------


class Chromium:
    """Headless Chromium (WebGL in software, SwiftShader) driven over the DevTools protocol."""

    def __init__(self, profile: Path, width: int = 800, height: int = 500) -> None:
        from websockets.sync.client import connect

        cmd = [
            CHROMIUM, "--headless", "--no-sandbox", "--no-first-run", "--mute-audio", "--hide-scrollbars",
            "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
            f"--window-size={width},{height}", "--remote-debugging-port=0", f"--user-data-dir={profile}",
            "about:blank",
        ]  # fmt: skip
        self.proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        self.ws: Any = None
        deadline, port = time.monotonic() + WAIT, None
        while port is None:
            line = _line(self.proc.stderr, max(deadline - time.monotonic(), 0.0))
            if not line:
                self.close()
                pytest.fail("Chromium did not start its DevTools server")
            m = re.search(r"DevTools listening on ws://[^/]+:(\d+)/", line)
            port = m and int(m[1])
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=WAIT) as r:
            page = next(t for t in json.load(r) if t["type"] == "page")
        self.ws = connect(page["webSocketDebuggerUrl"], max_size=None, open_timeout=WAIT)
        self.calls = 0

    def call(self, method: str, **params: Any) -> dict:
        self.calls += 1
        self.ws.send(json.dumps({"id": self.calls, "method": method, "params": params}))
        deadline = time.monotonic() + WAIT
        while True:  # skip events until the answer
            msg = json.loads(self.ws.recv(timeout=max(deadline - time.monotonic(), 0.01)))
            if msg.get("id") == self.calls:
                assert "error" not in msg, (method, msg["error"])
                return msg["result"]

    def js(self, expression: str) -> Any:
        r = self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        assert "exceptionDetails" not in r, r["exceptionDetails"]
        return r["result"].get("value")

    def text(self) -> str:
        return self.js("document.body ? document.body.innerText : ''") or ""

    def key(self, key: str, code: int) -> None:
        """Press and release ``key`` (a real key event, into whatever has the focus)."""
        for kind in ("keyDown", "keyUp"):
            self.call("Input.dispatchKeyEvent", type=kind, key=key, code=key, windowsVirtualKeyCode=code)

    def click_button(self, label: str) -> None:
        assert self.js(
            f"(() => {{ const b = [...document.querySelectorAll('button')].find(b => b.innerText.trim() === {label!r});"
            " if (b) b.click(); return !!b; })()"
        ), f"no button {label!r} on the page"

    def tick(self, label: str) -> None:
        """Click the checkbox labelled ``label``."""
        assert self.js(
            f"(() => {{ let e = [...document.querySelectorAll('*')].find(e => e.children.length === 0 && "
            f"e.textContent.trim() === {label!r});"
            " while (e && !e.querySelector('input[type=checkbox]')) e = e.parentElement;"
            " if (e) e.querySelector('input[type=checkbox]').click(); return !!e; })()"
        ), f"no checkbox {label!r} on the page"

    def screenshot(self) -> np.ndarray:
        from PIL import Image

        png = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))

    def close(self) -> None:
        if self.ws is not None:
            self.ws.close()
        self.proc.terminate()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=10)


@pytest.fixture(scope="module")
def browsing(run_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Any, Chromium]]:
    """The viewer of ``run_dir`` on a free port and Chromium showing it (its GUI synced: the readout shown)."""
    _need_viser()
    _need_chromium()
    from quasisim.eval.web_view import WebView

    view = WebView(run_dir, "127.0.0.1", 0)
    browser = None
    try:
        browser = Chromium(tmp_path_factory.mktemp("chromium-profile"))
        browser.call("Page.navigate", url=view.url)
        _wait("the page to connect to the viewer", lambda: view.server.get_clients())
        _wait("the viewer's panel on the page", lambda: "frame 0 / 19" in browser.text())
        browser.tick("Fast rendering")  # WebGL in software: 1-2 frames a second with shadows and environment light
        _wait("fast rendering on the server", lambda: view.fast.value)
        yield view, browser
    finally:
        if browser is not None:
            browser.close()
        view.stop()


def test_the_page_drives_the_frames(browsing) -> None:
    """The page shows the run's panel; its slider (keyboard) and buttons (clicks) move the frame on the server,
    which poses the hand, and the page shows the new frame."""
    view, browser = browsing
    text = browser.text()
    for words in ("20 frames at 20 fps", "Play", "Pause", "Previous frame", "Next frame", "Contacts", "demo: "):
        assert words in text
    assert browser.js("document.querySelectorAll('canvas').length") >= 1
    palm = min(view.bodies)
    start = np.array(view.bodies[palm].position)
    browser.js("document.querySelector('[role=slider]').focus()")
    browser.key("End", 35)  # the slider to its last frame, as a user's keyboard does
    _wait("the slider's frame on the server", lambda: view.frame == 19)
    assert np.linalg.norm(np.array(view.bodies[palm].position) - start) > 0.02
    _wait("the page's readout of frame 19", lambda: "frame 19 / 19" in browser.text())
    browser.click_button("Previous frame")
    _wait("a step back", lambda: view.frame == 18)
    _wait("the slider on the page at 18", lambda: browser.js("document.querySelector('[role=slider]')"
                                                             ".getAttribute('aria-valuenow')") == "18")  # fmt: skip
    browser.click_button("Play")
    _wait("playing on", lambda: view.playing and view.frame not in (18, 19))
    browser.click_button("Pause")
    _wait("a pause", lambda: not view.playing)
    paused = view.frame
    time.sleep(0.5)
    assert view.frame == paused


def _stable_screenshot(browser: Chromium) -> np.ndarray:
    """A screenshot equal to the one before it (every mesh arrived and drawn)."""
    shots = [browser.screenshot()]

    def settled() -> bool:
        shots.append(browser.screenshot())
        return np.array_equal(shots[-1], shots[-2])

    _wait("the 3D view to settle", settled, timeout=3 * WAIT, every=0.5)
    return shots[-1]


def test_the_scene_renders_and_moves(browsing) -> None:
    """Screenshots (WebGL in software): the 3D view is not empty and a frame later the hand is elsewhere."""
    view, browser = browsing
    layers = ("Contacts", "Robot keypoints", "Demo (keypoints, object)")
    for label in layers:  # the hand, the object, table and floor alone
        browser.tick(label)
        _wait(f"{label} hidden on the server", lambda label=label: not view.toggles[label].value)
    view.set_frame(0)
    _wait("the page's readout of frame 0", lambda: "frame 0 / 19" in browser.text())
    first = _stable_screenshot(browser)
    left = slice(0, int(0.55 * first.shape[1]))  # the 3D view beside the panel (the panel shows the frame too)
    assert len(np.unique(first[:, left].reshape(-1, 3), axis=0)) > 50
    browser.js("document.querySelector('[role=slider]').focus()")
    browser.key("End", 35)
    _wait("the page's readout of frame 19", lambda: "frame 19 / 19" in browser.text())
    last = _stable_screenshot(browser)
    moved = np.abs(last[:, left].astype(int) - first[:, left].astype(int)).sum(axis=-1) > 30
    assert moved.sum() > 500, moved.sum()
    for label in layers:
        browser.tick(label)
        _wait(f"{label} shown again", lambda label=label: view.toggles[label].value)
