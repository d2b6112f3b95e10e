"""experiments/studies: the pure pieces of every study, the report of `all` (verdict rule,
aggregation over seeds, writer, every claim on constructed per-seed rows), and token_assignment,
visibility and distribution end to end.

The end-to-end runs use the `smoke` preset on a two-scene synthetic test split with freshly
initialised weights saved where the study looks for trained ones, so nothing is trained (but the
variable-view loop, three steps of the smoke model).
"""

import dataclasses
import json
import math
import pathlib

import chex
import jax
import numpy as np
import pytest
from PIL import Image

from experiments import data, pixel_baseline, re10k, weights
from experiments.studies import (
  PIXEL_ALIGNED,
  StudySettings,
  camera_noise,
  context_extension,
  distribution,
  in_views,
  psnr_of,
  report,
  test_time_scaling,
  token_assignment,
  token_count,
  trained_tokengs,
  view_extrapolation,
  visibility,
  write_table,
)
from experiments.studies import __main__ as run_all
from tokengs_jax import evaluation, model
from tokengs_jax.gaussians import Gaussians

SMOKE = re10k.PRESETS["smoke"]


def _rotation(axis, degrees: float) -> np.ndarray:
  """Rodrigues' rotation [3, 3] about a unit axis [3]."""
  x, y, z = axis
  k = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
  angle = np.deg2rad(degrees)
  return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _relative_rotation(before: np.ndarray, after: np.ndarray) -> tuple[float, np.ndarray]:
  """(angle in degrees, unit axis [3]) of R with after = before @ R (camera-frame rotation)."""
  r = before[:3, :3].T.astype(np.float64) @ after[:3, :3]
  angle = np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1)))
  axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
  return float(angle), axis / max(np.linalg.norm(axis), 1e-12)


def _random_cameras(views: int, seed: int = 0) -> np.ndarray:
  """[V, 4, 4] rigid camera-to-world matrices."""
  rng = np.random.default_rng(seed)
  c2w = np.tile(np.eye(4, dtype=np.float32), (views, 1, 1))
  for v in range(views):
    axis = rng.normal(size=3)
    c2w[v, :3, :3] = _rotation(axis / np.linalg.norm(axis), rng.uniform(0, 90))
    c2w[v, :3, 3] = rng.normal(size=3)
  return c2w


# ----------------------------------------------------------------------------------------------
# camera_noise


def test_rotate_cameras_turns_only_non_reference_cameras_about_the_axis():
  c2w = _random_cameras(3)
  axes = np.array([[1.0, 0.0, 0.0], [0.0, 0.6, 0.8], [0.0, 0.0, -1.0]])
  out = camera_noise.rotate_cameras(c2w, axes, 7.0)
  assert out.shape == (3, 4, 4) and out.dtype == np.float32
  np.testing.assert_array_equal(out[0], c2w[0])  # the reference camera is exact
  np.testing.assert_array_equal(out[:, :3, 3], c2w[:, :3, 3])  # centres stay
  np.testing.assert_array_equal(out[:, 3], c2w[:, 3])
  for v in (1, 2):
    angle, axis = _relative_rotation(c2w[v], out[v])
    assert angle == pytest.approx(7.0, abs=1e-3)
    np.testing.assert_allclose(axis, axes[v], atol=1e-3)  # right-handed, in camera coordinates
    np.testing.assert_allclose(out[v, :3, :3] @ out[v, :3, :3].T, np.eye(3), atol=1e-5)
  np.testing.assert_allclose(camera_noise.rotate_cameras(c2w, axes, 0.0), c2w, atol=1e-7)


def test_noisy_draws_one_axis_per_scene_and_view_and_grows_only_the_angle():
  rng = np.random.default_rng(0)
  examples = [
    (
      f"s{i}",
      {
        "context_c2w": _random_cameras(3, seed=i)[None],
        "context_images": rng.uniform(size=(1, 3, 2, 2, 3)),
        "target_c2w": _random_cameras(2, seed=10 + i)[None],
      },
    )
    for i in range(2)
  ]
  small = camera_noise.noisy(examples, 2.0, seed=0)
  large = camera_noise.noisy(examples, 5.0, seed=0)
  assert [key for key, _ in large] == ["s0", "s1"]
  axes = {}
  for position, (_, batch) in enumerate(examples):
    before = batch["context_c2w"][0]
    for name, degrees, result in (("small", 2.0, small), ("large", 5.0, large)):
      perturbed = result[position][1]
      assert perturbed["context_c2w"].shape == (1, 3, 4, 4)
      assert perturbed["target_c2w"] is batch["target_c2w"]  # targets stay exact
      assert perturbed["context_images"] is batch["context_images"]
      np.testing.assert_array_equal(perturbed["context_c2w"][0, 0], before[0])
      for v in (1, 2):
        angle, axes[name, position, v] = _relative_rotation(
          before[v], perturbed["context_c2w"][0, v]
        )
        assert angle == pytest.approx(degrees, abs=1e-3)
  for position in range(2):
    for v in (1, 2):  # the same axis at every angle
      np.testing.assert_allclose(axes["small", position, v], axes["large", position, v], atol=2e-3)
  assert (
    np.abs(axes["large", 0, 1] - axes["large", 1, 1]).max() > 0.1
  )  # another scene, another axis
  assert np.abs(axes["large", 0, 1] - axes["large", 0, 2]).max() > 0.1  # another view, another axis
  reseeded = camera_noise.noisy(examples, 5.0, seed=1)[0][1]["context_c2w"]
  assert np.abs(reseeded - large[0][1]["context_c2w"]).max() > 1e-3


