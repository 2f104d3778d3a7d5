"""A minimal headless-Chromium driver over the DevTools protocol on a pipe (stdlib only).

Chromium started with ``--remote-debugging-pipe`` reads DevTools (CDP) commands from file
descriptor 3 and writes replies and events to descriptor 4, each a JSON message ended by a
NUL byte: no websocket library, no driver binary, nothing from the network. Used by
tests/test_report_browser.py; also a command for a person:

    python tests/_chromium.py report.html shot.png [width]

prints what the page measured (scroll width, images, console errors) and writes a
full-page screenshot.
"""

from __future__ import annotations

import base64
import fcntl
import json
import os
import select
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CANDIDATES = ("/usr/bin/chromium", "chromium", "chromium-browser", "google-chrome")
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-quic",
         "--disable-extensions", "--hide-scrollbars", "--remote-debugging-pipe")
MAX_SHOT_HEIGHT = 16000  # px: Chromium refuses larger captures


def find_chromium() -> str | None:
    for c in CANDIDATES:
        p = shutil.which(c) or (c if Path(c).is_file() else None)
        if p:
            return p
    return None


class Chromium:
    """``with Chromium() as b: b.open(url, width)`` then `measure` / `screenshot`."""

    def __init__(self, executable: str | None = None, timeout: float = 60.0):
        self.executable = executable or find_chromium()
        if self.executable is None:
            raise FileNotFoundError("chromium: not installed (apt-get install -y chromium)")
        self.timeout = timeout
        self._id = 0
        self._buf = b""
        self.events: list[dict] = []
        self.session: str | None = None

    def __enter__(self) -> Chromium:
        self._profile = tempfile.TemporaryDirectory(prefix="camo_sbi_chromium_")
        cmd_r, self._cmd_w = os.pipe()
        self._res_r, res_w = os.pipe()

        def child_fds():  # descriptors 3 and 4, as --remote-debugging-pipe expects
            a = fcntl.fcntl(cmd_r, fcntl.F_DUPFD, 10)
            b = fcntl.fcntl(res_w, fcntl.F_DUPFD, 10)
            os.dup2(a, 3)
            os.dup2(b, 4)

        self.proc = subprocess.Popen(
            [self.executable, *FLAGS, f"--user-data-dir={self._profile.name}", "about:blank"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
            preexec_fn=child_fds, pass_fds=(3, 4))  # fds are closed after preexec_fn, except 3 and 4
        os.close(cmd_r)
        os.close(res_w)
        return self

    def __exit__(self, *exc) -> None:
        try:
            if self.proc.poll() is None:
                try:
                    self.call("Browser.close", session=False, timeout=10)
                except Exception:  # noqa: BLE001 - closing anyway
                    pass
                try:
                    self.proc.wait(10)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait(10)
        finally:
            os.close(self._cmd_w)
            os.close(self._res_r)
            if self.proc.stderr:
                self.proc.stderr.close()
            self._profile.cleanup()

    # ------------------------------------------------------------------ protocol

    def _read_message(self, deadline: float) -> dict:
        while b"\0" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError("chromium: no DevTools reply in time")
            ready, _, _ = select.select([self._res_r], [], [], left)
            if ready:
                chunk = os.read(self._res_r, 1 << 20)
                if not chunk:
                    raise RuntimeError(f"chromium: exited (rc={self.proc.poll()})")
                self._buf += chunk
        raw, self._buf = self._buf.split(b"\0", 1)
        return json.loads(raw)

    def call(self, method: str, params: dict | None = None, *, session: bool = True,
             timeout: float | None = None) -> dict:
        self._id += 1
        msg = {"id": self._id, "method": method, "params": params or {}}
        if session and self.session:
            msg["sessionId"] = self.session
        os.write(self._cmd_w, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + (timeout or self.timeout)
        while True:
            m = self._read_message(deadline)
            if m.get("id") == self._id:
                if "error" in m:
                    raise RuntimeError(f"chromium: {method} failed: {m['error']}")
                return m.get("result", {})
            self.events.append(m)

    def wait_event(self, method: str, timeout: float | None = None) -> dict:
        deadline = time.monotonic() + (timeout or self.timeout)
        for i, e in enumerate(self.events):
            if e.get("method") == method:
                return self.events.pop(i)
        while True:
            m = self._read_message(deadline)
            if m.get("method") == method:
                return m
            self.events.append(m)

    # ------------------------------------------------------------------ page

    def open(self, url: str, width: int = 1400, height: int = 900) -> None:
        target = self.call("Target.createTarget", {"url": "about:blank"}, session=False)["targetId"]
        self.session = self.call("Target.attachToTarget", {"targetId": target, "flatten": True},
                                 session=False)["sessionId"]
        for domain in ("Page", "Runtime", "Log"):
            self.call(f"{domain}.enable")
        self.width = width
        self.call("Emulation.setDeviceMetricsOverride",
                  {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False})
        self.call("Page.navigate", {"url": url})
        self.wait_event("Page.loadEventFired")

    def evaluate(self, expression: str):
        r = self.call("Runtime.evaluate", {"expression": expression, "returnByValue": True, "awaitPromise": True})
        if "exceptionDetails" in r:
            raise RuntimeError(f"chromium: evaluate failed: {r['exceptionDetails']}")
        return r["result"].get("value")

    def measure(self) -> dict:
        """scrollWidth, innerWidth, scrollHeight, images [(src head, complete, naturalWidth)],
        the elements wider than the viewport, and console / page errors seen so far."""
        m = self.evaluate("""(async () => {
            await Promise.all([...document.images].map(i => i.decode().catch(() => null)));
            const wide = [...document.querySelectorAll('body *')]
                .filter(e => e.getBoundingClientRect().right > window.innerWidth + 1)
                .slice(0, 10).map(e => e.tagName + (e.id ? '#' + e.id : '') + ' ' +
                                      Math.round(e.getBoundingClientRect().right));
            return {scrollWidth: document.documentElement.scrollWidth, innerWidth: window.innerWidth,
                    scrollHeight: document.documentElement.scrollHeight, wide: wide,
                    images: [...document.images].map(i => [i.src.slice(0, 40), i.complete, i.naturalWidth])};
        })()""")
        errors = []
        for e in self.events:
            p = e.get("params", {})
            if e.get("method") == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
                errors.append(" ".join(str(a.get("value", a.get("description", ""))) for a in p.get("args", [])))
            elif e.get("method") == "Runtime.exceptionThrown":
                errors.append(p.get("exceptionDetails", {}).get("text", "exception"))
            elif e.get("method") == "Log.entryAdded" and p.get("entry", {}).get("level") == "error":
                errors.append(p["entry"].get("text", ""))
        m["console_errors"] = errors
        return m

    def screenshot(self, path, full_page: bool = True) -> Path:
        """A PNG of the page (the whole height, up to MAX_SHOT_HEIGHT px, when ``full_page``)."""
        params = {"format": "png"}
        if full_page:
            h = min(int(self.evaluate("document.documentElement.scrollHeight")), MAX_SHOT_HEIGHT)
            params.update({"captureBeyondViewport": True,
                           "clip": {"x": 0, "y": 0, "width": self.width, "height": h, "scale": 1}})
        data = base64.b64decode(self.call("Page.captureScreenshot", params, timeout=120)["data"])
        path = Path(path)
        path.write_bytes(data)
        return path


def main(argv: list[str]) -> int:
    if len(argv) < 2:
        print(__doc__)
        return 2
    width = int(argv[2]) if len(argv) > 2 else 1400
    with Chromium() as b:
        b.open(Path(argv[0]).resolve().as_uri(), width)
        print(json.dumps(b.measure(), indent=1))
        print(b.screenshot(argv[1]))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
