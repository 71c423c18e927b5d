"""Files an attacker could plant where asp-dist reads stored tensors: pickles that run code when unpickled."""

from __future__ import annotations

import io
import pickle
from pathlib import Path

import torch


class Marker:
    """Unpickling this creates `path` (builtins.open in write mode): the file appearing means code ran."""

    def __init__(self, path: Path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def torch_pickle(marker: Path) -> bytes:
    """A torch.save file (what torch.load reads) whose payload runs code: inside a base-like dict."""
    buf = io.BytesIO()
    torch.save({"format": "asp-dist base", "version": 2, "weights": {}, "payload": Marker(marker)}, buf)
    return buf.getvalue()


def raw_pickle(marker: Path) -> bytes:
    """A bare pickle (no zip container), which older torch.load also accepted."""
    return pickle.dumps(Marker(marker), protocol=4)


PLANTS = {"torch-pickle": torch_pickle, "raw-pickle": raw_pickle}