# ----------------------------------------------------------------------------------------------
# studies/__init__.py


def test_write_table_writes_json_and_markdown(tmp_path):
  rows = [
    {"name": "a", "count": 3, "psnr": 21.123456, "extra": 1.0},
    {"name": "b", "count": 10, "psnr": 0.000123456, "extra": 2.0},
  ]
  path = write_table(
    tmp_path / "deep" / "out",
    "table",
    "A title",
    rows,
    ["name", "psnr", "count"],
    notes=["first note", "second note"],
  )
  assert path == tmp_path / "deep" / "out" / "table.md"
  payload = json.loads((tmp_path / "deep" / "out" / "table.json").read_text())
  assert payload == {"title": "A title", "rows": rows, "notes": ["first note", "second note"]}
  lines = path.read_text().splitlines()
  assert lines[0] == "# A title"
  table = lines[lines.index("| name | psnr | count |") :]
  assert table[1] == "|---|---|---|"
  assert table[2] == "| a | 21.12 | 3 |"
  assert table[3] == "| b | 0.0001235 | 10 |"
  assert "- first note" in lines and "- second note" in lines
  assert "extra" not in path.read_text()  # only the requested columns


# ----------------------------------------------------------------------------------------------
# view_extrapolation and test_time_scaling: view selection


def test_view_extrapolation_targets_inside_and_beyond_both_ends():
  settings = view_extrapolation.ViewExtrapolation(gap=4, start=2, offsets=(1, 2, 3, 8))
  frames = view_extrapolation.target_frames(settings, num_frames=10)
  # inputs at 2 and 6; +k after 6 while < 10, -k before 2 while >= 0
  assert frames == {"inside": 4, "+1": 7, "-1": 1, "+2": 8, "-2": 0, "+3": 9}
  assert list(frames) == ["inside", "+1", "-1", "+2", "-2", "+3"]
  longer = view_extrapolation.target_frames(settings, num_frames=15)
  assert longer["+8"] == 14 and "-8" not in longer and "+8" not in frames
  defaults = view_extrapolation.ViewExtrapolation()
  frames = view_extrapolation.target_frames(defaults, num_frames=24)
  assert frames["inside"] == 6 and frames["+8"] == 18 and frames["-2"] == 0 and "-4" not in frames
  with pytest.raises(ValueError, match="need 11 frames"):
    view_extrapolation.target_frames(defaults, num_frames=10)


def test_test_time_scaling_targets_are_novel_views_at_every_context_size():
  targets = test_time_scaling.shared_targets((2, 3, 4, 6), 12, 3)
  # inputs over the curve: {0, 12} | {0, 6, 12} | {0, 4, 8, 12} | {0, 2, 5, 7, 10, 12}
  np.testing.assert_array_equal(targets, [1, 9, 11])
  for count in (2, 3, 4, 6):
    context, target = test_time_scaling.spaced_views(count, 12, targets)({"images": [0] * 24}, 0)
    assert len(context) == count and context[0] == 0 and context[-1] == 12
    assert np.all(np.diff(context) > 0)
    np.testing.assert_array_equal(target, targets)
    assert not set(target.tolist()) & set(context.tolist())
  with pytest.raises(ValueError, match="larger gap"):
    test_time_scaling.shared_targets((2, 3, 4, 6), 12, 5)


# ----------------------------------------------------------------------------------------------
# token_count and token_assignment: pure pieces


@pytest.fixture(scope="module")
def smoke_model():
  """(config, params) of the smoke preset's model (4 tokens x 16 Gaussians), fresh weights."""
  config = SMOKE.model
  return config, model.init_params(jax.random.key(0), config)


