"""A headless Chromium driven over the DevTools protocol (websockets, a dependency of viser): open a page,
take screenshots until a condition holds. Software WebGL (SwiftShader) so it runs without a GPU."""
from __future__ import annotations

import base64
import itertools
import json
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--hide-scrollbars", "--mute-audio",
         "--remote-debugging-port=0", "--remote-allow-origins=*"]


def find_chromium():
    for n in CHROMIUM_NAMES:
        p = shutil.which(n)
        if p:
            return p
    return None


class Chromium:
    def __init__(self, url, width=800, height=600, start_timeout=30.0):
        """Opens ``url`` (given at launch: a navigation from about:blank swaps the page's process)."""
        from websockets.sync.client import connect

        exe = find_chromium()
        if exe is None:
            raise RuntimeError("no chromium on PATH")
        self._tmp = tempfile.mkdtemp(prefix="tlvg_chromium_")
        self.proc = subprocess.Popen([exe, *FLAGS, f"--user-data-dir={self._tmp}", f"--window-size={width},{height}",
                                      url], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        port_file = Path(self._tmp) / "DevToolsActivePort"
        t0 = time.monotonic()
        while not (port_file.is_file() and port_file.read_text().strip()):
            if self.proc.poll() is not None or time.monotonic() - t0 > start_timeout:
                self.close()
                raise RuntimeError("chromium did not start")
            time.sleep(0.1)
        port = int(port_file.read_text().split()[0])
        ws_url = None
        while ws_url is None and time.monotonic() - t0 < start_timeout:
            try:
                pages = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=5).read())
                ws_url = next((p["webSocketDebuggerUrl"] for p in pages if p.get("type") == "page"), None)
            except OSError:
                pass
            if ws_url is None:
                time.sleep(0.1)
        if ws_url is None:
            self.close()
            raise RuntimeError("chromium has no page to drive")
        self.ws = connect(ws_url, max_size=64 << 20, open_timeout=start_timeout)
        self._ids = itertools.count(1)
        self.width, self.height = width, height
        self.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False)

    def call(self, method, timeout=30.0, **params):
        i = next(self._ids)
        self.ws.send(json.dumps({"id": i, "method": method, "params": params}))
        t0 = time.monotonic()
        while True:
            msg = json.loads(self.ws.recv(timeout=max(0.1, timeout - (time.monotonic() - t0))))
            if msg.get("id") == i:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})

    def eval(self, js):
        return self.call("Runtime.evaluate", expression=js, returnByValue=True).get("result", {}).get("value")

    def screenshot(self) -> np.ndarray:
        """The page as uint8 RGB [H, W, 3]."""
        import cv2

        data = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        return img[:, :, ::-1].copy()

    def wait_for(self, predicate, timeout=30.0, interval=0.5, settle=1.0):
        """Screenshots until predicate(img) holds on a settled page (mean absolute change from the previous
        screenshot below ``settle`` grey levels: viser fades splats in); returns (last image, whether it held)."""
        t0 = time.monotonic()
        prev = None
        while True:
            img = self.screenshot()
            still = prev is not None and prev.shape == img.shape and \
                np.abs(img.astype(np.int16) - prev.astype(np.int16)).mean() < settle
            if still and predicate(img):
                return img, True
            if time.monotonic() - t0 > timeout:
                return img, False
            prev = img
            time.sleep(interval)

    def close(self):
        ws = getattr(self, "ws", None)
        if ws is not None:
            try:
                ws.close()
            except Exception:  # noqa: BLE001
                pass
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        shutil.rmtree(self._tmp, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
