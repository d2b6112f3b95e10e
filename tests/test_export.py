import numpy as np
import plyfile
import pytest

from tokengs_jax import export


def _gaussians(n=50, seed=0):
  rng = np.random.default_rng(seed)
  return dict(
    means=rng.normal(size=(n, 3)),
    opacities=rng.uniform(0.05, 0.95, n),
    scales=rng.uniform(0.01, 0.2, (n, 3)),
    quats=rng.normal(size=(n, 4)),
    colors=rng.uniform(0, 1, (n, 3)),
  )


def test_ply_round_trip_in_viewer_layout(tmp_path):
  g = _gaussians()
  path = export.write_ply(tmp_path / "g.ply", **g)
  header = path.read_bytes().split(b"end_header")[0].decode()
  for name in ("f_dc_0", "opacity", "scale_0", "rot_3", "nx"):
    assert f"property float {name}" in header
  back = export.read_ply(path)
  q = g["quats"] / np.linalg.norm(g["quats"], axis=-1, keepdims=True)
  np.testing.assert_allclose(back["quats"], q, atol=1e-6)
  for k in ("means", "opacities", "scales", "colors"):
    np.testing.assert_allclose(back[k], g[k], rtol=1e-4, atol=1e-5)


def test_ply_read_by_plyfile_in_the_3dgs_layout(tmp_path):
  """An independent reader (plyfile) sees the reference 3DGS vertex layout, float32 little endian,
  and the pre-activation values viewers decode: SH DC colour, logit opacity, log scale, unit
  wxyz."""
  g = _gaussians(37, seed=3)
  ply = plyfile.PlyData.read(str(export.write_ply(tmp_path / "g.ply", **g)))
  assert ply.byte_order == "<" and not ply.text
  vertex = ply["vertex"]
  names = [
    "x",
    "y",
    "z",
    "nx",
    "ny",
    "nz",
    "f_dc_0",
    "f_dc_1",
    "f_dc_2",
    "opacity",
    "scale_0",
    "scale_1",
    "scale_2",
    "rot_0",
    "rot_1",
    "rot_2",
    "rot_3",
  ]
  assert [p.name for p in vertex.properties] == names
  assert all(vertex.data.dtype[name] == np.dtype("<f4") for name in names)
  assert vertex.count == 37
  column = lambda *keys: np.stack([vertex[k] for k in keys], axis=-1)
  sh_c0 = 1.0 / (2.0 * np.sqrt(np.pi))  # Y_0^0
  np.testing.assert_allclose(column("x", "y", "z"), g["means"], rtol=1e-6, atol=1e-6)
  np.testing.assert_array_equal(column("nx", "ny", "nz"), 0.0)
  np.testing.assert_allclose(
    column("f_dc_0", "f_dc_1", "f_dc_2"), (g["colors"] - 0.5) / sh_c0, rtol=1e-5, atol=1e-5
  )
  np.testing.assert_allclose(
    vertex["opacity"], np.log(g["opacities"] / (1 - g["opacities"])), rtol=1e-4, atol=1e-5
  )
  np.testing.assert_allclose(
    column("scale_0", "scale_1", "scale_2"), np.log(g["scales"]), rtol=1e-5, atol=1e-5
  )
  rot = column("rot_0", "rot_1", "rot_2", "rot_3")
  np.testing.assert_allclose(np.linalg.norm(rot, axis=-1), 1.0, atol=1e-6)
  np.testing.assert_allclose(
    rot, g["quats"] / np.linalg.norm(g["quats"], axis=-1, keepdims=True), atol=1e-6
  )
  # what a viewer decodes: colour = 0.5 + C0 f_dc, opacity = sigmoid, scale = exp
  np.testing.assert_allclose(
    0.5 + sh_c0 * column("f_dc_0", "f_dc_1", "f_dc_2"), g["colors"], atol=1e-5
  )
  np.testing.assert_allclose(1 / (1 + np.exp(-vertex["opacity"])), g["opacities"], atol=1e-5)
  np.testing.assert_allclose(
    np.exp(column("scale_0", "scale_1", "scale_2")), g["scales"], rtol=1e-5
  )


def test_ply_refuses_non_finite(tmp_path):
  g = _gaussians(4)
  g["means"][1, 0] = np.nan
  with pytest.raises(ValueError, match="non-finite"):
    export.write_ply(tmp_path / "bad.ply", **g)


