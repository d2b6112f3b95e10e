"""Who reaches the viewer (issue 28): only its own page (the websocket's Origin check), and with
`--token` only who holds the token of its URL (page, websocket), checked over HTTP and in
headless Chromium."""

import contextlib
import functools
import http.server
import json
import threading
import urllib.error
import urllib.request

import numpy as np
import pytest

from experiments.viewer import browser
from experiments.viewer import server as viewer_server

TOKEN = "a-token-for-the-tests"
CONNECTED = "websocket connected to the viewer"

needs_chromium = pytest.mark.skipif(
  browser.find_chromium() is None,
  reason="needs Chromium: apt-get install -y chromium (docs/viewer.md)",
)


@contextlib.contextmanager
def _viewer(token=None):
  """A viewer server whose page shows CONNECTED once its websocket is open."""
  server = viewer_server.start("127.0.0.1", 0, token=token)
  server.gui.add_markdown(CONNECTED)
  try:
    yield server
  finally:
    server.stop()


@pytest.fixture(scope="module")
def open_viewer():
  with _viewer() as server:
    yield server


@pytest.fixture(scope="module")
def tokened_viewer():
  with _viewer(token=TOKEN) as server:
    yield server


def _get(url, cookie=None):
  """(status, headers) of a GET of `url`."""
  request = urllib.request.Request(url, headers={"Cookie": cookie} if cookie else {})
  try:
    with urllib.request.urlopen(request, timeout=10) as reply:
      return reply.status, reply.headers
  except urllib.error.HTTPError as refused:
    return refused.code, refused.headers


def _handshake(url, origin, cookie=None) -> int:
  """The HTTP status a websocket handshake to `url` gets (101: open)."""
  import viser
  from websockets.exceptions import InvalidStatus
  from websockets.sync.client import connect

  try:
    with connect(
      url,
      origin=origin,
      subprotocols=[f"viser-v{viser.__version__}"],
      additional_headers={"Cookie": cookie} if cookie else None,
      open_timeout=10,
    ):
      return 101
  except InvalidStatus as refused:
    return refused.response.status_code


def test_without_a_token_the_page_is_open(open_viewer):
  status, headers = _get(f"http://127.0.0.1:{open_viewer.get_port()}/")
  assert status == 200 and headers["Set-Cookie"] is None


def test_token_guards_the_page_and_the_websocket(tokened_viewer):
  """The page needs `?token=` (403 without it or with another one) and sets the token as a
  cookie for its port; the websocket needs the cookie (what the page's client sends) or the
  query, and still its own page's Origin."""
  port = tokened_viewer.get_port()
  page, socket, origin = f"http://127.0.0.1:{port}/", f"ws://127.0.0.1:{port}/", None
  assert _get(page)[0] == 403
  assert _get(f"{page}?token=not-{TOKEN}")[0] == 403
  status, headers = _get(f"{page}?token={TOKEN}")
  assert status == 200
  cookie = headers["Set-Cookie"]
  assert cookie.startswith(f"tokengs_viewer_token_{port}={TOKEN};")
  assert "HttpOnly" in cookie and "SameSite=Strict" in cookie
  cookie = cookie.partition(";")[0]
  assert _get(page, cookie=cookie)[0] == 200  # a reload
  origin = f"http://127.0.0.1:{port}"
  assert _handshake(socket, origin) == 403
  assert _handshake(socket, origin, cookie=f"tokengs_viewer_token_{port}=not-{TOKEN}") == 403
  assert _handshake(socket, origin, cookie=cookie) == 101
  assert _handshake(f"{socket}?token={TOKEN}", origin) == 101
  assert _handshake(f"{socket}?token={TOKEN}", "http://evil.example") == 403
  assert _handshake(socket, "http://evil.example", cookie=cookie) == 403


