"""viser's server with its websocket open only to the viewer's own page, and optionally only to
holders of a token.

A browser lets any web page open a websocket to 127.0.0.1 and sends the page's origin with the
handshake; viser accepts every origin, so a page in another tab could read the whole scene and
press "save". The handshake is accepted only from the page this server served: an `Origin` that is
`http://` + the request's `Host`, where that host is `localhost` or an IP address (a name could be
rebound to this machine by its DNS, an address cannot). A handshake without an `Origin` (no
browser sends one) is refused as well: nothing but the viewer's page talks to it.

The Origin check does not stop another user of a shared machine: their own client reaches
127.0.0.1 too and sends any `Origin` it likes. With a token, every request (page and websocket)
must carry it, as `?token=` or as the cookie the page sets: viser's client opens its websocket at
the page's URL without the query, and the handshake carries no `Referer`, so the cookie is what
brings the token from the page to its websocket. Cookies are shared by every port of a host, so
its name holds the port (two viewers keep their own), it is `HttpOnly` (no page script reads it)
and `SameSite=Strict` (another site's requests do not carry it).
"""

from __future__ import annotations

import contextlib
import hmac
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


def token_cookie_name(host: str | None) -> str:
  """The name of the token's cookie for requests with header `Host: host` (its port in it)."""
  port = (host or "").rpartition(":")[2]
  return f"tokengs_viewer_token_{port if port.isascii() and port.isdigit() else ''}"


def _query_tokens(request) -> list[str]:
  return urllib.parse.parse_qs(urllib.parse.urlsplit(request.path).query).get("token", [])


def _cookie_tokens(request) -> list[str]:
  name = token_cookie_name(request.headers.get("Host"))
  pairs = (
    pair.strip().partition("=")
    for header in request.headers.get_all("Cookie")
    for pair in header.split(";")
  )
  return [value for key, _, value in pairs if key == name]


def _matches(candidates: list[str], token: str) -> bool:
  """Whether one of `candidates` is `token` (compared in constant time)."""
  return any(hmac.compare_digest(c.encode(), token.encode()) for c in candidates)


def _refusal(connection, request, token: str | None):
  """A 403 response to a request without the token, or to a websocket handshake from another
  origin; None lets it through."""
  if token is not None and not _matches(_query_tokens(request) + _cookie_tokens(request), token):
    return connection.respond(http.HTTPStatus.FORBIDDEN, "this viewer needs its URL's token\n")
  headers = request.headers
  if headers.get("Upgrade", "").lower() != "websocket":
    return None
  if same_page_origin(headers.get("Origin"), headers.get("Host")):
    return None
  return connection.respond(http.HTTPStatus.FORBIDDEN, "origin not allowed\n")


def _checked(process_request, token: str | None):
  """`process_request` behind `_refusal`; a page requested with the token in its query sets the
  token's cookie, which its websocket handshake then carries."""

  def checked(connection, request):
    refused = _refusal(connection, request, token)
    if refused is not None or process_request is None:
      return refused
    response = process_request(connection, request)
    if response is not None and token is not None and _matches(_query_tokens(request), token):
      name = token_cookie_name(request.headers.get("Host"))
      response.headers["Set-Cookie"] = f"{name}={token}; Path=/; HttpOnly; SameSite=Strict"
    return response

  return checked


@contextlib.contextmanager
def _checked_serve(token: str | None):
  """While open, `websockets.asyncio.server.serve` runs the caller's `process_request` behind
  `_checked`: viser builds its server inside `ViserServer.__init__` with no hook for the
  handshake, and calls `serve` before that returns."""
  import websockets.asyncio.server as websockets_server

  plain = websockets_server.serve

  def serve(*args, process_request=None, **kwargs):
    return plain(*args, process_request=_checked(process_request, token), **kwargs)

  with _PATCHING:
    websockets_server.serve = serve
    try:
      yield
    finally:
      websockets_server.serve = plain


def start(host: str, port: int, token: str | None = None):
  """A running `viser.ViserServer` on `host`:`port` (the next free port when it is busy) whose
  websocket accepts only the pages it served; with a `token`, every request must carry it (as
  `?token=` or as the cookie the page sets)."""
  import viser

  with _checked_serve(token):
    return viser.ViserServer(host=host, port=port, verbose=False)
