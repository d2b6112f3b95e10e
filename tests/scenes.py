"""Small scenes the objective, model and training tests share (imported by them; no tests here).

- Gaussians in front of an identity camera looking down +z (the objective's terms).
- A time-conditioned model and random views of it at given times, 16x16 (the dynamic objective,
  `model.decode_at_times`, dynamic training).
- Colour ramps for the tiny preset, 32x32 (the static objective, training).
- The model tests' configs (`MICRO`, `FULL`) with cached parameters, random posed views, and the
  official model's fixture (`official_fixture`: config, weights and reference inputs / outputs).
"""

import functools
import json

import jax
import jax.numpy as jnp
import numpy as np
from conftest import reference_fixture

from tokengs_jax import model


def gaussians_in_front(means_key, colours_key, shape, *, spread, opacity, scale):
  """Round Gaussians [*shape] of one opacity and size, centred within `spread` of (0, 0, 2):
  in front of an identity camera looking down +z."""
  from tokengs_jax.gaussians import Gaussians

  means = jax.random.uniform(means_key, (*shape, 3), minval=-spread, maxval=spread)
  return Gaussians(
    means=means.at[..., 2].add(2.0),
    opacities=jnp.full(shape, opacity),
    scales=jnp.full((*shape, 3), scale),
    quats=jnp.tile(jnp.array([1.0, 0, 0, 0]), (*shape, 1)),
    colors=jax.random.uniform(colours_key, (*shape, 3)),
  )


EVAL_HEIGHT = EVAL_WIDTH = 16


def evaluation_batch(
  rng, context_frames, target_frames, height=EVAL_HEIGHT, width=EVAL_WIDTH
) -> dict:
  """A batch of one with random images, cameras along x at the frame number, and its frames."""
  vc, vt = len(context_frames), len(target_frames)

  def cameras(frames):
    c2w = np.tile(np.eye(4, dtype=np.float32), (1, len(frames), 1, 1))
    c2w[0, :, 0, 3] = 0.1 * np.asarray(frames, np.float32)
    return c2w

  intrinsics = np.tile(np.array([width, height, width / 2, height / 2], np.float32), (1, 1, 1))
  return {
    "context_images": rng.uniform(size=(1, vc, height, width, 3)).astype(np.float32),
    "target_images": rng.uniform(size=(1, vt, height, width, 3)).astype(np.float32),
    "context_c2w": cameras(context_frames),
    "target_c2w": cameras(target_frames),
    "context_intrinsics": np.repeat(intrinsics, vc, axis=1),
    "target_intrinsics": np.repeat(intrinsics, vt, axis=1),
    "context_frames": np.asarray([context_frames]),
    "target_frames": np.asarray([target_frames]),
  }


def evaluation_gaussians(batch_shape, n=6, seed=0):
  """`n` Gaussians per set within 0.4 of (0, 0, 2), seen by every camera of `evaluation_batch`."""
  return gaussians_in_front(
    *jax.random.split(jax.random.key(seed)), (*batch_shape, n), spread=0.4, opacity=0.8, scale=0.15
  )


def scene_of_two_examples():
  """Gaussians [2, N] that cover part of two views, and two examples' input views
  [2, 3, 16, 16, 3] of different mean colours (neither of them grey)."""
  key = jax.random.split(jax.random.key(1), 3)
  gaussians = gaussians_in_front(key[0], key[1], (2, 24), spread=0.6, opacity=0.8, scale=0.08)
  tint = jnp.array([[0.2, 0.9, 0.5], [0.8, 0.1, 0.3]])[:, None, None, None]
  context = tint * jax.random.uniform(key[2], (2, 3, 16, 16, 3), minval=0.5, maxval=1.5)
  return gaussians, context


DYNAMIC_SIZE = 16  # height and width of `dynamic_batch`'s views
# 4 static + 2 dynamic tokens of 16 Gaussians: 96 Gaussians, cheap to render and compile.
DYNAMIC_CONFIG = model.preset(
  "tiny",
  enc_depth=1,
  dec_depth=1,
  enc_embed_dim=32,
  enc_num_heads=2,
  num_gs_tokens=4,
  num_dynamic_gs_tokens=2,
  dec_patch_size=4,
  time_embedding=True,
  dec_init_values=1.0,
)


