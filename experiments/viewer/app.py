"""The viser GUI: predicted Gaussians as splats, input cameras as frustums, a target view rendered
by our renderer beside the 3D view, sliders over the held-out scenes and their target views, an
opacity threshold that counts the Gaussians that matter, and static / dynamic switches and a time
slider for Kubric models."""

from __future__ import annotations

import functools

import threading

import jax
import numpy as np

from experiments import results
from experiments.viewer import scenes as scenes_lib
from tokengs_jax import export
from tokengs_jax.objective import ObjectiveConfig

_INPUT_COLOUR = (40, 90, 200)
_TARGET_COLOUR = (220, 60, 40)  # the target view rendered in the panel
_OTHER_TARGET_COLOUR = (150, 150, 150)
READY_TEXT = "Gaussians shown"  # in the panel once a scene is drawn
# The 3D view's background: what the model was trained against (as the render beside it).
TRAINING_BACKGROUND = tuple(ObjectiveConfig().background)


def _rotation_wxyz(rotation: np.ndarray) -> np.ndarray:
  import viser.transforms as tf

  return tf.SO3.from_matrix(np.asarray(rotation, np.float64)).wxyz


def vertical_fov(intrinsics: np.ndarray, height: int) -> float:
  """Vertical field of view (radians) of a pinhole camera [4] (fx, fy, cx, cy) in pixels."""
  return float(2.0 * np.arctan(height / (2.0 * intrinsics[1])))


def world_up(c2w: np.ndarray) -> np.ndarray:
  """The scene's up direction from its cameras: the mean of their -y axes (OpenCV y is down).
  c2w: [V, 4, 4] -> [3]."""
  up = -np.asarray(c2w)[:, :3, 1].mean(axis=0)
  return up / max(np.linalg.norm(up), 1e-12)


def _is_input(c2w: np.ndarray, scene: scenes_lib.ViewScene) -> bool:
  return any(np.allclose(c2w, seen, atol=1e-5) for seen in scene.inputs.c2w)


def novel_target(scene: scenes_lib.ViewScene) -> int:
  """The first target view whose camera is not one of the input cameras (0 if all are): the view
  worth rendering beside the 3D view."""
  return next((i for i, c2w in enumerate(scene.targets.c2w) if not _is_input(c2w, scene)), 0)


def overview_pose(c2w: np.ndarray, means: np.ndarray, pull_back: float) -> tuple[np.ndarray, ...]:
  """(position, look_at, up) of a viewpoint behind camera `c2w` [4, 4], looking at the Gaussians
  in front of it (their median depth), `pull_back` median depths further back."""
  forward, origin = c2w[:3, 2], c2w[:3, 3]
  depth = (means - origin) @ forward
  ahead = depth[depth > 0]
  distance = float(np.median(ahead)) if len(ahead) else 1.0
  return origin - pull_back * distance * forward, origin + distance * forward, -c2w[:3, 1]


