"""The appearance panel in a real browser: `ns-viewer` on a small trained checkpoint (127.0.0.1), driven by headless
Chromium through the Chrome DevTools protocol (a websocket; the `websockets` client ships with viser).

Checks that the panel's elements exist (their labels in the DOM) and that choosing another appearance changes the
rendered pixels (screenshots of the render area), and shows a training view's transient mask / teacher render.
The last screenshot is written to tmp (and to docs/viewer_panel.png when that file is missing or
WILLAGS_UPDATE_SCREENSHOTS=1). Needs Debian's `chromium` (`make test` installs it when missing and root is
available); otherwise skips saying why.
"""

import base64
import io
import json
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

pytestmark = [pytest.mark.slow, pytest.mark.browser, pytest.mark.timing]

REPO = Path(__file__).resolve().parents[1]
SCREENSHOT = REPO / "docs" / "viewer_panel.png"
LABELS = [
    "Appearance A",
    "Appearance B",
    "Search training images",
    "A -> B",
    "Photo path",
    "Use photo",
    "Random seed",
    "Random appearance",
    "Appearance spec",
    "Latent norm",
    "Show transient mask / teacher",
]
CHROMIUM_FLAGS = [
    "--headless=new",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--use-angle=swiftshader",  # WebGL (viser's three.js canvas) on the CPU
    "--enable-unsafe-swiftshader",
    "--window-size=1280,1000",
    "--remote-debugging-address=127.0.0.1",
    "--remote-debugging-port=0",
]


def _chromium() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    pytest.skip("no chromium on PATH: install Debian's chromium (make test does when root: apt-get install chromium)")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


PATIENCE_S = 900.0
"""How long a wait may take before the test calls it a hang: each wait returns as soon as its condition holds, so
this only bounds a failure and never decides a pass on a slow machine."""


def _wait(pred, timeout: float, what: str, proc=None):
    t0 = time.time()
    while time.time() - t0 < timeout:
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"{what}: the process exited with {proc.returncode}")
        out = pred()
        if isinstance(out, np.ndarray) or out:
            return out
        time.sleep(0.5)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


class DevTools:
    """The few Chrome DevTools protocol calls the test needs, over one page's websocket."""

    def __init__(self, ws_url: str):
        from websockets.sync.client import connect

        self.ws = connect(ws_url, max_size=64 * 2**20, open_timeout=PATIENCE_S)
        self.next_id = 0

    def call(self, method: str, **params):
        self.next_id += 1
        self.ws.send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv(timeout=PATIENCE_S))
            if msg.get("id") == self.next_id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg["result"]

    def js(self, expression: str):
        res = self.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in res:
            raise RuntimeError(f"javascript failed: {res['exceptionDetails']}")
        return res["result"].get("value")

    def screenshot(self) -> np.ndarray:
        data = self.call("Page.captureScreenshot", format="png")["data"]
        return np.asarray(Image.open(io.BytesIO(base64.b64decode(data))).convert("RGB"))

    def close(self):
        self.ws.close()


# clicks the control whose label is `label`: the smallest element showing exactly that text, then the nearest
# ancestor holding a button / checkbox (viser lays a label and its input out in one row)
CLICK_JS = """
(label, selector) => {
  const els = [...document.querySelectorAll('body *')].filter(e => e.innerText && e.innerText.trim() === label);
  if (!els.length) return 'no element labelled ' + label;
  let e = els[els.length - 1];
  for (let i = 0; i < 6 && e; i++, e = e.parentElement) {
    if (e.matches(selector)) { e.click(); return 'ok'; }
    const c = e.querySelector(selector);
    if (c) { c.click(); return 'ok'; }
  }
  return 'no ' + selector + ' near ' + label;
}
"""

# types into the text input whose current value is `old` (React listens to the native input event)
TYPE_JS = """
(old, text) => {
  const inp = [...document.querySelectorAll('input')].find(i => i.value === old);
  if (!inp) return 'no input showing ' + old;
  const set = Object.getOwnPropertyDescriptor(HTMLInputElement.prototype, 'value').set;
  set.call(inp, text);
  inp.dispatchEvent(new Event('input', {bubbles: true}));
  inp.dispatchEvent(new Event('change', {bubbles: true}));
  inp.dispatchEvent(new Event('blur', {bubbles: true}));
  return 'ok';
}
"""


SCROLL_JS = """
(label) => {
  const els = [...document.querySelectorAll('body *')].filter(e => e.innerText && e.innerText.trim() === label);
  if (els.length) els[els.length - 1].scrollIntoView({block: 'start'});
}
"""


def _render_width(page_text: str) -> int:
    """Width of the viewer's last render, from its "Resolution: WxHpx" line (0 if absent)."""
    import re

    m = re.search(r"Resolution:\s*(\d+)\s*[x×]\s*(\d+)", page_text)
    return int(m.group(1)) if m else 0


