"""experiments.view: the scenes it shows, its GUI state, the viewer in headless Chromium."""

import dataclasses
import json
import re
import socket
import urllib.request

import jax
import numpy as np
import pytest
from PIL import Image

from experiments import data, kubric, re10k, weights
from experiments.kubric_task import KubricExperiment, KubricTask
from experiments.tasks import Task
from experiments.viewer import browser, scenes
from experiments.viewer import server as viewer_server
from experiments.viewer.app import READY_TEXT, novel_target, vertical_fov
from tokengs_jax import evaluation, model
from tokengs_jax.gaussians import Gaussians
from tokengs_jax.objective import ObjectiveConfig


def _gaussians(n, seed=0):
  rng = np.random.default_rng(seed)
  return Gaussians(
    means=rng.normal(size=(n, 3)).astype(np.float32),
    opacities=rng.uniform(0, 1, n).astype(np.float32),
    scales=rng.uniform(0.01, 0.3, (n, 3)).astype(np.float32),
    quats=rng.normal(size=(n, 4)).astype(np.float32),
    colors=rng.uniform(0, 1, (n, 3)).astype(np.float32),
  )


def test_covariances_are_rotated_squared_scales():
  g = _gaussians(16)
  cov = scenes.covariances(g.scales, g.quats)
  np.testing.assert_allclose(cov, np.swapaxes(cov, -1, -2), atol=1e-7)
  np.testing.assert_allclose(np.linalg.eigvalsh(cov), np.sort(g.scales**2, axis=-1), atol=1e-6)
  # 30 degrees about z (wxyz, any norm): R diag(1, 4, 9) R^T, R = [[c, -s], [s, c]] in xy
  c, s = np.cos(np.pi / 6), np.sin(np.pi / 6)
  quat = 2 * np.float32([[np.cos(np.pi / 12), 0, 0, np.sin(np.pi / 12)]])
  expected = [[c * c + 4 * s * s, -3 * c * s, 0], [-3 * c * s, s * s + 4 * c * c, 0], [0, 0, 9]]
  np.testing.assert_allclose(
    scenes.covariances(np.float32([[1, 2, 3]]), quat)[0], expected, atol=1e-5
  )


def test_selection_by_opacity_and_part():
  g = dataclasses.replace(_gaussians(6), opacities=np.array([0.0, 0.2, 0.9, 0.05, 0.6, 1.0]))
  scene = scenes.ViewScene("s", g, num_static=4)
  assert scenes.selection(scene, 0.0).all()
  assert scenes.selection(scene, 0.5).tolist() == [False, False, True, False, True, True]
  assert scenes.selection(scene, 0.1, show_dynamic=False).tolist() == [
    False,
    True,
    True,
    False,
    False,
    False,
  ]
  assert scenes.selection(scene, 0.1, show_static=False).tolist() == [False] * 4 + [True, True]
  assert scenes.opacity_census(g.opacities, (0.05, 0.5)) == [(0.05, 5), (0.5, 3)]


def test_novel_target_is_the_first_target_that_is_no_input():
  def cameras(xs):
    c2w = np.tile(np.eye(4, dtype=np.float32), (len(xs), 1, 1))
    c2w[:, 0, 3] = xs
    return scenes.Cameras(np.zeros((len(xs), 2, 2, 3)), c2w, np.ones((len(xs), 4)))

  scene = scenes.ViewScene("s", _gaussians(2), 2, cameras([0.0, 2.0]), cameras([0.0, 1.0, 2.0]))
  assert novel_target(scene) == 1
  assert novel_target(dataclasses.replace(scene, targets=cameras([2.0, 0.0]))) == 0


