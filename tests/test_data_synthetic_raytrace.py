"""The synthetic ray tracer (`synthetic.raytrace`) against analytic values: depths, shading,
textures (photographs included), segmentation and shadows."""

import jax.numpy as jnp
import numpy as np
import pytest
from synthetic_scenes import H, W

from tokengs_jax import camera
from tokengs_jax.data.synthetic import cameras, photos, raytrace
from tokengs_jax.data.synthetic.raytrace import Plane, Scene, Texture, render, texture_color

INTRINSICS = np.array([30.0, 28.0, 15.3, 12.7])  # fx != fy and an off-centre principal point


def _plane(point, normal, texture=raytrace.Texture(), tangent=(1.0, 0.0, 0.0)):
  return raytrace.Plane(
    point=np.asarray(point, float),
    normal=np.asarray(normal, float),
    tangent=np.asarray(tangent, float),
    texture=texture,
  )


def _pixel_dirs_cam():
  """Unnormalised camera-frame rays (x, y, 1) through pixel centres.  -> [H, W, 3]."""
  u = np.arange(W) + 0.5
  v = np.arange(H) + 0.5
  uu, vv = np.meshgrid(u, v)
  fx, fy, cx, cy = INTRINSICS
  return np.stack([(uu - cx) / fx, (vv - cy) / fy, np.ones_like(uu)], -1)


def test_fronto_parallel_plane_depth_is_its_distance():
  scene = raytrace.Scene(planes=(_plane((0, 0, 3.5), (0, 0, -1)),))
  out = raytrace.render(scene, np.eye(4), INTRINSICS, H, W)
  np.testing.assert_allclose(out.depth, 3.5, rtol=1e-5)
  assert (out.ids == 0).all()


def test_tilted_plane_depth_and_lambert_colour_match_analytic_values():
  normal = np.array([0.3, -0.2, -1.0])
  normal /= np.linalg.norm(normal)
  point = np.array([0.1, 0.2, 4.0])
  albedo = (0.8, 0.5, 0.25)
  light = np.array([0.2, -0.4, -1.0])
  scene = raytrace.Scene(
    planes=(_plane(point, normal, raytrace.Texture("solid", albedo)),),
    light_direction=tuple(light),
    ambient=0.3,
  )
  # Camera: rotated and translated, so the c2w path is exercised too.
  c2w = cameras.look_at(
    np.array([0.4, -0.3, -0.5]), np.array([0.2, 0.1, 4.0]), up=np.array([0, -1.0, 0])
  )
  out = raytrace.render(scene, c2w, INTRINSICS, H, W)

  dirs_cam = _pixel_dirs_cam()
  normal_cam = c2w[:3, :3].T @ normal
  point_cam = c2w[:3, :3].T @ (point - c2w[:3, 3])
  # plane n.X = n.p in camera frame, X = z * (x, y, 1)  =>  z = n.p / n.(x, y, 1)
  np.testing.assert_allclose(
    out.depth, (normal_cam @ point_cam) / (dirs_cam @ normal_cam), rtol=1e-4
  )
  facing = normal * np.sign(normal @ (c2w[:3, 3] - point))  # the side the camera sees
  lambert = max(0.0, float(facing @ (light / np.linalg.norm(light))))
  assert lambert > 0.5
  expected = np.asarray(albedo) * (0.3 + 0.7 * lambert)
  np.testing.assert_allclose(out.rgb, np.broadcast_to(expected, out.rgb.shape), atol=1e-5)


def test_checker_colour_follows_the_analytic_hit_point():
  texture = raytrace.Texture("checker", (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), frequency=2.0)
  scene = raytrace.Scene(planes=(_plane((0, 0, 2.0), (0, 0, -1), texture),), ambient=1.0)
  out = raytrace.render(scene, np.eye(4), INTRINSICS, H, W)
  hits = _pixel_dirs_cam() * 2.0  # hit points on z = 2
  # plane local axes: u along x, v along n x t = (0,0,-1) x (1,0,0) = (0,-1,0)
  parity = (np.floor(2.0 * hits[..., 0]) + np.floor(-2.0 * hits[..., 1])) % 2
  np.testing.assert_array_equal(out.rgb[..., 2] > 0.5, parity == 1)
  np.testing.assert_array_equal(out.rgb[..., 0] > 0.5, parity == 0)