def test_view_token_setting_puts_a_fresh_token_in_the_url(tmp_path):
  from experiments import view
  from tokengs_jax import export

  rng = np.random.default_rng(0)
  ply = export.write_ply(
    tmp_path / "g.ply",
    means=rng.normal(size=(4, 3)).astype(np.float32),
    opacities=np.full(4, 0.5, np.float32),
    scales=np.full((4, 3), 0.1, np.float32),
    quats=np.tile(np.float32([1, 0, 0, 0]), (4, 1)),
    colors=np.full((4, 3), 0.5, np.float32),
  )
  urls = []
  for _ in range(2):
    server, _, url = view.start(view.ViewSettings(str(ply), port=0, render_size=16, token=True))
    try:
      urls.append(url)
      page = f"http://127.0.0.1:{server.get_port()}"
      assert url.startswith(f"{page}/?token=") and len(url) - len(page) >= len("/?token=") + 43
      assert _get(url)[0] == 200 and _get(page)[0] == 403
    finally:
      server.stop()
  assert urls[0].partition("=")[2] != urls[1].partition("=")[2]
  server, _, url = view.start(view.ViewSettings(str(ply), port=0, render_size=16))
  try:
    assert url == f"http://127.0.0.1:{server.get_port()}" and _get(url)[0] == 200
  finally:
    server.stop()


# Another site's page: opens a websocket to `?target=` and writes what happened into its text.
_OTHER_SITE_PAGE = """<!doctype html><body>trying<script>
const target = new URLSearchParams(location.search).get("target");
const socket = new WebSocket(target, [%s]);
let opened = false;
socket.onopen = () => { opened = true; document.body.innerText = "other site: websocket opened"; };
socket.onclose = () => { if (!opened) document.body.innerText = "other site: websocket refused"; };
</script></body>"""


class _QuietFiles(http.server.SimpleHTTPRequestHandler):
  def log_message(self, *args):
    pass


@pytest.fixture(scope="module")
def other_site(tmp_path_factory):
  """`http://127.0.0.1:<another port>/page.html`: a page of another origin."""
  import viser

  root = tmp_path_factory.mktemp("other_site")
  (root / "page.html").write_text(_OTHER_SITE_PAGE % json.dumps(f"viser-v{viser.__version__}"))
  handler = functools.partial(_QuietFiles, directory=str(root))
  with http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler) as site:
    threading.Thread(target=site.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{site.server_address[1]}/page.html"
    site.shutdown()


@pytest.fixture(scope="module")
def chromium():
  with browser.headless_page(timeout_s=120) as page:
    yield page


def _shows(page, url, text) -> str:
  """The page's text once it contains `text` (else after 20 s)."""
  return browser.load(page, url, text, timeout_s=20)


@needs_chromium
def test_another_sites_page_cannot_open_the_websocket_in_chromium(
  chromium, other_site, open_viewer, tokened_viewer
):
  """A page from another origin (another port of 127.0.0.1) opening the viewer's websocket is
  refused, with the token too; the viewer's own page connects."""
  port = open_viewer.get_port()
  assert "websocket refused" in _shows(
    chromium, f"{other_site}?target=ws://127.0.0.1:{port}", "other site: "
  )
  assert CONNECTED in _shows(chromium, f"http://127.0.0.1:{port}/", CONNECTED)
  socket = f"ws://127.0.0.1:{tokened_viewer.get_port()}/?token={TOKEN}"
  target = urllib.request.quote(socket, safe="")
  assert "websocket refused" in _shows(chromium, f"{other_site}?target={target}", "other site: ")


@needs_chromium
def test_token_page_connects_in_chromium(chromium, tokened_viewer):
  """Chromium loads the page only with the token, and its client's websocket (which drops the
  query) opens on the cookie the page set."""
  page = f"http://127.0.0.1:{tokened_viewer.get_port()}/"
  refused = _shows(chromium, page, "token")
  assert "token" in refused and CONNECTED not in refused
  assert CONNECTED in _shows(chromium, f"{page}?token={TOKEN}", CONNECTED)
