"""Look at a reconstruction in the browser: an interactive viser viewer of predicted Gaussians.

    python -m experiments.view outputs/re10k/tiny_synthetic            # then open the printed URL
    python -m experiments.view outputs/kubric/tiny_synthetic --port 8081
    python -m experiments.view outputs/re10k/tiny_synthetic --checkpoint other/params.msgpack
    python -m experiments.view outputs/re10k/tiny_synthetic/gaussians.ply   # any 3DGS PLY
    python -m experiments.view outputs/re10k/tiny_synthetic --screenshot docs/viewer.png
    python -m experiments.view outputs/re10k/tiny_synthetic --token    # a shared machine

A results folder (written by `experiments.re10k` / `.dl3dv` / `.kubric`) gives its held-out scenes
(the evaluation's own views) reconstructed by its `params.msgpack`: splats, input cameras (blue)
and the target camera (red) as frustums, a slider over the scenes, an opacity threshold with the
count of Gaussians that reach it, static / dynamic switches and a time slider for Kubric models,
and the target view beside our renderer's image of the shown Gaussians (with PSNR).
`--checkpoint`, `--data-dir` and `--synthetic-dir` point the folder's settings at other weights or
scenes. Opening a folder writes nothing: a synthetic set its settings name that is not there is an
error, unless `--generate-data` asks for it to be written. The viewer's web client is served from
the installed viser package (nothing is downloaded), and its websocket answers only that page.
`--token` makes the page and its websocket require a fresh random token, printed in the URL: on a
shared machine, the other users reach 127.0.0.1 too.
`--screenshot PATH` writes a headless-Chromium screenshot and exits instead of serving.
"""

from __future__ import annotations

import dataclasses
import secrets
import sys
import time
from typing import Annotated

import tyro

from experiments import data
from experiments.viewer import app, browser, scenes
from experiments.viewer import server as viewer_server
from tokengs_jax import process


@dataclasses.dataclass(frozen=True)
class ViewSettings:
  """What to show and how to serve it.

  Attributes:
    source: a results folder (metrics.json + params.msgpack) or a `.ply` file.
    checkpoint: other weights (`params.msgpack`) with the folder's settings.
    data_dir: real-data root of the held-out scenes, if not the run's.
    synthetic_dir: synthetic set of the held-out scenes, if not the run's.
    generate_data: write the synthetic set the folder's settings name when it is missing (without
      it, opening a folder writes nothing: the folder may come from anyone).
    num_scenes: held-out scenes offered (0: the run's `eval.num_scenes`).
    host: address to serve on (127.0.0.1: this machine only; 0.0.0.0: the network).
    port: port (the next free one is taken when it is busy).
    token: require a fresh random token, printed in the URL, on the page and its websocket (on a
      shared machine the other users reach 127.0.0.1 too; a token chosen on the command line
      would show in their `ps`).
    render_size: pixels of the longer side of the target-view render in the panel.
    pull_back: the browser starts this many scene depths behind the target camera (0: at it).
    background: RGB in [0, 1] behind the splats (default: the training background).
    screenshot: write a headless-Chromium screenshot of the viewer here and exit.
    window: browser window (width, height) of the screenshot.
  """

  source: Annotated[str, tyro.conf.Positional]
  checkpoint: str | None = None
  data_dir: str | None = None
  synthetic_dir: str | None = None
  generate_data: bool = False
  num_scenes: int = 0
  host: str = "127.0.0.1"
  port: int = 8080
  token: bool = False
  render_size: int = 256
  pull_back: float = 0.6
  background: tuple[float, float, float] = app.TRAINING_BACKGROUND
  screenshot: str | None = None
  window: tuple[int, int] = (1280, 800)


def start(settings: ViewSettings):
  """Loads the source and serves it; returns (server, app, the URL to open)."""
  names = ("checkpoint", "data_dir", "synthetic_dir", "generate_data", "num_scenes")
  source = scenes.open_source(settings.source, **{k: getattr(settings, k) for k in names})
  token = secrets.token_urlsafe(32) if settings.token else None
  server = viewer_server.start(settings.host, settings.port, token)
  viewer = app.ViewerApp(
    source,
    server,
    render_size=settings.render_size,
    pull_back=settings.pull_back,
    background=settings.background,
  )
  host = "127.0.0.1" if settings.host == "0.0.0.0" else settings.host
  url = f"http://{host}:{server.get_port()}" + (f"/?token={token}" if token else "")
  return server, viewer, url


def main(argv=None) -> None:
  settings = tyro.cli(
    ViewSettings, args=sys.argv[1:] if argv is None else argv, prog="python -m experiments.view"
  )
  process.setup()
  try:
    server, _, url = start(settings)
  except data.GenerationRefused as refused:
    raise SystemExit(f"[view] {refused}") from None
  try:
    if settings.screenshot:
      path = browser.screenshot(
        url,
        settings.screenshot,
        ready_text=app.READY_TEXT,
        width=settings.window[0],
        height=settings.window[1],
      )
      print(f"[view] screenshot of {url} written to {path}", flush=True)
      return
    print(f"[view] serving {settings.source} at {url} (Ctrl-C stops)", flush=True)
    while True:
      time.sleep(3600)
  except KeyboardInterrupt:
    pass
  finally:
    server.stop()


if __name__ == "__main__":
  main()