def test_sphere_silhouette_is_where_project_points_puts_the_sphere():
  center, radius = np.array([0.4, -0.2, 5.0]), 0.9
  c2w = cameras.look_at(np.array([0.5, -0.5, -0.3]), np.array([0.0, 0.0, 5.0]))
  scene = raytrace.Scene(objects=(raytrace.Sphere(center=center, radius=radius),))
  out = raytrace.render(scene, c2w, INTRINSICS, H, W)
  covered = out.ids == 0
  eye = c2w[:3, 3]
  view = (center - eye) / np.linalg.norm(center - eye)
  rng = np.random.default_rng(0)
  directions = rng.normal(size=(400, 3))
  directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
  # visible surface points: facing the camera (with a margin away from the silhouette)
  surface = center + radius * directions
  facing = (
    np.einsum("ni,ni->n", directions, eye - surface) / np.linalg.norm(eye - surface, axis=-1) > 0.6
  )
  # points just outside the silhouette: a ring of radius 1.15 r perpendicular to the view ray
  perpendicular = directions - (directions @ view)[:, None] * view
  perpendicular /= np.linalg.norm(perpendicular, axis=-1, keepdims=True)
  outside = center + 1.15 * radius * perpendicular
  visible = surface[facing]
  points = np.concatenate([visible, outside]).astype(np.float32)
  uv, depth = camera.project_points(
    jnp.asarray(points), jnp.asarray(np.linalg.inv(c2w))[None], jnp.asarray(INTRINSICS)[None]
  )
  uv, depth = np.asarray(uv[0]), np.asarray(depth[0])
  in_image = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
  cols, rows = np.floor(np.where(in_image[:, None], uv, 0)).astype(int).T
  is_visible = np.arange(len(points)) < len(visible)
  for expect in (True, False):
    chosen = in_image & (is_visible == expect)
    assert chosen.sum() > 20
    # a point may share a pixel with the rim, hence not all
    assert (covered[rows, cols][chosen] == expect).mean() > 0.97
  # the depth at a visible point's pixel is that of a nearby point of the sphere
  hit = in_image & is_visible & covered[rows, cols]
  assert np.all(np.abs(out.depth[rows, cols] - depth)[hit] < 0.3 * radius)


def test_box_front_face_depth():
  box = raytrace.Box(center=np.array([0.0, 0.0, 3.0]), half_size=np.array([2.0, 2.0, 0.5]))
  out = raytrace.render(raytrace.Scene(objects=(box,)), np.eye(4), INTRINSICS, H, W)
  np.testing.assert_allclose(out.depth, 2.5, rtol=1e-5)


def test_segmentation_numbers_each_pixel_by_the_object_instance_it_sees():
  # a floor, a wall and three boxes side by side in front of the camera; the last two are the
  # parts of one rigid instance
  boxes = tuple(
    raytrace.Box(center=np.array([x, 0.0, 3.0]), half_size=np.array([0.3, 0.3, 0.3]))
    for x in (-1.0, 0.0, 1.0)
  )
  planes = (_plane((0, 0, 6), (0, 0, -1)), _plane((0, 1, 0), (0, -1, 0)))
  out = raytrace.render(raytrace.Scene(planes=planes, objects=boxes), np.eye(4), INTRINSICS, H, W)
  assert set(np.unique(out.ids)) == {0, 1, 2, 3, 4}
  expected = np.select([out.ids == 2, out.ids == 3, out.ids == 4], [1, 2, 2], 0)
  grouped = raytrace.Scene(planes=planes, objects=boxes, instances=(0, 1, 1))
  np.testing.assert_array_equal(grouped.segmentation(out.ids), expected)
  # by default every object is its own instance; rays that hit nothing are background too
  alone = raytrace.Scene(planes=planes, objects=boxes)
  np.testing.assert_array_equal(
    alone.segmentation(np.array([-1, 0, 1, 2, 3, 4])), [0, 0, 0, 1, 2, 3]
  )
  with pytest.raises(ValueError, match="2 instance numbers for 3 objects"):
    raytrace.Scene(objects=boxes, instances=(0, 1)).segmentation(out.ids)


