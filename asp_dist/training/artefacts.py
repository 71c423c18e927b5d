"""The tensors asp-dist stores (bases, cell and pack checkpoints), and the one way they are read back.

A stored artefact is ``torch.save`` of plain containers only: dicts, lists, tuples, strings, numbers, None
and tensors, never a pickled object of a class. It is read back with ``torch.load(weights_only=True)``, whose
unpickler builds nothing but those: a file planted in a results directory (a shared bucket, a copied sweep)
that asks for any other global, as a pickle whose ``__reduce__`` runs code does, is refused instead of run.
(docs/decisions/0057-stored-artefacts-hold-no-code.md)

Every way a stored file can be wrong (truncated, empty, not a torch file, asking for a global, of an old
format) is one ``DamagedArtefact`` whose message is one line: the caller sets the file aside and makes the
artefact again (a base is retrained, a checkpoint's cell starts over).
"""

from __future__ import annotations

import io
import re
from typing import Any


class DamagedArtefact(RuntimeError):
    """A stored base or checkpoint that cannot be read safely; its message is one line naming the file."""


def to_bytes(obj: Any) -> bytes:
    """`obj` (plain containers of tensors, strings and numbers) as the bytes torch.save writes."""
    import torch

    buf = io.BytesIO()
    torch.save(obj, buf)
    return buf.getvalue()


def from_bytes(data: bytes, what: str) -> Any:
    """What to_bytes stored, read without running code; DamagedArtefact (one line naming `what`) for any
    file that is not such an artefact."""
    import pickle
    import warnings

    import torch

    try:
        with warnings.catch_warnings():  # a raw pickle of another protocol: refused below, no warning first
            warnings.simplefilter("ignore")
            return torch.load(io.BytesIO(data), weights_only=True, map_location="cpu")
    except pickle.UnpicklingError as err:  # weights_only's refusal: a global it will not build (code, or a class)
        raise DamagedArtefact(f"{what} is not a plain-tensor artefact of this asp-dist (written by older code, or "
                              f"planted: {_first_line(err, 'a global it will not load')}); refused unread") from None
    except (RuntimeError, EOFError, ValueError, TypeError, KeyError, AttributeError, OSError) as err:
        raise DamagedArtefact(f"{what} cannot be read ({_first_line(err, type(err).__name__)})") from None


def load_file(path: Any, what: str | None = None) -> Any:
    """from_bytes of a local or S3 file (what: how to name it, default its path). FileNotFoundError passes."""
    return from_bytes(path.read_bytes(), what or str(path))


def require(condition: bool, what: str, problem: str) -> None:
    """DamagedArtefact unless `condition`: for a file that loads but does not hold what its reader expects."""
    if not condition:
        raise DamagedArtefact(f"{what} {problem}")


def _first_line(err: BaseException, fallback: str) -> str:
    """The error's first meaningful line, shortened: torch's messages run to a page of advice. For
    weights_only's refusal, the line naming the global it would not load."""
    text = str(err).strip()
    asked = re.search(r"GLOBAL ([\w.]+)", text)
    if asked:  # weights_only names the callable or class the file asks for
        return f"it asks for {asked[1]}"
    operand = re.search(r"Unsupported operand \d+", text)
    if operand:
        return operand[0]
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    first = lines[0].split(". This is an internal")[0] if lines else fallback  # miniz's advice: not about the file
    return " ".join(first.split())[:200]