def test_masked_render_equals_the_render_of_the_subset():
  """The viewer hides Gaussians by zero opacity (fixed shapes): same image as dropping them, also
  when a hidden one has non-finite parameters (never shown)."""
  g = _gaussians(24, seed=1)
  g = dataclasses.replace(g, means=g.means * 0.5 + np.float32([0, 0, 3]), scales=g.scales * 0.5)
  g.means[3, 1], g.scales[5, 0], g.opacities[7] = np.nan, np.inf, np.nan
  scene = scenes.ViewScene("s", g, num_static=24)
  visible = scenes.selection(scene, 0.4)
  expected = np.nan_to_num(g.opacities) >= 0.4
  expected[[3, 5, 7]] = False
  np.testing.assert_array_equal(visible, expected)
  assert all(np.isfinite(x).all() for x in jax.tree.leaves(scenes.masked(g, visible)))
  c2w, intrinsics = np.eye(4, dtype=np.float32), np.float32([20, 20, 8, 8])
  subset = jax.tree.map(lambda x: x[visible], g)
  np.testing.assert_allclose(
    scenes.render(scenes.masked(g, visible), c2w, intrinsics, 16, 16),
    scenes.render(subset, c2w, intrinsics, 16, 16),
    atol=1e-5,
  )


@pytest.mark.parametrize(
  "preset",
  [
    re10k.PRESETS["synthetic-tiny"],
    re10k.PRESETS["paper"],
    kubric.PRESETS["synthetic-tiny"],
    kubric.PRESETS["paper"],
  ],
)
def test_experiment_round_trips_through_metrics_json(preset):
  fields = json.loads(json.dumps(dataclasses.asdict(preset), default=str))
  experiment, task = scenes.experiment_from_fields(fields)
  assert experiment == preset
  assert isinstance(task, KubricTask) == isinstance(preset, KubricExperiment)
  with pytest.raises(ValueError, match="no fields"):
    scenes.experiment_from_fields({**fields, "not_a_field": 1})


@pytest.fixture(scope="module")
def results(tmp_path_factory):
  """A results folder as the entry points write it (settings + weights), for the smoke model with
  a spread-out head initialisation (the official one starts every Gaussian in one clump)."""
  root = tmp_path_factory.mktemp("view")
  smoke = re10k.PRESETS["smoke"]
  experiment = dataclasses.replace(
    smoke,
    output_dir=str(root / "results"),
    synthetic_dir=str(root / "data"),
    model=smoke.model.replace(clip_head_readout_std=0.3),
  )
  data.ensure_synthetic(experiment)
  out = root / "results"
  weights.save_params(
    out / "params.msgpack", model.init_params(jax.random.key(0), experiment.model)
  )
  (out / "metrics.json").write_text(
    json.dumps({"title": "smoke", "experiment": dataclasses.asdict(experiment)}, default=str)
  )
  return out, experiment


def test_results_source_rebuilds_the_evaluation_scenes(results):
  out, experiment = results
  source = scenes.open_source(out)
  examples = data.evaluation_scenes(experiment)
  assert source.keys == [key for key, _ in examples]
  scene = source.scene(1)
  assert scene.num_gaussians == scene.num_static == experiment.model.num_gaussians
  assert scene.key == examples[1][0] and scene.time is None
  np.testing.assert_array_equal(scene.inputs.images, examples[1][1]["context_images"][0])
  np.testing.assert_array_equal(scene.targets.c2w, examples[1][1]["target_c2w"][0])
  assert source.scene(1) is scene  # reconstructed once
  # the same network output as the evaluation's
  expected = evaluation.gaussians_for_batch(source.params, examples[1][1], experiment.model)
  np.testing.assert_allclose(scene.gaussians.means, np.asarray(expected.means)[0], atol=1e-6)


def test_open_source_refuses_what_it_cannot_show(results, tmp_path):
  with pytest.raises(FileNotFoundError, match="results folder"):
    scenes.open_source(tmp_path)
  with pytest.raises(ValueError, match="results folders"):
    scenes.open_source(tmp_path / "g.ply", checkpoint="x")


