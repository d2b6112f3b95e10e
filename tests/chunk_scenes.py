"""The scene dict the chunk tests write and read back (imported by them as `_scene`; no tests
here): posed frames of colour ramps, as `write_chunk` takes them; `write_chunk_set` writes a
chunk folder of them."""

import json

import numpy as np

from tokengs_jax.data import write_chunk


def chunk_scene(key="s0", frames=3, height=12, width=20, seed=0):
  rng = np.random.default_rng(seed)
  angles = rng.uniform(-0.3, 0.3, (frames, 3))
  c2w = np.tile(np.eye(4), (frames, 1, 1))
  for f, (_, b, c) in enumerate(angles):
    rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    c2w[f, :3, :3] = rz @ ry
    c2w[f, :3, 3] = rng.normal(size=3)
  intrinsics = np.tile([width * 0.9, height * 1.1, width / 2 + 0.3, height / 2 - 0.2], (frames, 1))
  ramp = np.linspace(0, 255, width, dtype=np.float32)
  images = np.zeros((frames, height, width, 3), np.uint8)
  images[..., 0] = ramp
  images[..., 1] = np.linspace(0, 255, height)[:, None]
  images[..., 2] = (np.arange(frames) * 40)[:, None, None]
  return {
    "key": key,
    "url": f"https://example.invalid/{key}",
    "c2w": c2w,
    "intrinsics": intrinsics,
    "images": images,
    "timestamps": np.arange(frames) * 1000,
  }


def write_chunk_set(folder, scenes, per_chunk=2):
  """Writes `scenes` as a pixelSplat chunk folder (`NNNNNN.torch` of `per_chunk` scenes each +
  `index.json`) at `folder`; returns it."""
  folder.mkdir(parents=True, exist_ok=True)
  index = {}
  for start in range(0, len(scenes), per_chunk):
    name = f"{start // per_chunk:06d}.torch"
    write_chunk(folder / name, scenes[start : start + per_chunk])
    index.update({scene["key"]: name for scene in scenes[start : start + per_chunk]})
  (folder / "index.json").write_text(json.dumps(index))
  return folder