def _render_area(img: np.ndarray) -> np.ndarray:
    """The left part of the page: the render (nerfstudio's control panel is on the right)."""
    h, w = img.shape[:2]
    return img[h // 8 : h * 7 // 8, w // 16 : w // 2].astype(np.float32)


def test_appearance_panel_in_chromium(appearance_run, tmp_path):
    chromium = _chromium()
    cfg, names, seen = appearance_run
    port = _free_port()
    viewer_cmd = [sys.executable, "-m", "nerfstudio.scripts.viewer.run_viewer", "--load-config", str(cfg)]
    viewer_cmd += ["--viewer.websocket-host", "127.0.0.1", "--viewer.websocket-port", str(port)]
    log = open(tmp_path / "viewer.log", "w")
    viewer = subprocess.Popen(viewer_cmd, stdout=log, stderr=subprocess.STDOUT)
    browser = None
    tools = None
    try:
        url = f"http://127.0.0.1:{port}/"

        def http_up():
            try:
                with urllib.request.urlopen(url, timeout=2) as r:
                    return r.status == 200
            except OSError:
                return False

        _wait(http_up, PATIENCE_S, "ns-viewer's HTTP server", viewer)
        profile = tmp_path / "chromium-profile"  # a fresh profile every run
        browser = subprocess.Popen(
            [chromium, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "about:blank"],
            stdout=subprocess.DEVNULL,
            stderr=open(tmp_path / "chromium.log", "w"),
        )
        port_file = profile / "DevToolsActivePort"
        _wait(
            lambda: port_file.exists() and port_file.read_text().strip(),
            PATIENCE_S,
            "chromium's DevTools port",
            browser,
        )
        cdp_port = int(port_file.read_text().split()[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{cdp_port}/json/list", timeout=PATIENCE_S) as r:
            pages = [p for p in json.loads(r.read()) if p.get("type") == "page"]
        tools = DevTools(pages[0]["webSocketDebuggerUrl"])
        tools.call("Page.enable")
        tools.call("Page.navigate", url=url)

        text = lambda: tools.js("document.body ? document.body.innerText : ''") or ""  # noqa: E731
        _wait(lambda: all(label in text() for label in LABELS), PATIENCE_S, "the appearance panel's labels")
        body = text()
        for label in LABELS:
            assert label in body, label

        def settled(previous: np.ndarray | None, min_change: float):
            """A screenshot once the render area stops changing (and differs from `previous` if given)."""
            last = [None]

            def check():
                shot = tools.screenshot()
                area = _render_area(shot)
                prev, last[0] = last[0], area
                if prev is None or np.abs(area - prev).mean() > 0.05 or area.std() < 2.0:
                    return None  # still rendering (or still blank)
                if previous is not None and np.abs(area - _render_area(previous)).mean() < min_change:
                    return None
                return shot

            return check

        first = _wait(settled(None, 0), PATIENCE_S, "the first render")
        assert tools.js(f"({CLICK_JS})('Random appearance', 'button')") == "ok"
        _wait(
            lambda: (
                "sample:1" in (tools.js("[...document.querySelectorAll('input')].map(i => i.value).join('|')") or "")
            ),
            PATIENCE_S,
            "the SPEC field to show sample:1",
        )
        second = _wait(settled(first, 1.0), PATIENCE_S, "the render under the random appearance")
        change = float(np.abs(_render_area(second) - _render_area(first)).mean())
        assert change > 1.0, f"the render did not change with the appearance (mean |diff| {change:.2f} levels)"

        # a training image's appearance typed as a SPEC, then its transient mask / teacher view
        name = names[seen[0]]
        assert tools.js(f"({TYPE_JS})('sample:1', {json.dumps('image:' + name)})") == "ok"
        third = _wait(settled(second, 1.0), PATIENCE_S, f"the render under image:{name}")
        assert tools.js(f"({CLICK_JS})('Show transient mask / teacher', 'input[type=checkbox]')") == "ok"
        has_img = "[...document.querySelectorAll('img')].some(i => i.src.startsWith('data:image/png'))"
        _wait(lambda: tools.js(has_img), PATIENCE_S, "the transient mask / teacher picture in the panel")
        assert "image | teacher | transient mask" in text()
        assert np.abs(_render_area(third) - _render_area(second)).mean() > 1.0
        # the picture for people: the panel scrolled into view, the render at full resolution
        tools.js(f"({SCROLL_JS})('Appearance A')")
        try:
            _wait(lambda: _render_width(text()) >= 200, 40, "the full-resolution render")
        except AssertionError:
            pass  # a slow machine: the picture shows the low-resolution render
        time.sleep(1.0)
        shot = tools.screenshot()
        Image.fromarray(shot).save(tmp_path / "viewer_panel.png")
        if not SCREENSHOT.exists() or os.environ.get("WILLAGS_UPDATE_SCREENSHOTS") == "1":
            Image.fromarray(shot).save(SCREENSHOT)
    finally:
        if tools is not None:
            tools.close()
        for proc in (browser, viewer):
            if proc is not None and proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    proc.kill()
        log.close()
