"""Kubric-4D (multi-view dynamic) reader, as the official TokenGS `Kubric` dataset + provider.

Layout: `<root>/<subset>/<scene>/output_{view:03d}.tar` (subsets v0, v1, v2; 9 cameras x 24
frames), each tar holding `./metadata.json`, `./rgba_{frame:05d}.png` and (optional)
`./depth_{frame:05d}.tiff` (float32, the distance from the camera centre to the surface along each
pixel's ray: Kubric's `z_to_depth` of the planar z, not z itself). From the metadata, as official:

- intrinsics: fx = focal_length * W / sensor_width, fy = focal_length * H / sensor_width,
  (cx, cy) = (W / 2, H / 2), with `H, W = metadata.resolution` (the same for every frame);
- frame f's camera-to-world: rotation of the wxyz (Hamilton) quaternion `camera.quaternions[f]`,
  translation `camera.positions[f]`, in Blender/OpenGL axes (+y up, looking down -z); OpenCV
  is obtained by negating the y and z columns.

Motion truth, optional (the official loader reads neither; the synthetic writers write both):
`./segmentation_{frame:05d}.png` (palette PNG of object instance numbers, 0 the background, k + 1
the metadata's `instances[k]`) and `instances[k]["positions"]` / `["quaternions"]` (each object's
pose at every frame), as Kubric writes them. Records carry them as `segmentations` and
`object_poses`; the evaluation takes its moving pixels and scene-flow truth from them
(`evaluation`).

Examples are built by the shared input pipeline: `KubricSceneSource` yields scene records (the C
cameras x F frames flattened camera-major, lazy PNG/TIFF members) and `kubric_view_selector`
draws the official views (`_get_indices_dynamic` + `_curate_batch_dynamic`): `num_context`
cameras and `num_context` increasing frames spanning a random gap, plus one target frame; context
view v is camera v at frame v, target view v is camera v at the target frame. The pipeline
(`DATASET_PRESETS["kubric"]`) then min-max normalises the times, normalises the cameras
(`mean_cam`) and scales them by `translation_scale / mean distance of the context views' depth
points from the origin` ("pointmap", `pointmap_scale`; as the official provider, it unprojects
the stored value as if it were planar z, see there).

Every failure to read a scene raises `KubricError` naming the file, and for a frame its member
(`.../output_002.tar member ./rgba_00007.png`): an unreadable or truncated tar, bad metadata, a
scene without all of its `num_cameras` tars (`KubricSceneSource`, official 9), a tar without
every frame its metadata lists (`metadata.num_frames`, else the number of poses; a tar cut at a
member boundary; depth maps and segmentations are optional, but all or none), malformed
`instances`, a corrupt frame, a depth map whose size is not the metadata's resolution. The
pipeline's `skip_bad` counts such a scene as a rejection (reason `KubricError`).

Modules: `camera_tar` (one camera's tar: metadata, poses, frames, depth conventions), `source` (scene listing and
`KubricSceneSource`), `sampling` (`kubric_view_selector`, `pointmap_scale`), `evaluation` (the
evaluation's (camera, frame) views: index and default protocol of novel views at novel times,
moving-pixel masks, scene-flow truth).
"""

from tokengs_jax.data.kubric.camera_tar import (
  KubricError,
  KubricView,
  decode_member,
  intrinsics_from_metadata,
  kubric_pose_to_opencv,
  opencv_to_kubric_pose,
  parse_kubric_view,
  pose_matrices,
  quat_wxyz_to_rotation,
  ray_depth_to_z,
  read_kubric_view,
  rotation_to_quat_wxyz,
  unproject_ray_depth,
  z_to_ray_depth,
)
from tokengs_jax.data.kubric.evaluation import (
  MOTION_THRESHOLD,
  OBJECT_POINTS,
  default_evaluation_views,
  evaluation_fields,
  flat_views,
  load_kubric_evaluation_index,
  motion_mask,
  moved_objects,
  truth_motion_mask,
  validate_kubric_evaluation_index,
)
from tokengs_jax.data.kubric.sampling import (
  kubric_view_selector,
  pointmap_scale,
  sample_dynamic_indices,
)
from tokengs_jax.data.kubric.source import KubricSceneSource, list_kubric_scenes

__all__ = [
  "MOTION_THRESHOLD",
  "OBJECT_POINTS",
  "KubricError",
  "KubricSceneSource",
  "KubricView",
  "decode_member",
  "default_evaluation_views",
  "evaluation_fields",
  "flat_views",
  "intrinsics_from_metadata",
  "kubric_view_selector",
  "kubric_pose_to_opencv",
  "list_kubric_scenes",
  "load_kubric_evaluation_index",
  "motion_mask",
  "moved_objects",
  "opencv_to_kubric_pose",
  "parse_kubric_view",
  "pointmap_scale",
  "pose_matrices",
  "quat_wxyz_to_rotation",
  "ray_depth_to_z",
  "read_kubric_view",
  "rotation_to_quat_wxyz",
  "sample_dynamic_indices",
  "truth_motion_mask",
  "unproject_ray_depth",
  "validate_kubric_evaluation_index",
  "z_to_ray_depth",
]