def test_token_count_resamples_the_trained_table_without_retraining(smoke_model, tmp_path):
  config, params = smoke_model
  settings = token_count.TokenCount(experiment=SMOKE)
  table = np.asarray(params["gs_tokens"])
  assert table.shape == (4, config.enc_embed_dim)
  for count, rows in ((2, [0, 3]), (8, None)):
    config_k, params_k = token_count.model_for(settings, config, params, count, tmp_path)
    assert config_k == config.replace(num_gs_tokens=count)
    assert config_k.num_gaussians == count * config.gaussians_per_token
    resampled = np.asarray(params_k["gs_tokens"])
    assert resampled.shape == (count, config.enc_embed_dim)
    if rows is not None:  # fewer: evenly spaced trained rows
      np.testing.assert_array_equal(resampled, table[rows])
    else:  # more: the trained rows, then noisy copies of them
      np.testing.assert_array_equal(resampled[:4], table)
      assert 0 < np.abs(resampled[4:] - table).max() < 0.1
    # everything but the token table is the trained model's, not a fresh initialisation
    same = jax.tree.map(
      np.array_equal,
      {k: v for k, v in params.items() if k != "gs_tokens"},
      {k: v for k, v in params_k.items() if k != "gs_tokens"},
    )
    assert all(jax.tree.leaves(same))
  assert not list(tmp_path.iterdir())  # nothing trained, nothing written


def test_token_count_retrain_reuses_a_saved_model(smoke_model, tmp_path):
  config, params = smoke_model
  saved = jax.tree.map(
    lambda x: np.full_like(x, 0.25),
    token_count.model_for(token_count.TokenCount(experiment=SMOKE), config, params, 2, tmp_path)[1],
  )
  weights.save_params(tmp_path / "tokens_2.msgpack", saved)
  settings = token_count.TokenCount(experiment=SMOKE, retrain=True)
  config_k, loaded = token_count.model_for(settings, config, params, 2, tmp_path)
  assert config_k.num_gs_tokens == 2
  chex.assert_trees_all_equal(loaded, saved)


def test_token_colours_are_distinct_and_valid():
  colours = token_assignment.token_colours(64)
  assert colours.shape == (64, 3) and colours.dtype == np.float32
  assert colours.min() >= 0 and colours.max() <= 1
  distances = np.linalg.norm(colours[:, None] - colours[None], axis=-1)
  assert distances[~np.eye(64, dtype=bool)].min() > 1e-3
  assert np.linalg.norm(colours[0] - colours[1]) > 0.2  # neighbours (adjacent tokens) differ a lot
  np.testing.assert_array_equal(token_assignment.token_colours(8), colours[:8])


def test_per_token_statistics_group_consecutive_gaussians():
  """Gaussian i belongs to token i // per_token."""
  means = np.array([[-3, 0, 0], [-1, 0, 0], [0, 2, 0], [0, -2, 0]], np.float32)
  gaussians = Gaussians(
    means=means,
    opacities=np.array([0.2, 0.4, 1.0, 0.0], np.float32),
    scales=np.ones((4, 3), np.float32),
    quats=np.ones((4, 4), np.float32),
    colors=np.ones((4, 3), np.float32),
  )
  stats = token_assignment.per_token_statistics(gaussians, per_token=2)
  # token spreads 1 and 2; scene centroid (-1, 0, 0), mean distance (2 + 0 + 2 sqrt 5) / 4
  scene = (1 + math.sqrt(5)) / 2
  np.testing.assert_allclose(stats["relative_spread"], [1 / scene, 2 / scene], rtol=1e-5)
  np.testing.assert_allclose(stats["opacity"], [0.3, 0.5], rtol=1e-6)


# ----------------------------------------------------------------------------------------------
# a study end to end (smoke preset, two synthetic scenes, fresh weights)


@pytest.fixture(scope="module")
def smoke_study(tmp_path_factory, smoke_model):
  """StudySettings on a generated two-scene test split, with saved fresh weights."""
  root = tmp_path_factory.mktemp("study")
  experiment = dataclasses.replace(
    SMOKE,
    synthetic_dir=str(root / "data"),
    output_dir=str(root / "run"),
    synthetic=dataclasses.replace(SMOKE.synthetic, num_train=1, num_test=2, workers=1),
    eval=dataclasses.replace(SMOKE.eval, num_scenes=2),
  )
  data.ensure_synthetic(experiment)
  params_path = weights.save_params(root / "params.msgpack", smoke_model[1])
  return StudySettings(
    experiment=experiment, params=str(params_path), output_dir=str(root / "studies")
  )


def test_trained_tokengs_loads_saved_weights_without_training(smoke_study, smoke_model):
  config, params = trained_tokengs(smoke_study)
  assert config == smoke_model[0]
  chex.assert_trees_all_equal(params, smoke_model[1])
  assert not (pathlib.Path(smoke_study.params).parent / "checkpoints").exists()  # no training


