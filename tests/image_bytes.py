"""Encoded images that the image-decoding tests share (imported by them; no tests here): small
frames of a given format, and frames whose header declares a size their pixels do not have."""

import io
import struct
import zlib

from PIL import Image


def declaring_more_pixels(data: bytes, height: int, width: int) -> bytes:
  """A small JPEG or PNG whose header declares `height` x `width` (its pixels are not there)."""
  data = bytearray(data)
  if data.startswith(b"\x89PNG"):  # IHDR: width, height, then a CRC over type and data
    data[16:24] = struct.pack(">II", width, height)
    data[29:33] = struct.pack(">I", zlib.crc32(data[12:29]))
  else:  # baseline JPEG start of frame: marker, length, precision, height, width
    start = data.index(b"\xff\xc0")
    data[start + 5 : start + 9] = struct.pack(">HH", height, width)
  return bytes(data)


def encoded(format_name: str) -> bytes:
  buffer = io.BytesIO()
  Image.new("RGB", (8, 8)).save(buffer, format=format_name)
  return buffer.getvalue()