def dynamic_params(seed=0):
  """Fresh parameters whose (zero-initialised) time embeddings are made non-zero, so that the
  decoded dynamic Gaussians depend on the time; decoder LayerScale 1 (config) for the same reason."""
  params = model.init_params(jax.random.PRNGKey(seed), DYNAMIC_CONFIG)
  keys = jax.random.split(jax.random.PRNGKey(seed + 1), 2)
  for key, name in zip(keys, ("patch_time_embed", "patch_time_embed_tgt")):
    kernel = params[name]["proj"]["kernel"]
    params[name]["proj"]["kernel"] = 0.5 * jax.random.normal(key, kernel.shape)
  return params


def dynamic_batch(context_times, target_times, seed=0):
  """Random images seen from cameras stepping along x; times [B, Vc] and [B, Vt]."""
  context_times = np.asarray(context_times, np.float32)
  target_times = np.asarray(target_times, np.float32)
  batch_size, num_context = context_times.shape
  views = num_context + target_times.shape[1]
  rng = np.random.default_rng(seed)
  images = rng.random((batch_size, views, DYNAMIC_SIZE, DYNAMIC_SIZE, 3)).astype(np.float32)
  c2w = np.tile(np.eye(4, dtype=np.float32), (batch_size, views, 1, 1))
  c2w[:, :, 0, 3] = np.linspace(-0.1, 0.1, views)
  intrinsics = np.tile(np.array([16, 16, 8, 8], np.float32), (batch_size, views, 1))
  batch = {"context_times": context_times, "target_times": target_times}
  for name, value in (("images", images), ("c2w", c2w), ("intrinsics", intrinsics)):
    batch[f"context_{name}"], batch[f"target_{name}"] = (
      value[:, :num_context],
      value[:, num_context:],
    )
  return batch


RAMP_SIZE = 32  # height and width of `synthetic_batch`'s views


def synthetic_batch(batch_size=2, context_views=2, target_views=4, seed=0):
  """Smooth colour ramps seen from cameras stepping along x (learnable, unlike noise)."""
  rng = np.random.default_rng(seed)
  views = context_views + target_views
  ramp = np.linspace(0, 1, RAMP_SIZE, dtype=np.float32)
  images = np.empty((batch_size, views, RAMP_SIZE, RAMP_SIZE, 3), np.float32)
  for b in range(batch_size):
    colour = rng.uniform(0.2, 0.8, 3).astype(np.float32)
    for v in range(views):
      images[b, v] = colour * (0.5 + 0.5 * np.roll(ramp, 2 * v))[None, :, None]
  c2w = np.tile(np.eye(4, dtype=np.float32), (batch_size, views, 1, 1))
  c2w[:, :, 0, 3] = np.linspace(-0.1, 0.1, views)
  intrinsics = np.tile(np.array([32, 32, 16, 16], np.float32), (batch_size, views, 1))
  split = lambda x: (x[:, :context_views], x[:, context_views:])
  batch = {}
  for name, value in (("images", images), ("c2w", c2w), ("intrinsics", intrinsics)):
    batch[f"context_{name}"], batch[f"target_{name}"] = split(value)
  return batch


# ----- the model tests' configs, parameters, views and the official fixture ----------------------

# A config small enough that each test compiles in about a second.
MICRO = model.ModelConfig(
  patch_size=4,
  dec_patch_size=2,
  enc_depth=1,
  dec_depth=2,
  enc_embed_dim=32,
  enc_num_heads=2,
  num_gs_tokens=4,
  image_size=(16, 16),
)
# Every optional part at once: multiscale readout, latent bottleneck, dynamic tokens, time.
FULL = MICRO.replace(
  enc_depth=3,
  use_multiscale_encoder=True,
  multiscale_encoder_layers=(0, 1, 2),
  use_latent_bottleneck=True,
  num_latents=6,
  latent_cross_attn_depth=2,
  num_dynamic_gs_tokens=3,
  time_embedding=True,
  dec_init_values=0.01,
  clip_head_z_init=0.1,
)


@functools.cache
def micro_params():
  return model.init_params(jax.random.key(0), MICRO)


@functools.cache
def full_init():
  return model.init_params(jax.random.key(1), FULL)


@functools.cache
def full_params():
  """FULL params with non-zero time embeds (they start at zero) so that time really matters."""
  params = jax.tree.map(lambda x: x, full_init())
  keys = jax.random.split(jax.random.key(2), 2)
  for key, name in zip(keys, ("patch_time_embed", "patch_time_embed_tgt")):
    kernel = params[name]["proj"]["kernel"]
    params[name]["proj"]["kernel"] = jax.random.normal(key, kernel.shape)
  return params


