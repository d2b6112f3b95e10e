"""viser's server with its websocket open only to the viewer's own page.

A browser lets any web page open a websocket to 127.0.0.1 and sends the page's origin with the
handshake; viser accepts every origin, so a page in another tab could read the whole scene and
press "save". The handshake is accepted only from the page this server served: an `Origin` that is
`http://` + the request's `Host`, where that host is `localhost` or an IP address (a name could be
rebound to this machine by its DNS, an address cannot). A handshake without an `Origin` (no
browser sends one) is refused as well: nothing but the viewer's page talks to it.
"""

from __future__ import annotations

import contextlib
import http
import ipaddress
import threading
import urllib.parse

_PATCHING = threading.Lock()


def same_page_origin(origin: str | None, host: str | None) -> bool:
  """Whether a websocket handshake with headers `Origin: origin` and `Host: host` comes from a
  page this server served (see the module's docstring)."""
  if not origin or not host or origin != f"http://{host}":
    return False
  name = urllib.parse.urlsplit(origin).hostname
  if name == "localhost":
    return True
  try:
    ipaddress.ip_address(name)
  except ValueError:
    return False
  return True


def _refuse_other_origins(connection, request):
  """A 403 response to a websocket handshake from another origin; None lets it through."""
  headers = request.headers
  if headers.get("Upgrade", "").lower() != "websocket":
    return None
  if same_page_origin(headers.get("Origin"), headers.get("Host")):
    return None
  return connection.respond(http.HTTPStatus.FORBIDDEN, "origin not allowed\n")


@contextlib.contextmanager
def _origin_checked_serve():
  """While open, `websockets.asyncio.server.serve` runs `_refuse_other_origins` before the
  caller's own `process_request`: viser builds its server inside `ViserServer.__init__` with no
  hook for the handshake, and calls `serve` before that returns."""
  import websockets.asyncio.server as websockets_server

  plain = websockets_server.serve

  def serve(*args, process_request=None, **kwargs):
    def checked(connection, request):
      refused = _refuse_other_origins(connection, request)
      if refused is not None or process_request is None:
        return refused
      return process_request(connection, request)

    return plain(*args, process_request=checked, **kwargs)

  with _PATCHING:
    websockets_server.serve = serve
    try:
      yield
    finally:
      websockets_server.serve = plain


def start(host: str, port: int):
  """A running `viser.ViserServer` on `host`:`port` (the next free port when it is busy) whose
  websocket accepts only the pages it served."""
  import viser

  with _origin_checked_serve():
    return viser.ViserServer(host=host, port=port, verbose=False)
