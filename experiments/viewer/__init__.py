"""The interactive viewer behind `python -m experiments.view` (viser, served from the package).

- `scenes`: what is shown, host-side: a results folder (or a PLY) -> per held-out scene Gaussians,
  cameras and target renders, plus the opacity / static-dynamic selection.
- `app`: the viser GUI over those scenes.
- `server`: viser's server, its websocket open only to the page it served (the Origin check).
- `browser`: headless-Chromium screenshots (the browser test and docs/viewer.png).
"""