class ViewerApp:
  """The GUI over a source of scenes (`scenes.ResultsSource` / `scenes.PlySource`).

  Every control redraws through one path per kind of change; values the app sets itself (a new
  scene's start time and target view) are set with the callbacks muted, so nothing draws twice.

  Args:
    source: the scenes (`keys`, `scene`, `default_time`, `time_conditioned`, `title` and the
      `objective` its renders were scored with).
    server: a running `viser.ViserServer`.
    render_size: longer side (pixels) of the target-view render shown in the panel.
    pull_back: a new browser starts this many scene depths behind the rendered target camera, so
      that the input cameras are in view (0: at the target camera).
    background: RGB in [0, 1] behind the splats in the 3D view; default the official training
      background. The target render beside it uses the run's own (`source.objective`, as the
      evaluation scored it: for "input_mean" each scene's mean input colour).
  """

  def __init__(
    self,
    source,
    server,
    render_size: int = 256,
    pull_back: float = 0.6,
    background: tuple[float, float, float] = TRAINING_BACKGROUND,
  ):
    self.source, self.server = source, server
    self.render_size, self.pull_back = render_size, pull_back
    server.scene.set_background_image(np.full((8, 8, 3), background, np.float32), format="png")
    self._lock = threading.RLock()
    self._muted = False
    gui = server.gui
    keys = source.keys
    first = source.scene(0, source.default_time(0))
    gui.add_markdown(f"**{source.title}**")
    self.scene_index = (
      gui.add_slider("held-out scene", min=0, max=len(keys) - 1, step=1, initial_value=0)
      if len(keys) > 1
      else None
    )
    self.scene_label = gui.add_markdown("")
    self.time = (
      gui.add_slider("time", min=0.0, max=1.0, step=0.01, initial_value=round(first.time, 2))
      if source.time_conditioned
      else None
    )
    self.target_view = (
      gui.add_slider(
        "target view",
        min=0,
        max=len(first.targets.c2w) - 1,
        step=1,
        initial_value=novel_target(first),
      )
      if first.targets is not None
      else None
    )
    self.threshold = gui.add_slider(
      "opacity threshold", min=0.0, max=1.0, step=0.01, initial_value=0.0
    )
    self.census = gui.add_markdown("")
    self.show_static = gui.add_checkbox("static Gaussians", True)
    self.show_dynamic = gui.add_checkbox(
      "dynamic Gaussians", True, visible=first.num_static < first.num_gaussians
    )
    self.show_cameras = gui.add_checkbox("cameras", True)
    self.save = gui.add_button("save the shown Gaussians as PLY")
    self.saved = gui.add_markdown("")
    self.to_target = gui.add_button(
      "view from the target camera", visible=first.targets is not None
    )
    self.image = gui.add_image(
      np.zeros((8, 16, 3), np.uint8),
      label="target | our render",
      format="png",
      visible=first.targets is not None,
    )
    self.scores = gui.add_markdown("")

    self._on(self.scene_index, lambda: self.show(new_scene=True))
    self._on(self.time, self.show)
    self._on(self.target_view, self.show_target)
    for handle in (self.threshold, self.show_static, self.show_dynamic):
      self._on(handle, self.refresh_selection)
    self._on(self.show_cameras, self._draw_cameras)
    self.save.on_click(lambda _: self.save_shown())
    self.to_target.on_click(lambda event: self._look_from_target(event.client, pull_back=0.0))
    self.show()
    server.on_client_connect(lambda client: self._look_from_target(client, self.pull_back))

  def _on(self, handle, redraw) -> None:
    if handle is not None:
      handle.on_update(lambda _: self._redraw(redraw))

  def _redraw(self, redraw) -> None:
    # A browser's change waits for the drawing in progress, then applies; a value the app sets
    # itself calls back on the drawing thread (re-entering the lock) while muted.
    with self._lock:
      if not self._muted:
        redraw()

  def _set_quietly(self, handle, value) -> None:
    self._muted = True
    try:
      handle.value = value
    finally:
      self._muted = False

  # -- state -----------------------------------------------------------------------------------

  def show(self, new_scene: bool = False) -> None:
    """(Re)draws everything for the chosen scene and time; a new scene starts at its first
    target's time and its first novel target view."""
    with self._lock:
      index = int(self.scene_index.value) if self.scene_index is not None else 0
      if new_scene and self.time is not None:
        self._set_quietly(self.time, round(self.source.default_time(index), 2))
      time = float(self.time.value) if self.time is not None else None
      self.scene = self.source.scene(index, time)
      scene = self.scene
      if new_scene and self.target_view is not None:
        self.target_view.max = len(scene.targets.c2w) - 1
        self._set_quietly(self.target_view, novel_target(scene))
      self.scene_label.content = (
        f"scene `{scene.key}` ({index + 1} of {len(self.source.keys)}), "
        f"{scene.num_gaussians:,} Gaussians"
      )
      if scene.inputs is not None:
        self.server.scene.set_up_direction(world_up(scene.inputs.c2w))
      self.show_target()

  def show_target(self) -> None:
    """Cameras, splats and the render, for the chosen target view."""
    with self._lock:
      scene = self.scene
      if scene.targets is not None:
        position, look_at, up = overview_pose(
          self._target_c2w(), scene.gaussians.means, self.pull_back
        )
        initial = self.server.initial_camera
        initial.position, initial.look_at, initial.up = position, look_at, up
        initial.fov = vertical_fov(
          scene.targets.intrinsics[self._target()], scene.targets.images.shape[1]
        )
      self._draw_cameras()
      self.refresh_selection()

  def selection(self) -> np.ndarray:
    return scenes_lib.selection(
      self.scene, float(self.threshold.value), self.show_static.value, self.show_dynamic.value
    )

  def refresh_selection(self) -> None:
    """Splats, counts and the target render for the current threshold and parts."""
    with self._lock:
      visible = self.selection()
      self._draw_splats(visible)
      self._write_census(visible)
      if self.scene.targets is not None:
        self._draw_render(visible)

  def save_shown(self):
    """Writes the shown Gaussians (threshold and parts applied) as a 3DGS PLY under
    `<source folder>/viewer/`, named after the scene as `results.data_path` allows (the key
    comes from the data); returns the path."""
    with self._lock:
      scene, visible = self.scene, self.selection()
      name = f"{scene.key}_opacity{float(self.threshold.value):.2f}"
      if scene.time is not None:
        name += f"_time{scene.time:.2f}"
      g = jax.tree.map(lambda x: x[visible], scene.gaussians)
      path = export.write_ply(
        results.data_path(self.source.folder / "viewer", name, ".ply"),
        g.means,
        g.opacities,
        g.scales,
        g.quats,
        g.colors,
      )
      self.saved.content = f"wrote {int(visible.sum()):,} Gaussians to `{path}`"
      return path

  def _target(self) -> int:
    return int(self.target_view.value)

  def _target_c2w(self) -> np.ndarray:
    return self.scene.targets.c2w[self._target()]

  # -- drawing ---------------------------------------------------------------------------------

  def _draw_splats(self, visible: np.ndarray) -> None:
    scene = self.scene
    g = scene.gaussians
    parts = {"static": np.arange(scene.num_gaussians) < scene.num_static}
    if scene.num_static < scene.num_gaussians:
      parts["dynamic"] = ~parts["static"]
    for name, part in parts.items():
      chosen = visible & part
      node = f"/gaussians/{name}"
      if not chosen.any():
        self.server.scene.remove_by_name(node)
        continue
      self.server.scene.add_gaussian_splats(
        node,
        centers=g.means[chosen],
        covariances=scenes_lib.covariances(g.scales[chosen], g.quats[chosen]),
        rgbs=np.clip(g.colors[chosen], 0.0, 1.0),
        opacities=g.opacities[chosen][:, None],
      )

  def _draw_cameras(self) -> None:
    scene = self.scene
    self.server.scene.remove_by_name("/cameras")
    if scene.inputs is None or not self.show_cameras.value:
      return
    means = scene.gaussians.means
    extent = float(np.median(np.linalg.norm(means - np.median(means, axis=0), axis=-1)))
    for kind, views in (("input", scene.inputs), ("target", scene.targets)):
      height, width = views.images.shape[1:3]
      for i, (image, c2w, intrinsics) in enumerate(zip(views.images, views.c2w, views.intrinsics)):
        rendered = kind == "target" and i == self._target()
        if kind == "target" and not rendered and _is_input(c2w, scene):
          continue  # the input's frustum is already there
        colour = (
          _INPUT_COLOUR if kind == "input" else _TARGET_COLOUR if rendered else _OTHER_TARGET_COLOUR
        )
        self.server.scene.add_camera_frustum(
          f"/cameras/{kind}_{i}",
          fov=vertical_fov(intrinsics, height),
          aspect=width / height,
          scale=0.15 * max(extent, 1e-3),
          thickness=2.0,
          thickness_units="screen",
          color=colour,
          image=export.to_uint8(image),
          format="png",
          wxyz=_rotation_wxyz(c2w[:3, :3]),
          position=c2w[:3, 3],
        )

  def _write_census(self, visible: np.ndarray) -> None:
    scene = self.scene
    total = scene.num_gaussians
    dynamic = scene.num_static < total
    lines = [
      f"**{int(visible.sum()):,} / {total:,}** {READY_TEXT} "
      f"(opacity ≥ {float(self.threshold.value):.2f}"
      + (", static / dynamic switches applied)" if dynamic else ")"),
      "",
      "| opacity ≥ | Gaussians | share |",
      "|---|---|---|",
    ]
    lines += [
      f"| {t:g} | {n:,} | {100.0 * n / total:.0f} % |"
      for t, n in scenes_lib.opacity_census(scene.gaussians.opacities)
    ]
    broken = total - int(scenes_lib.finite(scene.gaussians).sum())
    if broken:
      lines += [
        "",
        f"**non-finite parameters in {broken:,} of {total:,} Gaussians**: never shown or rendered",
      ]
    if dynamic:
      static = np.arange(total) < scene.num_static
      lines += [
        "",
        f"static {int((visible & static).sum()):,} / {scene.num_static:,}, "
        f"dynamic {int((visible & ~static).sum()):,} / {total - scene.num_static:,}",
      ]
    self.census.content = "\n".join(lines)

  def _draw_render(self, visible: np.ndarray) -> None:
    """The chosen target view beside our render of the shown Gaussians, upscaled to
    `render_size`, and the PSNR at the evaluation's resolution (shown set and all Gaussians)."""
    scene, view = self.scene, self._target()
    target, c2w = scene.targets.images[view], scene.targets.c2w[view]
    intrinsics = scene.targets.intrinsics[view]
    height, width = target.shape[:2]
    as_scored = functools.partial(  # as the evaluation rendered it: the run's background
      scenes_lib.render, objective=self.source.objective, context_images=scene.inputs.images
    )
    shown = scenes_lib.masked(scene.gaussians, visible)
    native = as_scored(shown, c2w, intrinsics, height, width)
    everything = as_scored(
      scenes_lib.masked(scene.gaussians, scenes_lib.finite(scene.gaussians)),
      c2w,
      intrinsics,
      height,
      width,
    )
    factor = max(1, self.render_size // max(height, width))
    large = as_scored(
      shown, c2w, scenes_lib.scaled_intrinsics(intrinsics, factor), height * factor, width * factor
    )
    gap = np.ones((height * factor, max(2, factor), 3), np.float32)
    upscaled_target = np.repeat(np.repeat(target, factor, axis=0), factor, axis=1)
    self.image.image = export.to_uint8(np.concatenate([upscaled_target, gap, large], axis=1))
    self.scores.content = (
      f"target view {view} at {width}x{height}: PSNR **{scenes_lib.psnr(native, target):.2f} "
      f"dB** with the shown Gaussians, {scenes_lib.psnr(everything, target):.2f} dB with all"
      + (" finite ones" if not scenes_lib.finite(scene.gaussians).all() else "")
      + (f" (time {scene.time:.2f})" if scene.time is not None else "")
    )

  # -- the browser's camera --------------------------------------------------------------------

  def _look_from_target(self, client, pull_back: float) -> None:
    scene = self.scene
    if client is None or scene.targets is None:
      return
    position, look_at, up = overview_pose(self._target_c2w(), scene.gaussians.means, pull_back)
    with client.atomic():
      client.camera.up_direction = up
      client.camera.position = position
      client.camera.look_at = look_at
      client.camera.fov = vertical_fov(
        scene.targets.intrinsics[self._target()], scene.targets.images.shape[1]
      )