def test_object_shadow_leaves_only_ambient_light():
  floor = _plane((0, 0, 0), (0, 1, 0), raytrace.Texture("solid", (1.0, 1.0, 1.0)))
  sphere = raytrace.Sphere(center=np.array([0.0, 1.0, 0.0]), radius=0.3)
  scene = raytrace.Scene(
    planes=(floor,), objects=(sphere,), light_direction=(0.0, 1.0, 0.0), ambient=0.25
  )
  origin = np.array([[3.0, 1.0, 0.0], [3.0, 1.0, 0.0]], np.float32)
  targets = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])  # under the sphere / in the open
  dirs = (targets - origin) / np.linalg.norm(targets - origin, axis=-1, keepdims=True)
  result = raytrace.trace(scene, origin, dirs.astype(np.float32))
  np.testing.assert_array_equal(result.ids, [0, 0])
  np.testing.assert_allclose(result.rgb, [[0.25] * 3, [1.0] * 3], atol=1e-6)


@pytest.mark.parametrize("kind", raytrace.TEXTURE_KINDS)
def test_textures_mix_between_their_two_colours(kind):
  photo = {"image": "grass.png", "tint": True} if kind == "photo" else {}  # a tinted photograph
  texture = raytrace.Texture(kind, (0.1, 0.2, 0.3), (0.9, 0.6, 0.3), frequency=1.7, seed=5, **photo)
  points = np.random.default_rng(1).uniform(-3, 3, (500, 3)).astype(np.float32)
  colors = raytrace.texture_color(texture, points)
  mix = (colors[:, 0] - 0.1) / 0.8
  np.testing.assert_allclose(colors[:, 1], 0.2 + 0.4 * mix, atol=1e-5)  # on the segment a-b
  assert mix.min() >= -1e-6 and mix.max() <= 1 + 1e-6
  if kind != "solid":
    assert mix.std() > 0.1  # an actual pattern


def test_value_noise_is_deterministic_continuous_and_seeded():
  points = np.random.default_rng(2).uniform(-5, 5, (300, 3)).astype(np.float32)
  a = raytrace.value_noise(points, seed=3)
  np.testing.assert_array_equal(a, raytrace.value_noise(points, seed=3))
  assert np.abs(a - raytrace.value_noise(points, seed=4)).mean() > 0.05
  nudged = raytrace.value_noise(points + 1e-3, seed=3)
  assert np.abs(a - nudged).max() < 0.02


def test_unknown_texture_kind_is_refused():
  with pytest.raises(ValueError, match="unknown texture kind"):
    raytrace.Texture("marble")


def test_photo_texture_tiles_the_photograph_and_tints_grey_ones():
  with pytest.raises(ValueError, match="names its `image`"):
    Texture(kind="photo")
  with pytest.raises(ValueError, match="names its `image`"):
    Texture(kind="checker", image="brick.png")
  image = photos.photo("astronaut.png")
  height, width = image.shape[:2]
  plain = Texture(kind="photo", image="astronaut.png", frequency=1.0, seed=0)
  # Texel (row 10, column 20) of tile (0, 0) and of tile (2, -1): the photograph repeats.
  uv = np.array([[20.5 / width, 10.5 / height, 0.0], [2 + 20.5 / width, -1 + 10.5 / height, 0.0]])
  np.testing.assert_allclose(texture_color(plain, uv.astype(np.float32)), image[[10, 10], [20, 20]])
  # A box face addresses the photograph with its two in-face axes (face axis 0: local y, z).
  on_face = np.array([[0.3, 20.5 / width, 10.5 / height]], np.float32)
  np.testing.assert_allclose(texture_color(plain, on_face, np.array([0])), image[[10], [20]])
  tinted = Texture(
    kind="photo", image="brick.png", tint=True, color_a=(1.0, 0.0, 0.0), color_b=(0.0, 0.0, 1.0)
  )
  colours = texture_color(tinted, np.random.default_rng(0).uniform(0, 1, (256, 3)))
  assert np.allclose(colours[:, 1], 0.0) and np.allclose(colours.sum(-1), 1.0)  # red..blue mixes


def test_a_plane_textured_with_a_photo_renders_the_photo():
  """The tracer end to end: a camera facing a photo-textured wall sees the photograph's texels."""
  wall = Plane(
    point=np.array([0.0, 0.0, 2.0]),
    normal=np.array([0.0, 0.0, -1.0]),
    tangent=np.array([1.0, 0.0, 0.0]),
    texture=Texture(kind="photo", image="coffee.png", frequency=0.25),
  )
  scene = Scene(planes=(wall,), ambient=1.0)
  image = render(scene, np.eye(4), np.array([16.0, 16.0, 8.0, 8.0]), 16, 16).rgb
  assert image.std() > 0.02  # texture detail, not a flat colour
  assert np.isin(
    np.round(image.reshape(-1, 3) * 255), np.round(photos.photo("coffee.png") * 255)
  ).all()