def test_ply_leaves_out_gaussians_below_min_opacity(tmp_path):
  """As the official `save_ply`: a Gaussian of opacity below `min_opacity` is left out (one of
  exactly `min_opacity` stays), and the file is byte for byte the one written without it;
  `min_opacity=0`, the default, keeps every one, a fully transparent one too."""
  g = _gaussians(6)
  g["opacities"][[1, 3, 4]] = [0.0049, 0.005, 0.0]
  without = {name: np.delete(values, [1, 4], axis=0) for name, values in g.items()}
  pruned = export.write_ply(tmp_path / "pruned.ply", **g, min_opacity=0.005).read_bytes()
  assert pruned == export.write_ply(tmp_path / "without.ply", **without).read_bytes()
  every = export.write_ply(tmp_path / "every.ply", **g, min_opacity=0).read_bytes()
  assert every == export.write_ply(tmp_path / "default.ply", **g).read_bytes()
  assert len(export.read_ply(tmp_path / "every.ply")["means"]) == 6
  g["opacities"][2] = np.nan  # pruning never hides a non-finite Gaussian
  with pytest.raises(ValueError, match="non-finite"):
    export.write_ply(tmp_path / "bad.ply", **g, min_opacity=0.005)


def test_ply_leaves_out_gaussians_no_camera_can_see_when_asked(tmp_path):
  """With `cameras`, the Gaussians the renderer culls in every camera (behind it, off the image)
  are left out, those it draws kept; without, every one is written; a non-finite one is still
  refused rather than dropped."""
  g = _gaussians(6)
  g["means"] = np.array(
    [[0, 0, 0], [0.2, -0.1, 0.5], [0, 0, -5], [40, 0, 0], [0, -0.3, 1], [0, 0, 0.1]], np.float64
  )
  cameras = {
    "world_to_camera": np.array([[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3.0], [0, 0, 0, 1]]]),
    "intrinsics": np.array([[40.0, 40.0, 16.0, 16.0]]),
    "height": 32,
    "width": 32,
  }
  seen = export.write_ply(tmp_path / "seen.ply", **g, cameras=cameras).read_bytes()
  # behind the camera (z = -2) and far off the image (x = 40 at depth 3) are left out
  without = {name: np.delete(values, [2, 3], axis=0) for name, values in g.items()}
  assert seen == export.write_ply(tmp_path / "without.ply", **without).read_bytes()
  every = export.write_ply(tmp_path / "every.ply", **g).read_bytes()
  assert len(export.read_ply(tmp_path / "every.ply")["means"]) == 6 and every != seen
  g["means"][3, 0] = np.nan
  with pytest.raises(ValueError, match="non-finite"):
    export.write_ply(tmp_path / "bad.ply", **g, cameras=cameras)


def test_grid_and_png(tmp_path):
  a = np.zeros((8, 10, 3))
  b = np.ones((6, 4, 3))
  grid = export.image_grid([[a, b], [b]], pad=2)
  assert grid.dtype == np.uint8 and grid.shape == (2 + 8 + 2 + 6 + 2, 2 + 10 + 2 + 4 + 2, 3)
  assert grid[2, 2].tolist() == [0, 0, 0] and grid[2, 14].tolist() == [255, 255, 255]
  from PIL import Image

  assert Image.open(export.save_png(tmp_path / "g.png", grid)).size == (
    grid.shape[1],
    grid.shape[0],
  )


def test_colorize_depth_masks_empty_pixels():
  depth = np.linspace(1, 5, 12).reshape(3, 4)
  alpha = np.ones((3, 4))
  alpha[0, 0] = 0
  rgb = export.colorize_depth(depth, alpha)
  assert rgb.shape == (3, 4, 3) and np.all(rgb[0, 0] == 0) and np.all(np.isfinite(rgb))
  assert rgb[2, 3].sum() < rgb[0, 1].sum() or rgb[0, 1, 0] > rgb[2, 3, 0]  # near brighter in red
  assert np.all(export.colorize_depth(np.zeros((2, 2))) == 0)


