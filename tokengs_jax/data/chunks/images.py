"""Bounded image decoding, shared by every data reader: chunk JPEGs, DL3DV frames, Kubric PNG/TIFF.

An encoded frame is untrusted input. Its byte length is checked before it is read
(`check_frame_bytes`): PIL scans garbage behind a JPEG marker byte by byte (a 255 MiB frame took
17-26 s and 0.5 GB). The size its header declares is checked before a pixel is decoded
(`MAX_FRAME_PIXELS`): PIL only warns (`DecompressionBombWarning`) between 89M and 179M pixels, and a
631-byte JPEG declaring 10000x10000 decoded with a 1.3 GB peak. Errors are the caller's data error type and
name the caller's `where` (file, scene, frame or member), never PIL's repr of the in-memory buffer,
which changes from run to run.
"""

from __future__ import annotations

import io

import numpy as np
from PIL import Image

from tokengs_jax.data.chunks.archive import ChunkError

# Far above real frames (a 4K JPEG takes a few MB, 8K UHD is 33.2M pixels), far below what
# exhausts a host: a frame decodes to at most 3 x 32 MiB = 96 MiB of RGB (PIL holds 128 MiB).
MAX_FRAME_BYTES = 64 << 20
MAX_FRAME_PIXELS = 1 << 25

# The formats the datasets ship (RE10K JPEG, DL3DV PNG / JPEG, Kubric PNG and TIFF depth). PIL
# would otherwise try every format it registers on untrusted bytes, EPS among them (Ghostscript).
IMAGE_FORMATS = ("JPEG", "PNG", "TIFF")

# What PIL raises for a malformed, truncated or oversized (> 2 x MAX_IMAGE_PIXELS) image.
_DECODE_ERRORS = (OSError, SyntaxError, ValueError, Image.DecompressionBombError)


def check_frame_bytes(size: int, *, where: str, error: type[ValueError] = ChunkError) -> None:
  """`error` naming `where` if an encoded frame of `size` bytes is more than `MAX_FRAME_BYTES`."""
  if size > MAX_FRAME_BYTES:
    raise error(f"{where}: {size} bytes, more than MAX_FRAME_BYTES {MAX_FRAME_BYTES}")


def _open(data: bytes, where: str, error: type[ValueError]) -> Image.Image:
  """`data` opened by PIL, which reads only the header; `error` unless its declared size is
  within `MAX_FRAME_PIXELS`."""
  try:
    image = Image.open(io.BytesIO(data), formats=IMAGE_FORMATS)
  except Image.UnidentifiedImageError:  # its message holds the buffer's repr: named by `where`
    raise error(
      f"{where}: corrupt image (not a {' / '.join(IMAGE_FORMATS)} file: no format recognises its "
      "header)"
    ) from None
  except _DECODE_ERRORS as cause:
    raise error(f"{where}: corrupt image ({cause})") from cause
  width, height = image.size
  if width * height > MAX_FRAME_PIXELS:
    image.close()
    raise error(
      f"{where}: the header declares {width}x{height} pixels, more than MAX_FRAME_PIXELS "
      f"{MAX_FRAME_PIXELS}"
    )
  return image


def image_size(data: bytes, *, where: str, error: type[ValueError] = ChunkError) -> tuple[int, int]:
  """(height, width) from an encoded image's header, no pixel decoded; `error` naming `where` for
  an unreadable header or one above `MAX_FRAME_PIXELS`."""
  with _open(data, where, error) as image:
    width, height = image.size
  return height, width


def decode_image(
  data: bytes, *, where: str, error: type[ValueError] = ChunkError, mode: str | None = None
) -> np.ndarray:
  """An encoded image's pixels (converted to `mode`, e.g. "RGB", when given), its header size
  checked first; `error` naming `where` for anything wrong with it."""
  with _open(data, where, error) as image:
    try:
      return np.asarray(image if mode is None else image.convert(mode))
    except _DECODE_ERRORS as cause:
      raise error(f"{where}: corrupt image ({cause})") from cause
