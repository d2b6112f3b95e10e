"""Writes `official_tiny.pth`: the tiny official fixture's weights as real `torch.save` writes them.

Not run by the tests (they never need torch); kept so the fixture can be re-made and checked:

    pip install --target /tmp/torch_check torch   # a CPU wheel is enough
    PYTHONPATH=/tmp/torch_check python tests/data/make_official_tiny_pth.py

The weights are `shared/fixtures/official_tokengs_tiny/weights.safetensors`, read with
safetensors' torch API and saved as an `nn.Module.state_dict()` is: an `OrderedDict` of tensors
carrying the `_metadata` attribute (one `{"version": 1}` entry per module prefix), which
`torch.save` pickles with a BUILD opcode after the items. `tests/test_model_official.py` checks
that loading this file gives exactly the params of the safetensors file.
"""

import collections
import pathlib

import torch
from safetensors.torch import load_file

HERE = pathlib.Path(__file__).resolve().parent
SOURCE = HERE.parents[2] / "shared/fixtures/official_tokengs_tiny/weights.safetensors"


def as_module_state_dict(tensors: dict[str, torch.Tensor]) -> collections.OrderedDict:
  state = collections.OrderedDict(sorted(tensors.items()))
  prefixes = {""} | {name.rsplit(".", 1)[0] for name in state if "." in name}
  # every ancestor module gets an entry too, as state_dict() visits the whole module tree
  prefixes |= {p.rsplit(".", i)[0] for p in prefixes for i in range(1, p.count(".") + 1)}
  state._metadata = collections.OrderedDict((p, {"version": 1}) for p in sorted(prefixes))
  return state


if __name__ == "__main__":
  torch.save(as_module_state_dict(load_file(SOURCE)), HERE / "official_tiny.pth")
