"""Reads back what a TensorBoard writer wrote (the tests have no `tensorboard` package): the
event files' records, parsed with tensorboardX's own protobuf classes."""

import pathlib
import struct

from tensorboardX.proto import event_pb2


def events(folder) -> list:
  """Every `Event` of the `events.out.tfevents.*` files in `folder`, in file order (each record:
  its length as 8 little-endian bytes, 4 bytes of CRC, the payload, 4 bytes of CRC)."""
  read = []
  for path in sorted(pathlib.Path(folder).glob("events.out.tfevents.*")):
    data, offset = path.read_bytes(), 0
    while offset < len(data):
      (length,) = struct.unpack("<Q", data[offset : offset + 8])
      read.append(event_pb2.Event.FromString(data[offset + 12 : offset + 12 + length]))
      offset += 12 + length + 4
  return read


def summaries(folder) -> dict[str, dict[int, object]]:
  """tag -> step -> its `Summary.Value` (`.simple_value`, `.image`, `.histo`)."""
  tags = {}
  for event in events(folder):
    for value in event.summary.value:
      tags.setdefault(value.tag, {})[event.step] = value
  return tags