def test_psnr_of_scores_every_scene_and_times_the_first_twice(smoke_study, smoke_model):
  """Invisible Gaussians render the grey background: PSNR = that of grey vs the targets."""
  examples = data.evaluation_scenes(smoke_study.experiment)
  assert len(examples) == 2
  calls = []
  n = smoke_model[0].num_gaussians  # the e2e test's Gaussian count: the render compiles once

  def method(batch):
    calls.append(batch)
    return Gaussians(
      means=np.tile([[[0.0, 0.0, 1.0]]], (1, n, 1)).astype(np.float32),
      opacities=np.zeros((1, n), np.float32),
      scales=np.full((1, n, 3), 0.01, np.float32),
      quats=np.tile([[[1.0, 0.0, 0.0, 0.0]]], (1, n, 1)).astype(np.float32),
      colors=np.ones((1, n, 3), np.float32),
    )

  scores, seconds = psnr_of(
    evaluation.Method(gaussians=method), examples, evaluation.Scorer(lpips=False)
  )
  assert [id(b) for b in calls] == [id(examples[0][1])] * 2 + [id(examples[1][1])]
  assert seconds >= 0 and len(scores) == 2
  for score, (_, batch) in zip(scores, examples):
    mse = np.mean((batch["target_images"][0] - 0.5) ** 2, axis=(1, 2, 3))
    assert score == pytest.approx(float(np.mean(-10 * np.log10(mse))), abs=1e-3)


def test_token_assignment_main_end_to_end(smoke_study, smoke_model):
  config = smoke_model[0]
  settings = token_assignment.TokenAssignment(
    experiment=smoke_study.experiment,
    params=smoke_study.params,
    output_dir=smoke_study.output_dir,
    num_scenes=1,
  )
  rows = token_assignment.main(settings)
  out = pathlib.Path(settings.output_dir) / "token_assignment"
  assert sorted(row["token"] for row in rows) == list(range(config.num_tokens))
  spreads = [row["relative_spread"] for row in rows]
  assert spreads == sorted(spreads)  # sorted by spread
  for row in rows:
    assert math.isfinite(row["relative_spread"]) and row["relative_spread"] > 0
    assert 0 < row["opacity"] < 1
  payload = json.loads((out / "token_assignment.json").read_text())
  assert payload["rows"] == rows
  assert payload["notes"][0].startswith("2 held-out scenes")
  table = (out / "token_assignment.md").read_text()
  assert table.count("\n| ") == 1 + len(rows)  # header + one line per token
  assert (out / "spread.png").stat().st_size > 0
  # num_scenes=1: one picture, of the first scene: 5 labelled rows (inputs, targets, renders,
  # token colours at the targets, at the inputs) of two 32x32 views upscaled 4x to 128x128
  pictures = list((out / "scenes").glob("*.png"))
  key = data.evaluation_scenes(settings.experiment)[0][0]
  assert [p.name for p in pictures] == [f"{key}.png"]
  image = np.asarray(Image.open(pictures[0]))
  assert image.shape[0] == 5 * 128 + 6 * 4 and image.shape[1] > 2 * 128 + 2 * 4
  # the token-colour rows differ from the RGB render row (the palette replaced the colours)
  render, tokens = image[4 + 2 * 132 : 4 + 2 * 132 + 128], image[4 + 3 * 132 : 4 + 3 * 132 + 128]
  assert np.abs(render.astype(int) - tokens.astype(int)).max() > 10


def test_camera_noise_needs_the_clean_angle():
  with pytest.raises(ValueError, match="must include 0"):
    camera_noise.CameraNoise(angles=(1.0, 5.0))
  assert camera_noise.CameraNoise(angles=(5.0, 0.0)).angles == (5.0, 0.0)


def test_token_assignment_names_pictures_inside_its_folder(smoke_study, monkeypatch, tmp_path):
  """A scene key like `../../../x` (from a data chunk) names a picture in scenes/, nowhere else."""
  from experiments import results

  examples = data.evaluation_scenes(smoke_study.experiment)
  monkeypatch.setattr(
    data, "evaluation_scenes", lambda *args: [("../../../escaped", examples[0][1])]
  )
  settings = token_assignment.TokenAssignment(
    experiment=smoke_study.experiment,
    params=smoke_study.params,
    output_dir=str(tmp_path / "studies"),
    num_scenes=1,
  )
  token_assignment.main(settings)
  written = {p.relative_to(tmp_path).parts[0] for p in tmp_path.rglob("*") if p.is_file()}
  assert written == {"studies"}
  scenes_folder = tmp_path / "studies" / "token_assignment" / "scenes"
  assert [p.name for p in scenes_folder.iterdir()] == [
    results.safe_file_name("../../../escaped") + ".png"
  ]


# ----------------------------------------------------------------------------------------------
# report: the verdict rule, aggregation over seeds, the writer


