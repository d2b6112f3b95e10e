"""Headless Chromium on localhost: screenshots (the viewer's test, docs/viewer.png) and page texts.

Chromium is the Debian package (`apt-get install -y chromium`), driven over the DevTools protocol
(its websocket, with the `websockets` package viser already needs): load the page, wait in real
time until it shows a given text and its pixels stop changing, capture. (`chromium --screenshot`
alone is not enough: its virtual time does not wait for websocket traffic, so it can capture the
viewer before the scene has arrived.) WebGL runs on SwiftShader (CPU), and every host name but
localhost resolves to nothing, so a page that needed the network (a CDN script, a web font) shows
it.
"""

from __future__ import annotations

import base64
import contextlib
import itertools
import json
import os
import pathlib
import shutil
import signal
import subprocess
import tempfile
import time
import urllib.request

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome")

_FLAGS = (
  "--headless",
  "--no-sandbox",
  "--disable-gpu",
  "--use-angle=swiftshader",
  "--enable-unsafe-swiftshader",
  "--disable-quic",
  "--no-first-run",
  "--disable-background-networking",
  "--disable-component-update",
  "--disable-sync",
  "--hide-scrollbars",
  "--remote-debugging-port=0",
  "--remote-allow-origins=*",
  "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE localhost, EXCLUDE 127.0.0.1",
)

# viser tells a software-WebGL browser so in a notice over the canvas; it is about the machine
# taking the screenshot, not the viewer, so it is closed before the capture.
_CLOSE_NOTICES = (
  "document.querySelectorAll('.mantine-Notifications-root, "
  '[class*="mantine-Notification-root"]\').forEach(e => e.remove())'
)


# Waits for a few animation frames: viser renders on demand, and an animation in progress (the
# splats fade in) asks for the next frame, so a page still changing differs after these.
_FRAMES = (
  "new Promise(done => { let left = 5; const step = () => --left ? "
  "requestAnimationFrame(step) : done(true); requestAnimationFrame(step); })"
)


def find_chromium() -> str | None:
  """The Chromium executable ($CHROMIUM, else the first of CHROMIUM_NAMES on PATH), or None."""
  named = os.environ.get("CHROMIUM")
  if named:
    return shutil.which(named)
  return next((path for path in map(shutil.which, CHROMIUM_NAMES) if path), None)