@functools.cache
def official_fixture():
  config = model.config_from_official(
    json.loads((reference_fixture("official_tokengs_tiny", "options.json")).read_text())
  )
  params = model.load_official_checkpoint(
    reference_fixture("official_tokengs_tiny", "weights.safetensors"), config
  )
  io = dict(np.load(reference_fixture("official_tokengs_tiny", "io.npz")))
  # torch NCHW -> our NHWC
  io["images_rgb"] = io["images_rgb"].transpose(0, 1, 3, 4, 2)
  io["plucker"] = io["plucker"].transpose(0, 1, 3, 4, 2)
  return config, params, io


def random_inputs(key, batch, views, height, width):
  k1, k2, k3 = jax.random.split(key, 3)
  images = jax.random.uniform(k1, (batch, views, height, width, 3))
  angles = jax.random.normal(k2, (batch, views, 3)) * 0.3
  rot = jax.vmap(jax.vmap(lambda a: jax.scipy.linalg.expm(jnp.cross(jnp.eye(3), a))))(angles)
  c2w = jnp.zeros((batch, views, 4, 4)).at[..., :3, :3].set(rot).at[..., 3, 3].set(1.0)
  c2w = c2w.at[..., :3, 3].set(jax.random.normal(k3, (batch, views, 3)) * 0.2)
  intrinsics = jnp.broadcast_to(
    jnp.array([width * 1.1, height * 1.1, width / 2, height / 2]), (batch, views, 4)
  )
  return images, c2w, intrinsics


# ----- DL3DV scenes as they ship (zips with transforms.json and images_4/) -----------------------


def write_dl3dv_scene(path, scene, *, capture_scale=2, benchmark=False):
  """Writes a rendered scene (`render_re10k_like_scene`: OpenCV c2w, intrinsics in pixels of its
  images) as one DL3DV scene: `path` ending in `.zip` (the official zip, members under
  `<key>/`), else a directory. `transforms.json` holds nerfstudio poses and the intrinsics of a
  capture `capture_scale` times the stored `images_4/` PNGs, as DL3DV's do; `benchmark` nests it
  under `gaussian_splat/` (DL3DV-10K-Benchmark)."""
  import io
  import pathlib
  import zipfile

  from PIL import Image

  from tokengs_jax.data import opencv_to_nerfstudio_c2w

  path = pathlib.Path(path)
  height, width = scene["images"].shape[1:3]
  fx, fy, cx, cy = (float(v) * capture_scale for v in scene["intrinsics"][0])
  names = [f"frame_{f + 1:05d}.png" for f in range(len(scene["images"]))]
  poses = opencv_to_nerfstudio_c2w(scene["c2w"])
  transforms = {
    **{"w": width * capture_scale, "h": height * capture_scale},
    **{"fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "camera_model": "OPENCV"},
    "frames": [
      {"file_path": f"images/{name}", "transform_matrix": pose.tolist()}
      for name, pose in zip(names, poses)
    ],
  }
  files = {"transforms.json": json.dumps(transforms).encode()}
  for name, image in zip(names, scene["images"]):
    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, "PNG")
    files[f"images_4/{name}"] = buffer.getvalue()
  prefix = "gaussian_splat/" if benchmark else ""
  path.parent.mkdir(parents=True, exist_ok=True)
  if path.suffix == ".zip":
    with zipfile.ZipFile(path, "w") as archive:
      for name, payload in files.items():
        archive.writestr(f"{path.stem}/{prefix}{name}", payload)
    return
  for name, payload in files.items():
    (path / prefix / name).parent.mkdir(parents=True, exist_ok=True)
    (path / prefix / name).write_bytes(payload)


def write_dl3dv_scenes(folder, keys, *, frames=12, size=(36, 64), seed=0):
  """Renders one synthetic room walk per key (the project's ray tracer) and writes each as
  `<folder>/<key>.zip` (`write_dl3dv_scene`).  -> {key: the rendered scene}."""
  import pathlib

  from tokengs_jax.data.synthetic.generate import render_re10k_like_scene

  scenes = {}
  for index, key in enumerate(keys):
    scenes[key] = render_re10k_like_scene(seed, "train", index, *size, frames)
    write_dl3dv_scene(pathlib.Path(folder) / f"{key}.zip", scenes[key])
  return scenes