def test_verdict_holds_fails_or_is_not_shown_by_the_spread_of_paired_differences():
  # per-seed differences (1.0, 1.1, 0.9): mean 1.0 > their sample std 0.1
  assert report.verdict([11.0, 11.2, 10.9], [10.0, 10.1, 10.0]) == report.HOLDS
  assert report.verdict([10.0, 10.1, 10.0], [11.0, 11.2, 10.9]) == report.FAILS
  # differences (1.0, -0.5, 2.0): mean 0.83 < std 1.26
  assert report.verdict([11.0, 9.5, 12.0], [10.0, 10.0, 10.0]) == report.NOT_SHOWN
  # paired: the seeds' scenes move both sides by 10 dB, the difference is 1 dB on each
  assert report.verdict([21.0, 11.0], [20.0, 10.0]) == report.HOLDS
  assert report.difference([21.0, 11.0], [20.0, 10.0]) == "+1.00 ± 0.00"
  assert report.difference([1.0, 2.0], [2.0, 4.0], 1) == "-1.5 ± 0.7"
  # lower is better (a share, a Gini): the sign turns
  assert report.verdict([0.1, 0.11], [0.4, 0.45], higher_is_better=False) == report.HOLDS
  assert report.verdict([0.4, 0.45], [0.1, 0.11], higher_is_better=False) == report.FAILS
  # no spread to compare with: one seed; no difference; a NaN
  assert report.verdict([12.0], [10.0]) == report.NOT_SHOWN
  assert report.verdict([10.0, 10.0], [10.0, 10.0]) == report.NOT_SHOWN
  assert report.verdict([float("nan"), 1.0], [0.0, 0.0]) == report.NOT_SHOWN
  with pytest.raises(ValueError, match="unpaired"):
    report.verdict([1.0, 2.0, 3.0], [1.0, 2.0])
  # a claim of parts; a "no loss" part
  assert report.all_of([report.HOLDS, report.HOLDS]) == report.HOLDS
  assert report.all_of([report.HOLDS, report.NOT_SHOWN]) == report.NOT_SHOWN
  assert report.all_of([report.NOT_SHOWN, report.FAILS]) == report.FAILS
  assert report.no_worse([10.0, 10.1], [10.0, 10.1]) == report.HOLDS
  assert report.no_worse([10.5, 9.0], [10.0, 10.1]) == report.HOLDS  # (+0.5, -1.1): not shown
  assert report.no_worse([9.0, 9.2], [10.0, 10.1]) == report.FAILS


def test_aggregate_gives_mean_and_sample_std_per_key():
  per_seed = [
    [{"angle": 0, "psnr": 20.0, "drop": 0.0}, {"angle": 5, "psnr": 18.0, "drop": -2.0}],
    [{"angle": 0, "psnr": 22.0, "drop": 0.0}, {"angle": 5, "psnr": 19.0, "drop": -3.0}],
  ]
  rows = report.aggregate(per_seed, ["angle"], ["psnr", "drop"])
  assert [row["angle"] for row in rows] == [0, 5]
  assert rows[0]["psnr"] == "21.00 ± 1.41" and rows[1]["drop"] == "-2.50 ± 0.71"
  assert rows[1]["psnr_seeds"] == [18.0, 19.0] and rows[1]["psnr_mean"] == 18.5
  assert report.means(rows) == [
    {"angle": 0, "psnr": 21.0, "drop": 0.0},
    {"angle": 5, "psnr": 18.5, "drop": -2.5},
  ]
  assert report.mean_std([3.0]) == "3.00" and report.mean_std([1.0, 2.0], 1) == "1.5 ± 0.7"


def _fake_claim(key: str, verdict: str) -> report.Claim:
  rows = report.aggregate([[{"x": 1, "y": 2.0}], [{"x": 1, "y": 3.0}]], ["x"], ["y"])
  plot = report.Plot(f"plot_{key}", "A plot", report.series(report.means(rows), "x", ["y"]), "x")
  return report.Claim(
    key, f"claim {key}", "What the paper says.", rows, ["x", "y"], verdict, "n", plot
  )


def test_write_report_has_the_verdict_table_a_section_per_claim_and_its_plots(tmp_path):
  claims = [_fake_claim("a", report.HOLDS), _fake_claim("b", report.NOT_SHOWN)]
  path = report.write_report(tmp_path / "out" / "studies.md", claims, ["header line"], quick=True)
  text = path.read_text()
  lines = text.splitlines()
  assert lines[0].startswith("# ") and lines[2] == report.QUICK_BANNER
  assert "verdicts are a smoke test, not findings" in report.QUICK_BANNER
  assert "header line" in lines and any(line.startswith("Verdict rule: ") for line in lines)
  table = lines[lines.index("| claim | verdict | evidence |") :]
  assert table[2] == "| (a) claim a | **holds** | n |"
  assert table[3] == "| (b) claim b | **not shown at this scale** | n |"
  for claim in claims:
    section = text[text.index(f"## ({claim.key}) claim {claim.key}") :]
    assert "| x | y |" in section and "| 1 | 2.50 ± 0.71 |" in section
    assert f"**Verdict: {claim.verdict}.** n" in section
    link = f"studies/plot_{claim.key}.png"
    assert f"![claim {claim.key}]({link})" in section
    assert (path.parent / link).stat().st_size > 0  # the link resolves beside the report
  assert text.count("**Verdict: ") == 2
  full = report.write_report(tmp_path / "full.md", claims[:1], [], quick=False).read_text()
  assert report.QUICK_BANNER not in full


