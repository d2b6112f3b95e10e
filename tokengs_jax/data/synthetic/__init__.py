"""Offline synthetic scenes: an independent numpy ray tracer and writers of the real data formats.

from tokengs_jax.data.synthetic import generate_re10k_like, generate_kubric_like
generate_re10k_like("data/synthetic_re10k", num_train=256, num_test=32, height=64, width=64)
generate_kubric_like("data/synthetic_kubric", num_scenes=16)
generate_galleries("data/galleries", num_scenes=24)  # out-of-distribution test set (64x64)
generate_courtyards("data/courtyards")  # the frozen test family (fixed seed)
generate_kubric_ood("data/synthetic_kubric", num_scenes=8)  # the frozen dynamic test family
"""

from tokengs_jax.data.synthetic.cameras import (
  ArcConfig,
  WalkConfig,
  arc_path,
  forward_walk,
  look_at,
  orbit_cameras,
  pinhole_intrinsics,
)
from tokengs_jax.data.synthetic.generate import (
  KubricLikeConfig,
  Re10kLikeConfig,
  generate_kubric_like,
  generate_re10k_like,
  render_kubric_like_scene,
  render_re10k_like_scene,
  write_kubric_view,
)
from tokengs_jax.data.synthetic.held_out import (
  COURTYARD_DATASET,
  GalleryDatasetConfig,
  gallery_views,
  generate_courtyards,
  generate_galleries,
  render_gallery_scene,
)
from tokengs_jax.data.synthetic.raytrace import (
  Box,
  Plane,
  RenderOutput,
  Scene,
  Sphere,
  Texture,
  render,
  trace,
)
from tokengs_jax.data.synthetic.courtyards import CourtyardConfig, sample_courtyard
from tokengs_jax.data.synthetic.kubric_ood import KubricOodConfig, generate_kubric_ood
from tokengs_jax.data.synthetic.scenes import (
  DynamicConfig,
  DynamicScene,
  GalleryConfig,
  RoomConfig,
  sample_dynamic_scene,
  sample_gallery_scene,
  sample_room_scene,
)
from tokengs_jax.data.synthetic.varied import VariedRoomConfig, sample_varied_room

__all__ = [
  "ArcConfig",
  "Box",
  "DynamicConfig",
  "DynamicScene",
  "GalleryConfig",
  "COURTYARD_DATASET",
  "CourtyardConfig",
  "GalleryDatasetConfig",
  "KubricLikeConfig",
  "KubricOodConfig",
  "Plane",
  "Re10kLikeConfig",
  "RenderOutput",
  "RoomConfig",
  "Scene",
  "Sphere",
  "Texture",
  "VariedRoomConfig",
  "WalkConfig",
  "arc_path",
  "forward_walk",
  "gallery_views",
  "generate_courtyards",
  "generate_galleries",
  "generate_kubric_like",
  "generate_kubric_ood",
  "generate_re10k_like",
  "look_at",
  "orbit_cameras",
  "pinhole_intrinsics",
  "render",
  "render_gallery_scene",
  "render_kubric_like_scene",
  "render_re10k_like_scene",
  "sample_dynamic_scene",
  "sample_gallery_scene",
  "sample_room_scene",
  "sample_courtyard",
  "sample_varied_room",
  "trace",
  "write_kubric_view",
]