def test_opening_a_results_folder_writes_no_data_unless_asked(results, tmp_path):
  """metrics.json names a synthetic set that is not there: opening the folder refuses in one line
  naming the flag and writes nothing; with the flag the set is written."""
  out, experiment = results
  folder = tmp_path / "results"
  folder.mkdir()
  absent = tmp_path / "absent"
  fields = {**dataclasses.asdict(experiment), "synthetic_dir": str(absent)}
  (folder / "metrics.json").write_text(json.dumps({"experiment": fields}, default=str))
  with pytest.raises(FileNotFoundError, match="--generate-data") as refused:  # GenerationRefused
    scenes.open_source(folder, checkpoint=str(out / "params.msgpack"))
  assert "\n" not in str(refused.value) and str(absent) in str(refused.value)
  assert sorted(p.name for p in tmp_path.iterdir()) == ["results"]
  assert sorted(p.name for p in folder.iterdir()) == ["metrics.json"]
  source = scenes.open_source(folder, checkpoint=str(out / "params.msgpack"), generate_data=True)
  assert len(source.keys) == len(data.evaluation_scenes(experiment)) and absent.is_dir()


def test_the_target_render_uses_the_runs_background():
  """What the viewer shows beside a target is what the evaluation scored: an empty scene renders
  the objective's background, the inputs' mean colour under "input_mean"."""
  empty = scenes.masked(_gaussians(4), np.zeros(4, bool))
  c2w, intrinsics = np.eye(4, dtype=np.float32), np.float32([8.0, 8.0, 4.0, 4.0])
  grey = scenes.render(empty, c2w, intrinsics, 8, 8)
  np.testing.assert_allclose(grey, np.broadcast_to(ObjectiveConfig().background, grey.shape))
  inputs = np.zeros((2, 8, 8, 3), np.float32)
  inputs[0] = (1.0, 0.2, 0.0)  # mean (0.5, 0.1, 0.0)
  mean = scenes.render(
    empty, c2w, intrinsics, 8, 8, ObjectiveConfig(background="input_mean"), context_images=inputs
  )
  np.testing.assert_allclose(mean, np.broadcast_to((0.5, 0.1, 0.0), mean.shape), atol=1e-6)


def _free_port() -> int:
  with socket.socket() as s:
    s.bind(("127.0.0.1", 0))
    return s.getsockname()[1]


@pytest.fixture(scope="module")
def viewer(results):
  from experiments import view

  server, app, _ = view.start(
    view.ViewSettings(
      str(results[0]), port=_free_port(), render_size=64, pull_back=0.0, background=(1.0, 1.0, 1.0)
    )
  )  # the untrained model's grey splats show on white
  yield server, app
  server.stop()


def test_same_page_origin_only():
  assert viewer_server.same_page_origin("http://127.0.0.1:8080", "127.0.0.1:8080")
  assert viewer_server.same_page_origin("http://localhost:8080", "localhost:8080")
  assert viewer_server.same_page_origin("http://[::1]:8080", "[::1]:8080")
  assert viewer_server.same_page_origin("http://10.1.2.3:8080", "10.1.2.3:8080")  # --host 0.0.0.0
  assert not viewer_server.same_page_origin("http://evil.example", "127.0.0.1:8080")
  assert not viewer_server.same_page_origin("http://127.0.0.1:9999", "127.0.0.1:8080")
  assert not viewer_server.same_page_origin(None, "127.0.0.1:8080")  # no browser
  # a name rebound to this machine by its DNS: same "origin" as Host, still another site's page
  assert not viewer_server.same_page_origin("http://evil.example:8080", "evil.example:8080")


def test_viewer_websocket_answers_only_its_own_page(viewer):
  """Another site's page (or a client without an Origin) gets HTTP 403 at the handshake; the
  page the viewer served connects."""
  import viser
  from websockets.exceptions import InvalidStatus
  from websockets.sync.client import connect

  port = viewer[0].get_port()
  url, protocol = f"ws://127.0.0.1:{port}", [f"viser-v{viser.__version__}"]
  for origin in ("http://evil.example", None):
    with pytest.raises(InvalidStatus) as refused:
      connect(url, origin=origin, subprotocols=protocol, open_timeout=10)
    assert refused.value.response.status_code == 403
  with connect(url, origin=f"http://127.0.0.1:{port}", subprotocols=protocol, open_timeout=10):
    pass