def _per_seed_rows(seed: int) -> dict:
  """Constructed rows of one seed for every study of `all`, each making its claim hold."""
  jitter = 0.01 * seed
  p = PIXEL_ALIGNED
  tuning = [
    {
      "axis": f"{target} tuning steps",
      "value": n,
      "psnr": 20 + n * gain + jitter,
      "seconds_per_scene": n * cost,
    }
    for target, gain, cost in (("tokens", 0.1, 0.02), ("gaussians", 0.05, 0.015))
    for n in (5, 10)
  ]
  return {
    camera_noise: [
      {
        "angle_deg": a,
        "TokenGS": 20 - a * 0.1,
        p: 22 - a,
        "TokenGS drop": -a * 0.1 + jitter,
        f"{p} drop": -a,
      }
      for a in (0.0, 5.0)
    ],
    view_extrapolation: [
      {
        "target": t,
        "frames_outside_span": d,
        "scenes": 2,
        "TokenGS": 18 - d * 0.1,
        p: 18 - d + jitter,
      }
      for t, d in (("inside", 0), ("+2", 2), ("-2", 2))
    ],
    context_extension: [
      {"views": v, "trained with 2 views": 20.0, "trained with 2-4 views": 20 + v * 0.1 + jitter}
      for v in (2, 3, 4)
    ],
    test_time_scaling: [
      {"axis": "input views", "value": 2, "psnr": 20.0, "seconds_per_scene": 0.01},
      {"axis": "no tuning (2 views)", "value": 0, "psnr": 20.0, "seconds_per_scene": 0.01},
      *tuning,
    ],
    token_count: [
      {
        "tokens": k,
        "gaussians": 16 * k,
        "tuning_steps": 0,
        "psnr": 19 + k / 64 + jitter,
        "seconds_per_scene": 0.01,
      }
      for k in (128, 64)
    ],
    visibility: [
      {"visibility loss": "on", "psnr": 20.0 + jitter, "outside_share": 0.01},
      {"visibility loss": "off", "psnr": 20.0 - jitter, "outside_share": 0.2 + jitter},
    ],
    distribution: [
      *(
        {"bin": b, "depth_from": b, "depth_to": b + 1, "TokenGS": 1.0, p: 2.0 - b / 2}
        for b in (1, 2, 3)
      ),
      {"bin": distribution.GINI, "TokenGS": 0.1 + jitter, p: 0.4},
    ],
  }


def test_every_claim_of_all_builds_from_per_seed_rows(tmp_path):
  seeds = [_per_seed_rows(seed) for seed in range(3)]
  claims = [study.claim([rows[study] for rows in seeds]) for study in run_all.STUDIES]
  assert [claim.key for claim in claims] == list("abcdefg")
  assert [claim.verdict for claim in claims] == [report.HOLDS] * 7
  path = report.write_report(tmp_path / "studies.md", claims, [], quick=False)
  for claim in claims:
    assert (tmp_path / report.FIGURES / f"{claim.plot.name}.png").exists()
    assert set(claim.columns) <= set(claim.rows[0])
  assert path.read_text().count("**Verdict: holds.**") == 7
  # the same rows with TokenGS's drop the larger: (a) fails
  # (a) with TokenGS's drop twice the baseline's (-10 vs -5 dB at 5 degrees): fails; with
  # differences -5 and +5 dB over the seeds (mean 0, spread 7.1) it is not shown
  worse = [
    {**row, "TokenGS drop": row[f"{PIXEL_ALIGNED} drop"] * 2} for row in seeds[0][camera_noise]
  ]
  assert camera_noise.claim([worse, worse]).verdict == report.FAILS
  spread = [{**row, "TokenGS drop": 0.0} for row in worse]
  assert camera_noise.claim([worse, spread]).verdict == report.NOT_SHOWN


# ----------------------------------------------------------------------------------------------
# the pure pieces of the new studies


