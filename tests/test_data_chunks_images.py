"""`data.chunks.images`: bounded image decoding. Frames decode to their pixels; a frame over a
bound, corrupt or of a format the datasets do not ship is refused with the caller's error type,
naming the caller's `where`."""

import io

import numpy as np
import pytest
from image_bytes import declaring_more_pixels, encoded
from PIL import Image

from tokengs_jax.data import chunks
from tokengs_jax.data.chunks import ChunkError, images


class _ReaderError(ValueError):
  """A caller's own data error type (as the DL3DV and Kubric readers pass theirs)."""


def _pixels(height=5, width=7):
  return np.random.default_rng(0).integers(0, 256, (height, width, 3), dtype=np.uint8)


def _save(array: np.ndarray, format_name: str, **kwargs) -> bytes:
  buffer = io.BytesIO()
  Image.fromarray(array).save(buffer, format=format_name, **kwargs)
  return buffer.getvalue()


@pytest.mark.parametrize("format_name", ["JPEG", "PNG"])
def test_an_image_pil_only_warns_about_is_refused_before_decoding(format_name, no_pixel_decoding):
  # 100M pixels: PIL warns (above 89M) but decodes; a 631-byte JPEG took 1.3 GB
  data = declaring_more_pixels(encoded(format_name), 10_000, 10_000)
  with pytest.warns(Image.DecompressionBombWarning):
    with pytest.raises(ChunkError, match=r"^c scene 's' frame 3: the header declares 10000x10000"):
      chunks.decode_jpeg(data, where="c scene 's' frame 3")


def test_image_errors_name_the_frame_and_are_the_same_every_run():
  # PIL's message named `<_io.BytesIO object at 0x...>`, another address in every run
  where = "c.torch scene 's' frame 0"
  for read in (chunks.jpeg_size, chunks.decode_jpeg):
    with pytest.raises(ChunkError) as error:
      read(b"not an image", where=where)
    assert str(error.value) == (
      f"{where}: corrupt image (not a JPEG / PNG / TIFF file: no format recognises its header)"
    )


@pytest.mark.parametrize("format_name", ["GIF", "BMP", "ICO"])
def test_only_the_formats_datasets_ship_are_opened(format_name):
  # every format PIL registers would otherwise parse untrusted bytes (EPS runs Ghostscript)
  with pytest.raises(ChunkError, match=r"^f: corrupt image \(not a JPEG / PNG / TIFF file"):
    chunks.decode_jpeg(encoded(format_name), where="f")


def test_a_png_decodes_to_its_exact_pixels():
  pixels = _pixels()
  decoded = images.decode_image(_save(pixels, "PNG"), where="f.png")
  assert decoded.shape == (5, 7, 3) and decoded.dtype == np.uint8
  np.testing.assert_array_equal(decoded, pixels)


def test_a_jpeg_decodes_to_its_shape_and_converts_to_the_mode_asked():
  flat = np.full(
    (6, 10, 3), (200, 40, 90), np.uint8
  )  # one colour: JPEG keeps it within a level or two
  data = _save(flat, "JPEG", quality=95)
  rgb = images.decode_image(data, where="f.jpg", mode="RGB")
  assert rgb.shape == (6, 10, 3) and rgb.dtype == np.uint8
  assert np.abs(rgb.astype(int) - flat).max() <= 3
  grey = images.decode_image(data, where="f.jpg", mode="L")
  assert grey.shape == (6, 10) and grey.dtype == np.uint8
  expected = (200 * 299 + 40 * 587 + 90 * 114) / 1000  # ITU-R 601-2 luma, PIL's "L"
  assert np.abs(grey.astype(float) - expected).max() <= 3


def test_image_size_reads_height_and_width_from_the_header_alone(no_pixel_decoding):
  assert images.image_size(_save(_pixels(5, 7), "PNG"), where="f") == (5, 7)
  assert images.image_size(_save(_pixels(9, 4), "JPEG"), where="f") == (9, 4)


def test_the_pixel_bound_admits_exactly_max_frame_pixels(no_pixel_decoding):
  png = encoded("PNG")
  height, width = 4096, images.MAX_FRAME_PIXELS // 4096  # 4096 x 8192 = 2^25
  assert images.image_size(declaring_more_pixels(png, height, width), where="f") == (height, width)
  over = declaring_more_pixels(png, height, width + 1)
  with pytest.raises(_ReaderError, match=rf"^a\.png: the header declares {width + 1}x{height} "):
    images.image_size(over, where="a.png", error=_ReaderError)
  with pytest.raises(_ReaderError, match=r"^a\.png: the header declares"):
    images.decode_image(over, where="a.png", error=_ReaderError)


def test_check_frame_bytes_admits_the_bound_and_refuses_one_byte_more():
  images.check_frame_bytes(images.MAX_FRAME_BYTES, where="f")
  with pytest.raises(ChunkError, match=r"^f: 67108865 bytes, more than MAX_FRAME_BYTES 67108864$"):
    images.check_frame_bytes(images.MAX_FRAME_BYTES + 1, where="f")
  with pytest.raises(_ReaderError, match=r"^scene 's' frame 2: 67108865 bytes"):
    images.check_frame_bytes(
      images.MAX_FRAME_BYTES + 1, where="scene 's' frame 2", error=_ReaderError
    )


def test_a_truncated_frame_is_a_corrupt_image_naming_the_file():
  data = _save(_pixels(32, 32), "PNG")
  truncated = data[: len(data) // 2]  # a header that opens, pixel data that ends early
  with pytest.raises(_ReaderError, match=r"^scene 's' frame 1 \(f\.png\): corrupt image \("):
    images.decode_image(truncated, where="scene 's' frame 1 (f.png)", error=_ReaderError)