def test_viewer_state_follows_the_controls(viewer):
  _, app = viewer
  scene = app.scene
  assert app.image.image.shape == (64, 64 + 2 * 1 + 64, 3)  # target | gap | render, 2x upscaled
  assert app.source.objective == Task().objective(app.source.experiment)
  assert "PSNR" in app.scores.content
  assert f"**{scene.num_gaussians:,} / {scene.num_gaussians:,}**" in app.census.content
  threshold = round(float(np.median(scene.gaussians.opacities)), 2)
  app.threshold.value = threshold  # the callback runs synchronously
  kept = int(np.sum(scene.gaussians.opacities >= threshold))
  assert 0 < kept < scene.num_gaussians
  assert f"**{kept:,} / {scene.num_gaussians:,}**" in app.census.content
  app.show_static.value = False  # a static model: nothing left but the background
  assert f"**0 / {scene.num_gaussians:,}**" in app.census.content
  background = np.asarray(ObjectiveConfig().background, np.float32) * 255
  assert np.abs(app.image.image[:, 66:] - background).max() <= 1
  app.show_static.value = True
  app.threshold.value = 0.0
  app.scene_index.value = 1
  assert app.scene.key == app.source.keys[1]
  view = app.target_view.value  # a new scene shows its first target that is not an input view
  assert view == novel_target(app.scene) and f"target view {view} " in app.scores.content


def _screenshot(url, path) -> np.ndarray:
  path = browser.screenshot(url, path, ready_text=READY_TEXT, width=960, height=720)
  return np.asarray(Image.open(path).convert("RGB")).astype(np.float32)


@pytest.mark.skipif(
  browser.find_chromium() is None,
  reason="needs Chromium: apt-get install -y chromium (docs/viewer.md)",
)
def test_viewer_draws_the_splats_in_headless_chromium(viewer, tmp_path):
  """The page needs nothing from the web; with the browser at the target camera, the splats are
  drawn where the Gaussians project (compared with a capture without them)."""
  server, app = viewer
  url = f"http://127.0.0.1:{server.get_port()}/"
  page = urllib.request.urlopen(url, timeout=10).read().decode()
  assert not re.search(r"""(src|href)=["']?(https?:)?//""", page), "the client loads from the web"
  app.scene_index.value = 0
  app.threshold.value = 0.0
  app.show_cameras.value = False  # the splats alone
  with_splats = _screenshot(url, tmp_path / "on.png")
  assert with_splats.shape == (720, 960, 3)
  app.show_static.value = False
  without = _screenshot(url, tmp_path / "off.png")
  app.show_static.value = app.show_cameras.value = True
  canvas = np.s_[:, :600]  # left of viser's control panel
  assert without[canvas].std() < with_splats[canvas].std()
  rows, columns = np.nonzero(np.abs(with_splats - without)[canvas].max(axis=-1) > 24)
  assert len(rows) > 1000, f"only {len(rows)} pixels show splats"
  # where the Gaussians' (opacity-weighted) centre projects in the browser's camera
  scene, view = app.scene, app.target_view.value
  c2w = scene.targets.c2w[view]
  local = (scene.gaussians.means - c2w[:3, 3]) @ c2w[:3, :3]
  x, y, z = np.average(local, axis=0, weights=scene.gaussians.opacities)
  fov = vertical_fov(scene.targets.intrinsics[view], scene.targets.images.shape[1])
  focal = 360 / np.tan(fov / 2)  # pixels, in the 720-pixel-high window
  np.testing.assert_allclose(
    [columns.mean(), rows.mean()], [480 + focal * x / z, 360 + focal * y / z], atol=10
  )