def test_gini_relative_density_and_per_bin_counts():
  assert distribution.gini(np.ones(4), np.ones(4)) == pytest.approx(0.0)
  assert distribution.gini(np.array([0, 0, 0, 4.0]), np.ones(4)) == pytest.approx(0.75)
  # weights count as repeated values: (0, 0, 0, 4) == values (0, 4) with weights (3, 1)
  assert distribution.gini(np.array([0, 4.0]), np.array([3.0, 1.0])) == pytest.approx(0.75)
  density = distribution.relative_density(np.array([2.0, 2.0, 0.0]), np.array([1.0, 3.0, 0.0]))
  np.testing.assert_allclose(density, [2.0, 2.0 / 3.0, 0.0])  # 4 Gaussians over area 4: 1 / unit
  edges = np.array([0.5, 1.5, 3.0])
  depths = np.array([[[1.0, 2.0], [0.0, 2.0]]])  # one view, one pixel without a surface
  np.testing.assert_allclose(
    distribution.area_per_bin(depths, np.array([[2.0, 0.5, 1.0, 1.0]]), edges), [1.0, 8.0]
  )
  inside = np.array([[True, True, False], [True, False, True]])
  depth = np.array([[1.0, 2.0, 1.0], [1.0, 9.0, 2.0]])
  counts = distribution.gaussians_per_bin(inside, depth, np.array([0.5, 1.0, 0.25]), edges)
  np.testing.assert_allclose(counts, [1.0, 1.25])  # view 0: 0.5 | 1.0; view 1: 0.5 | 0.25


def test_in_views_marks_centres_in_front_and_inside_each_image():
  c2w = np.stack([np.eye(4), np.eye(4)]).astype(np.float32)
  c2w[1, 0, 3] = 2.0  # the second camera 2 to the right
  intrinsics = np.array([[10.0, 10.0, 8.0, 8.0]] * 2, np.float32)
  means = np.array([[0, 0, 1], [0, 0, -1], [2, 0, 1], [0, 0, 0.01]], np.float32)
  inside, depth = in_views(means, c2w, intrinsics, 16, 16, near=0.025)
  np.testing.assert_array_equal(inside, [[True, False, False, False], [False, False, True, False]])
  np.testing.assert_allclose(depth[0], [1, -1, 1, 0.01])


def test_outside_share_counts_centres_in_no_input_view():
  batch = {
    "context_images": np.zeros((1, 2, 16, 16, 3), np.float32),
    "context_c2w": np.eye(4, dtype=np.float32)[None, None].repeat(2, axis=1),
    "context_intrinsics": np.array([[[10.0, 10.0, 8.0, 8.0]] * 2], np.float32),
  }
  means = np.array([[[0, 0, 1], [0, 0, -1], [5, 0, 1], [0, 0.1, 2]]], np.float32)
  method = evaluation.Method(
    gaussians=lambda b: Gaussians(
      means=means,
      opacities=np.ones((1, 4), np.float32),
      scales=np.ones((1, 4, 3), np.float32),
      quats=np.ones((1, 4, 4), np.float32),
      colors=np.ones((1, 4, 3), np.float32),
    )
  )
  assert visibility.outside_share(method, [("s", batch)], near=0.025) == pytest.approx(0.5)


def test_view_schedule_tuning_time_and_distance_rows():
  schedule = context_extension.view_schedule(0, 300, (2, 3, 4))
  assert set(schedule.tolist()) == {2, 3, 4} and len(schedule) == 300
  np.testing.assert_array_equal(schedule, context_extension.view_schedule(0, 300, (2, 3, 4)))
  assert not np.array_equal(schedule, context_extension.view_schedule(1, 300, (2, 3, 4)))
  curve = [{"seconds_per_scene": 0.2, "psnr": 12.0}, {"seconds_per_scene": 0.1, "psnr": 10.0}]
  assert test_time_scaling.psnr_at_time(curve, 0.15) == pytest.approx(11.0)
  assert math.isnan(test_time_scaling.psnr_at_time(curve, 0.3))  # beyond it: not measured
  # equal time: token tuning at 10 steps (0.2 s) is the longest the Gaussian curve reaches (0.3 s)
  tuning = [
    {"axis": test_time_scaling.UNTUNED, "value": 0, "psnr": 10.0, "seconds_per_scene": 0.0},
    *(
      {"axis": axis, "value": n, "psnr": 10 + n * gain, "seconds_per_scene": n * cost}
      for axis, gain, cost in (
        (test_time_scaling.TOKENS, 0.2, 0.02),
        ("gaussians tuning steps", 0.1, 0.01),
      )
      for n in (10, 30)
    ),
  ]
  assert test_time_scaling.equal_time(tuning) == pytest.approx((12.0, 12.0))  # 20 Gaussian steps
  slower = [
    {**r, "seconds_per_scene": 10 * r["seconds_per_scene"]}
    if r["axis"] == test_time_scaling.TOKENS
    else r
    for r in tuning
  ]
  assert all(math.isnan(x) for x in test_time_scaling.equal_time(slower))
  rows = [
    {"frames_outside_span": 0, "m": 3.0},
    {"frames_outside_span": 2, "m": 1.0},
    {"frames_outside_span": 2, "m": 2.0},
  ]
  assert view_extrapolation.by_distance(rows, ["m"]) == [
    {"frames": 0, "m": 3.0},
    {"frames": 2, "m": 1.5},
  ]