def test_fly_through_passes_through_keyframes():
  c, s = np.cos(0.3), np.sin(0.3)
  k0, k1 = np.eye(4), np.eye(4)
  k1[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
  k1[:3, 3] = [1, 0, 0]
  path = export.fly_through_poses(np.stack([k0, k1]), 5)
  np.testing.assert_allclose(path[0], k0, atol=1e-6)
  np.testing.assert_allclose(path[-1], k1, atol=1e-6)
  mid = path[2]
  np.testing.assert_allclose(mid[:3, 3], [0.5, 0, 0], atol=1e-6)
  np.testing.assert_allclose(np.arctan2(mid[0, 2], mid[0, 0]), 0.15, atol=1e-6)


# imageio's reader, the independent check of the file, starts its ffmpeg by a fork (the writer
# does not: next test)
@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")
def test_mp4_is_written(tmp_path):
  frames = [np.full((15, 17, 3), i / 5.0) for i in range(5)]
  path = export.write_mp4(tmp_path / "v.mp4", frames, fps=5)
  assert path.stat().st_size > 0
  import imageio.v2 as imageio

  assert sum(1 for _ in imageio.get_reader(path)) == 5


def test_mp4_encoder_starts_without_forking_a_threaded_process(tmp_path):
  import warnings

  import jax.numpy as jnp

  float(jnp.ones(4).sum())  # JAX's threads are running
  frames = [np.full((8, 8, 3), 0.5)] * 3
  with warnings.catch_warnings():
    warnings.simplefilter("error")  # JAX's "os.fork() was called" warning raises here
    export.write_mp4(tmp_path / "v.mp4", frames, fps=5)
  with pytest.raises(ValueError, match="sizes"):
    export.write_mp4(tmp_path / "w.mp4", [np.zeros((8, 8, 3)), np.zeros((6, 8, 3))])


def _plyfile_variant(tmp_path, name, g, *, kind="f4", byte_order="<", text=False, drop=()):
  """The Gaussians `g` written by plyfile with another type, endianness, encoding, property
  order (reversed) or without some properties."""
  import plyfile

  ours = export.read_ply(export.write_ply(tmp_path / "ours.ply", **g))
  raw = {
    **{k: ours["means"][:, i] for i, k in enumerate("xyz")},
    **{f"f_dc_{i}": (ours["colors"][:, i] - 0.5) / export.SH_C0 for i in range(3)},
    "opacity": np.log(ours["opacities"] / (1 - ours["opacities"])),
    **{f"scale_{i}": np.log(ours["scales"][:, i]) for i in range(3)},
    **{f"rot_{i}": ours["quats"][:, i] for i in range(4)},
  }
  names = [k for k in reversed(list(raw)) if k not in drop]
  table = np.empty(len(ours["means"]), [(k, kind) for k in names])
  for k in names:
    table[k] = raw[k]
  element = plyfile.PlyElement.describe(table, "vertex")
  path = tmp_path / name
  plyfile.PlyData([element], text=text, byte_order=byte_order).write(str(path))
  return path, ours


@pytest.mark.parametrize(
  "variant",
  [{"kind": "f8"}, {"byte_order": ">"}, {"text": True}, {"kind": "f8", "byte_order": ">"}],
)
def test_ply_reader_honours_the_header(tmp_path, variant):
  path, expected = _plyfile_variant(tmp_path, "v.ply", _gaussians(), **variant)
  back = export.read_ply(path)
  for k in expected:
    np.testing.assert_allclose(back[k], expected[k], rtol=1e-5, atol=1e-5)


def test_ply_reader_refuses_what_it_cannot_honour_naming_the_file(tmp_path):
  path, _ = _plyfile_variant(tmp_path, "missing.ply", _gaussians(), drop=("rot_2",))
  with pytest.raises(ValueError, match=r"missing\.ply.*rot_2"):
    export.read_ply(path)
  good = export.write_ply(tmp_path / "good.ply", **_gaussians()).read_bytes()
  cases = {
    "no_end.ply": good.replace(b"end_header", b"end_headr"),
    "not_ascii.ply": good.replace(b"element vertex", "élément vertex".encode()),
    "short.ply": good[:-3],
    "list.ply": good.replace(b"end_header", b"property list uchar int idx\nend_header"),
  }
  for name, content in cases.items():
    (tmp_path / name).write_bytes(content)
    with pytest.raises(ValueError, match=name.replace(".", r"\.")):
      export.read_ply(tmp_path / name)
  empty = export.read_ply(export.write_ply(tmp_path / "empty.ply", **_gaussians(0)))
  assert empty["means"].shape == (0, 3) and empty["quats"].shape == (0, 4)


def test_to_uint8_scales_floats_and_keeps_uint8():
  floats = np.array([[[0.0, 0.5, 1.0], [np.nan, 2.0, -1.0]]])
  np.testing.assert_array_equal(export.to_uint8(floats), [[[0, 128, 255], [0, 255, 0]]])
  already = np.array([[[3, 128, 250]]], np.uint8)
  np.testing.assert_array_equal(export.to_uint8(already), already)