class _DynamicSource:
  """Two hand-made dynamic scenes (3 static + 3 dynamic Gaussians in front of one camera; the
  second has a Gaussian with a NaN centre)."""

  title, keys, time_conditioned = "dynamic", ["a", "b"], True
  objective = ObjectiveConfig()  # the render settings every source names

  def default_time(self, index):
    return 0.25 * (index + 1)

  def scene(self, index, time=None):
    g = _gaussians(6, seed=index)
    g = dataclasses.replace(
      g,
      means=g.means * 0.3 + np.float32([0, 0, 2]),
      opacities=np.float32([0.9, 0.2, 0.8, 0.7, 0.05, 0.6]),
    )
    g.means[4, 0] = np.nan if index == 1 else g.means[4, 0]
    camera = scenes.Cameras(
      np.zeros((1, 8, 8, 3), np.float32),
      np.eye(4, dtype=np.float32)[None],
      np.float32([[10, 10, 4, 4]]),
    )
    return scenes.ViewScene(self.keys[index], g, 3, camera, camera, time)


def test_viewer_dynamic_controls():
  import viser

  from experiments.viewer.app import ViewerApp

  server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
  try:
    app = ViewerApp(_DynamicSource(), server, render_size=16)
    assert app.time.value == 0.25 and app.scene.time == 0.25
    assert "static 3 / 3, dynamic 3 / 3" in app.census.content
    app.show_dynamic.value = False
    assert "**3 / 6**" in app.census.content and "dynamic 0 / 3" in app.census.content
    app.threshold.value = 0.5
    assert "**2 / 6**" in app.census.content
    app.time.value = 0.9
    assert app.scene.time == 0.9 and app.time.value == 0.9
    app.scene_index.value = 1  # a new scene starts at its own first target time
    assert app.scene.key == "b" and app.scene.time == 0.5
    assert "**non-finite parameters in 1 of 6 Gaussians**" in app.census.content
    assert "with all finite ones" in app.scores.content
  finally:
    server.stop()


class _KeyedSource(_DynamicSource):
  """`_DynamicSource` with scene keys as a data chunk may hold them, saving under `folder`."""

  def __init__(self, keys, folder):
    self.keys, self.folder = keys, folder


def test_viewer_saves_inside_its_folder_whatever_the_scene_key(tmp_path):
  import viser

  from experiments import results
  from experiments.viewer.app import ViewerApp

  outside = tmp_path / "outside" / "x"  # absolute: where the key alone would have put it
  source = _KeyedSource(["../../escaped", str(outside)], tmp_path / "results")
  server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
  try:
    app = ViewerApp(source, server, render_size=16)
    saved = [app.save_shown()]
    app.scene_index.value = 1
    saved.append(app.save_shown())
  finally:
    server.stop()
  assert [p.parent for p in saved] == [tmp_path / "results" / "viewer"] * 2
  assert [p.name for p in saved] == [
    results.safe_file_name(f"{key}_opacity0.00_time0.{t}") + ".ply"
    for key, t in zip(source.keys, (25, 50))
  ]
  assert [p.relative_to(tmp_path).parts[0] for p in tmp_path.rglob("*.ply")] == ["results"] * 2


def test_viewer_shows_a_ply(tmp_path):
  import viser

  from experiments.viewer.app import ViewerApp
  from tokengs_jax import export

  g = _gaussians(9)
  path = export.write_ply(tmp_path / "g.ply", **dataclasses.asdict(g))
  source = scenes.open_source(path)
  assert source.keys == ["g"] and not source.time_conditioned
  np.testing.assert_allclose(source.scene(0).gaussians.means, g.means, atol=1e-6)
  server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
  try:
    app = ViewerApp(source, server)
    assert app.scene_index is None and app.time is None
    assert "**9 / 9**" in app.census.content and app.scores.content == ""
    app.threshold.value = 0.5
    kept = g.opacities >= 0.5
    saved = export.read_ply(app.save_shown())  # the pruned set, as a viewer-readable PLY
    assert saved["means"].shape == (kept.sum(), 3) and str(tmp_path / "viewer") in app.saved.content
    np.testing.assert_allclose(saved["opacities"], g.opacities[kept], atol=1e-5)
  finally:
    server.stop()