# ----------------------------------------------------------------------------------------------
# all: scale, per-seed experiments, the work folder, the command line


def test_all_scales_seed_experiments_and_command_line(tmp_path):
  quick = run_all.All(quick=True).scale()
  assert quick.seeds == 2 and quick.steps < run_all.FULL.steps
  assert run_all.All(seeds=5, steps=7).scale() == dataclasses.replace(
    run_all.FULL, seeds=5, steps=7
  )
  default = re10k.PRESETS["synthetic-tiny"]
  experiments = [run_all.seed_experiment(quick, seed, tmp_path) for seed in (0, 1)]
  for seed, experiment in enumerate(experiments):
    assert experiment.seed == seed and experiment.checkpoint is None  # from scratch
    assert experiment.model == default.model and experiment.train.steps == quick.steps
    assert experiment.train.learning_rate == re10k.PRESETS["pretrain"].train.learning_rate
    assert experiment.synthetic.num_train == quick.train_scenes
  assert experiments[0].synthetic_dir != experiments[1].synthetic_dir
  assert experiments[0].output_dir != experiments[1].output_dir
  settings = run_all.study_settings(quick, experiments[0])
  assert list(settings) == list(run_all.STUDIES)
  assert all(s.experiment is experiments[0] for s in settings.values())
  assert settings[token_count].retrain and settings[token_count].tokens == quick.tokens
  run_all.check_work_dir(tmp_path / "work", quick)
  run_all.check_work_dir(tmp_path / "work", quick)  # the same scale: reused
  with pytest.raises(SystemExit, match="another scale"):
    run_all.check_work_dir(tmp_path / "work", run_all.FULL)
  import tyro

  parsed = tyro.extras.subcommand_cli_from_dict(
    {"all": run_all.All}, args=["all", "--quick", "--seeds", "3", "--output-dir", "x"]
  )
  assert parsed == run_all.All(quick=True, seeds=3, output_dir="x")
  assert parsed.work() == pathlib.Path("outputs/studies/all_quick")


# ----------------------------------------------------------------------------------------------
# the new studies end to end (smoke preset, fresh weights)


def _with_fresh_baseline(smoke_study, smoke_model, tmp_path):
  """smoke_study's settings with a saved, freshly initialised pixel-aligned baseline."""
  path = weights.save_params(
    tmp_path / "baseline.msgpack", pixel_baseline.init_params(jax.random.key(1), smoke_model[0])
  )
  return dict(
    experiment=smoke_study.experiment,
    params=smoke_study.params,
    baseline_params=str(path),
    output_dir=str(tmp_path / "studies"),
  )


def test_distribution_main_end_to_end(smoke_study, smoke_model, tmp_path):
  settings = distribution.Distribution(
    **_with_fresh_baseline(smoke_study, smoke_model, tmp_path), bins=3
  )
  rows = distribution.main(settings)
  assert [row["bin"] for row in rows] == [1, 2, 3, distribution.GINI]
  for name in distribution.METHODS:
    densities = np.array([row[name] for row in rows[:3]])
    assert np.all(np.isfinite(densities)) and np.all(densities >= 0)
    assert 0 <= rows[-1][name] < 1
  assert rows[0]["depth_from"] < rows[0]["depth_to"] <= rows[1]["depth_from"]
  out = pathlib.Path(settings.output_dir) / "distribution"
  assert json.loads((out / "distribution.json").read_text())["rows"] == rows
  assert (out / "distribution.png").stat().st_size > 0


def test_visibility_main_end_to_end(smoke_study, smoke_model, tmp_path):
  ablation = weights.save_params(
    tmp_path / "off.msgpack", model.init_params(jax.random.key(2), smoke_model[0])
  )
  settings = visibility.Visibility(
    **_with_fresh_baseline(smoke_study, smoke_model, tmp_path), ablation_params=str(ablation)
  )
  rows = visibility.main(settings)
  assert [row["visibility loss"] for row in rows] == ["on", "off"]
  for row in rows:
    assert math.isfinite(row["psnr"]) and 0 <= row["outside_share"] <= 1
  assert (pathlib.Path(settings.output_dir) / "visibility" / "visibility.png").exists()


@pytest.mark.slow  # compiles a train step per view count
def test_train_variable_views_changes_the_weights(smoke_study, smoke_model):
  experiment = dataclasses.replace(  # a batch of 4: one example per (virtual) device
    smoke_study.experiment,
    train=dataclasses.replace(smoke_study.experiment.train, steps=3, batch_size=4),
  )
  trained = context_extension.train_variable_views(experiment, smoke_model[1], (2, 3))
  changed = jax.tree.map(lambda a, b: not np.array_equal(a, b), trained, smoke_model[1])
  assert any(jax.tree.leaves(changed))
  assert all(np.all(np.isfinite(leaf)) for leaf in jax.tree.leaves(trained))