class _DevTools:
  """A minimal DevTools-protocol session with one page (request -> matching response)."""

  def __init__(self, websocket_url: str):
    from websockets.sync.client import connect

    self._socket = connect(websocket_url, max_size=None, open_timeout=20)
    self._ids = itertools.count(1)

  def __call__(self, method: str, **params) -> dict:
    request_id = next(self._ids)
    self._socket.send(json.dumps({"id": request_id, "method": method, "params": params}))
    while True:
      reply = json.loads(self._socket.recv(timeout=60))
      if reply.get("id") == request_id:
        if "error" in reply:
          raise RuntimeError(f"DevTools {method}: {reply['error']}")
        return reply.get("result", {})

  def evaluate(self, expression: str):
    reply = self("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
    return reply["result"].get("value")

  def capture(self) -> bytes:
    return base64.b64decode(self("Page.captureScreenshot", format="png")["data"])

  def close(self) -> None:
    self._socket.close()


def _chromium_or_raise(chromium: str | None) -> str:
  chromium = chromium or find_chromium()
  if chromium is None:
    raise FileNotFoundError("no Chromium found (apt-get install -y chromium, or set $CHROMIUM)")
  return chromium


def _devtools_port(profile: pathlib.Path, process: subprocess.Popen, log, deadline: float) -> int:
  port_file = profile / "DevToolsActivePort"
  while time.monotonic() < deadline:
    if port_file.exists() and port_file.read_text().strip():
      return int(port_file.read_text().split()[0])
    if process.poll() is not None:
      log.seek(0)
      raise RuntimeError(f"Chromium exited with {process.returncode}:\n{log.read()[-3000:]}")
    time.sleep(0.1)
  raise TimeoutError("Chromium did not open its DevTools port")


@contextlib.contextmanager
def _chromium_page(chromium: str, width: int, height: int, deadline: float):
  """A DevTools session with the blank page of a fresh headless Chromium (own temporary
  profile); the browser and its helper processes (its own process group) are shut down on exit.
  A helper still writing to the profile as it is removed cannot fail the caller."""
  with (
    tempfile.TemporaryDirectory(prefix="chromium-profile-", ignore_cleanup_errors=True) as profile,
    tempfile.TemporaryFile("w+") as log,
  ):
    process = subprocess.Popen(
      [
        chromium,
        *_FLAGS,
        f"--user-data-dir={profile}",
        f"--window-size={width},{height}",
        "about:blank",
      ],
      stdout=subprocess.DEVNULL,
      stderr=log,
      text=True,
      start_new_session=True,
    )
    try:
      port = _devtools_port(pathlib.Path(profile), process, log, deadline)
      with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as reply:
        page = next(t for t in json.load(reply) if t["type"] == "page")
      devtools = _DevTools(page["webSocketDebuggerUrl"])
      try:
        yield devtools
      finally:
        devtools.close()
    finally:
      _stop_group(process)


def _stop_group(process: subprocess.Popen) -> None:
  """SIGTERM to the process group the browser leads, then SIGKILL to the group once the browser
  has exited or after 10 s: its helper processes must not outlive it."""
  with contextlib.suppress(ProcessLookupError):
    os.killpg(process.pid, signal.SIGTERM)
  with contextlib.suppress(subprocess.TimeoutExpired):
    process.wait(timeout=10)
  with contextlib.suppress(ProcessLookupError):
    os.killpg(process.pid, signal.SIGKILL)
  process.wait()


def _wait_for_text(devtools: _DevTools, text: str, deadline: float) -> bool:
  """Polls until the page's text contains `text`; False if `deadline` passes first."""
  while not devtools.evaluate(
    f"document.body !== null && document.body.innerText.includes({json.dumps(text)})"
  ):
    if time.monotonic() > deadline:
      return False
    time.sleep(0.2)
  return True


def _settled_capture(devtools: _DevTools, settle_s: float, deadline: float) -> bytes | None:
  """A PNG of the page once two captures `settle_s` and five animation frames apart are
  identical (notices closed before each); None if it still changes at `deadline`."""
  previous = None
  while True:
    devtools.evaluate(_CLOSE_NOTICES)
    image = devtools.capture()
    if image == previous:
      return image
    if time.monotonic() > deadline:
      return None
    previous = image
    time.sleep(settle_s)
    devtools.evaluate(_FRAMES)


def screenshot(
  url: str,
  path,
  *,
  ready_text: str = "",
  width: int = 1280,
  height: int = 800,
  timeout_s: float = 60.0,
  settle_s: float = 1.0,
  chromium: str | None = None,
) -> pathlib.Path:
  """Loads `url` in a fresh headless Chromium profile and writes a PNG of the window to `path`.

  Captures once the page's text contains `ready_text` and two captures `settle_s` and five
  animation frames apart are identical (the viewer has drawn its splats).

  Raises:
    FileNotFoundError: no Chromium.
    TimeoutError: the page did not get ready / settle within `timeout_s`.
  """
  deadline = time.monotonic() + timeout_s
  path = pathlib.Path(path)
  with _chromium_page(_chromium_or_raise(chromium), width, height, deadline) as devtools:
    devtools("Page.enable")
    devtools(
      "Emulation.setDeviceMetricsOverride",
      width=width,
      height=height,
      deviceScaleFactor=1,
      mobile=False,
    )
    devtools("Page.navigate", url=url)
    if not _wait_for_text(devtools, ready_text, deadline):
      raise TimeoutError(f"{url} did not show {ready_text!r} within {timeout_s} s")
    image = _settled_capture(devtools, settle_s, deadline)
    if image is None:
      raise TimeoutError(f"{url} kept changing for {timeout_s} s")
  path.parent.mkdir(parents=True, exist_ok=True)
  path.write_bytes(image)
  return path.resolve()


@contextlib.contextmanager
def headless_page(*, width: int = 1280, height: int = 800, timeout_s: float = 60.0, chromium=None):
  """The page of a fresh headless Chromium (own temporary profile), for `load`; Chromium is shut
  down on exit.

  Raises:
    FileNotFoundError: no Chromium.
    TimeoutError: Chromium did not open its DevTools port within `timeout_s`.
  """
  deadline = time.monotonic() + timeout_s
  with _chromium_page(_chromium_or_raise(chromium), width, height, deadline) as devtools:
    devtools("Page.enable")
    yield devtools


def load(page, url: str, text: str, timeout_s: float = 20.0) -> str:
  """Loads `url` in `page` (from `headless_page`) and returns the page's text once it contains
  `text`, or as it is after `timeout_s`."""
  page("Page.navigate", url=url)
  _wait_for_text(page, text, time.monotonic() + timeout_s)
  return page.evaluate("document.body === null ? '' : document.body.innerText")
