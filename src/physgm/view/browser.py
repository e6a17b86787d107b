"""A headless Chromium driven over the DevTools protocol: open the viewer, take screenshots.

Used by ``python -m physgm.view RUN_DIR --screenshot out.png`` and by the browser test. The
protocol is spoken over a websocket with the ``websockets`` package that viser already depends
on, so no browser driver package is needed; Chromium itself comes from the system (Debian:
``apt-get install chromium``). ``chromium --headless --screenshot`` alone would not do: it
captures when the page has loaded, before the scene has arrived over viser's websocket.
"""

from __future__ import annotations

import base64
import io
import json
import os
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np

# The brief's flags for a quiet, reproducible headless Chromium (no network besides localhost, no
# first-run UI). WebGL has no GPU here: Chromium draws it with SwiftShader, which it now does only
# when asked (--enable-unsafe-swiftshader; the viewer is a trusted local page).
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--enable-unsafe-swiftshader",
    "--hide-scrollbars",
    "--mute-audio",
)
CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def find_chromium() -> str | None:
    """Path of a Chromium executable ($PHYSGM_CHROMIUM first), or None."""
    env = os.environ.get("PHYSGM_CHROMIUM")
    if env:
        return env if shutil.which(env) else None
    for name in CHROMIUM_NAMES:
        path = shutil.which(name)
        if path:
            return path
    return None


class HeadlessBrowser:
    """One headless Chromium page of ``width`` x ``height`` CSS pixels; use as a context manager."""

    def __init__(
        self, width: int = 800, height: int = 600, executable: str | None = None, timeout: float = 30.0
    ) -> None:
        exe = executable or find_chromium()
        if exe is None:
            raise FileNotFoundError(
                "no Chromium found (tried $PHYSGM_CHROMIUM, " + ", ".join(CHROMIUM_NAMES) + "); "
                "install it, e.g. apt-get install chromium"
            )
        self.width, self.height, self.timeout = width, height, timeout
        self.profile = Path(tempfile.mkdtemp(prefix="physgm-chromium-"))
        self._log = open(self.profile / "chromium.log", "wb")  # noqa: SIM115 (closed in close())
        self.proc = subprocess.Popen(
            [
                exe,
                *CHROMIUM_FLAGS,
                f"--user-data-dir={self.profile}",
                f"--window-size={width},{height}",
                "--remote-debugging-address=127.0.0.1",
                "--remote-debugging-port=0",
                "about:blank",
            ],
            stdin=subprocess.DEVNULL,
            stdout=self._log,
            stderr=subprocess.STDOUT,
        )
        self._ws = None
        self._next_id = 0
        try:
            self._connect()
        except BaseException:
            self.close()
            raise

    def _connect(self) -> None:
        from websockets.sync.client import connect

        port_file = self.profile / "DevToolsActivePort"  # Chromium writes its debugging port here
        deadline = time.monotonic() + self.timeout
        while not port_file.is_file() or not port_file.read_text().strip():
            if self.proc.poll() is not None:
                raise RuntimeError(
                    f"Chromium exited with code {self.proc.returncode}; see {self.profile / 'chromium.log'}"
                )
            if time.monotonic() > deadline:
                raise TimeoutError(f"Chromium did not open its debugging port within {self.timeout:g} s")
            time.sleep(0.05)
        port = int(port_file.read_text().split()[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=self.timeout) as resp:
            targets = json.load(resp)
        page = next(t for t in targets if t.get("type") == "page")
        self._ws = connect(page["webSocketDebuggerUrl"], max_size=None, open_timeout=self.timeout)
        self.call(
            "Emulation.setDeviceMetricsOverride",
            width=self.width,
            height=self.height,
            deviceScaleFactor=1,
            mobile=False,
        )

    def call(self, method: str, **params) -> dict:
        """One DevTools command; returns its result (events in between are skipped)."""
        self._next_id += 1
        self._ws.send(json.dumps({"id": self._next_id, "method": method, "params": params}))
        deadline = time.monotonic() + self.timeout
        while True:
            msg = json.loads(self._ws.recv(timeout=max(0.1, deadline - time.monotonic())))
            if msg.get("id") == self._next_id:
                if "error" in msg:
                    raise RuntimeError(f"Chromium refused {method}: {msg['error']}")
                return msg.get("result", {})

    def open(self, url: str) -> None:
        self.call("Page.navigate", url=url)

    def screenshot(self) -> np.ndarray:  # [H, W, 3] uint8
        """What the page shows now."""
        from PIL import Image

        data = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))

    def close(self) -> None:
        if self._ws is not None:
            self._ws.close()
            self._ws = None
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()
        shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self) -> HeadlessBrowser:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def wait_until_still(
    browser: HeadlessBrowser, settle: float = 0.5, repeats: int = 3, timeout: float = 90.0
) -> np.ndarray:
    """The first screenshot equal to the ``repeats`` taken before it, ``settle`` s apart (notices closed).

    Call it once the scene has reached the page. The page fades the scene in, and a loaded
    machine may not draw a new frame between two screenshots: one repeat is not enough.
    """
    deadline = time.monotonic() + timeout
    previous, same = None, 0
    while time.monotonic() < deadline:
        dismiss_notifications(browser)
        shot = browser.screenshot()
        same = same + 1 if previous is not None and np.array_equal(shot, previous) else 0
        if same >= repeats:
            return shot
        previous = shot
        time.sleep(settle)
    raise TimeoutError(f"the page did not settle within {timeout:g} s")


def dismiss_notifications(browser: HeadlessBrowser) -> int:
    """Close viser's pop-up notices (e.g. "Software WebGL rendering detected"); returns how many."""
    script = (
        "(() => { const b = document.querySelectorAll('.mantine-Notification-closeButton');"
        " b.forEach(x => x.click()); return b.length; })()"
    )
    return int(
        browser.call("Runtime.evaluate", expression=script, returnByValue=True)["result"].get("value", 0)
    )
