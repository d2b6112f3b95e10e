"""Data: chunk files, datasets, view sampling, transforms and the grain input pipeline.

    from tokengs_jax.data import ChunkedSceneSource, InputPipeline, DATASET_PRESETS
    source = ChunkedSceneSource("datasets/re10k/train", skip_bad=True)
    for batch in InputPipeline(source, DATASET_PRESETS["re10k"], batch_size=8, num_workers=8): ...

DL3DV in the official TokenGS layout (`transforms.json` + `images_4/` per scene zip) comes from
`DL3DVSceneSource(root)`; it yields the same scene records, so the rest is shared.
"""

from tokengs_jax.data.chunked import ChunkedSceneSource, SceneEntry
from tokengs_jax.data.chunks import (
  ChunkError,
  LazyTensor,
  UnsafeChunkError,
  decode_jpeg,
  encode_jpeg,
  load_tensor_archive,
  read_chunk,
  save_tensor_archive,
  write_chunk,
)
from tokengs_jax.data.dl3dv import (
  DL3DVError,
  DL3DVSceneSource,
  list_dl3dv_scenes,
  nerfstudio_to_opencv_c2w,
  opencv_to_nerfstudio_c2w,
  read_dl3dv_cameras,
)
from tokengs_jax.data.rejections import Rejections, summarize_rejections
from tokengs_jax.data.pipeline import (
  DATASET_PRESETS,
  TRANSLATION_SCALES,
  BadExampleError,
  ExampleConfig,
  InputPipeline,
  NoUsableExamplesError,
  field_of_view,
  make_example,
)
from tokengs_jax.data.sampler import (
  SAMPLER_PRESETS,
  BoundedSamplerConfig,
  EvaluationIndexError,
  EvaluationIndexReport,
  MissingIndexEntryError,
  NotEnoughFramesError,
  context_gap_bounds,
  evaluation_views,
  load_evaluation_index,
  sample_bounded,
  validate_evaluation_index,
)
from tokengs_jax.data.transforms import (
  flip_horizontal,
  normalize_cameras,
  resize_and_center_crop,
  rigid_inverse,
  translation_scale,
)

__all__ = [
  "BadExampleError",
  "BoundedSamplerConfig",
  "ChunkError",
  "ChunkedSceneSource",
  "DATASET_PRESETS",
  "DL3DVError",
  "DL3DVSceneSource",
  "EvaluationIndexError",
  "EvaluationIndexReport",
  "ExampleConfig",
  "InputPipeline",
  "LazyTensor",
  "MissingIndexEntryError",
  "NoUsableExamplesError",
  "NotEnoughFramesError",
  "Rejections",
  "SAMPLER_PRESETS",
  "SceneEntry",
  "TRANSLATION_SCALES",
  "UnsafeChunkError",
  "context_gap_bounds",
  "decode_jpeg",
  "encode_jpeg",
  "evaluation_views",
  "field_of_view",
  "flip_horizontal",
  "list_dl3dv_scenes",
  "load_evaluation_index",
  "load_tensor_archive",
  "make_example",
  "nerfstudio_to_opencv_c2w",
  "normalize_cameras",
  "opencv_to_nerfstudio_c2w",
  "read_chunk",
  "read_dl3dv_cameras",
  "resize_and_center_crop",
  "rigid_inverse",
  "sample_bounded",
  "save_tensor_archive",
  "summarize_rejections",
  "translation_scale",
  "validate_evaluation_index",
  "write_chunk",
]
