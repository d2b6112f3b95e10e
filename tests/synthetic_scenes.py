"""What the synthetic-data tests share (imported by them, `photo_names` as `_photo_names`; no
tests here): the image size they render at, and the photographs a traced scene draws."""

from tokengs_jax.data.synthetic.raytrace import Scene

H, W = 24, 32


def photo_names(scene: Scene) -> set[str]:
  return {p.texture.image for p in scene.primitives if p.texture.kind == "photo"}
