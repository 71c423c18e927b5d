"""training.torch_runtime: a process that trains cells never imports torch._dynamo (≈ 2 CPU-s each Ray worker
paid), and its optimizers compute exactly what torch's own do -- before and after something loads dynamo.

Each check runs in a fresh interpreter: whether torch._dynamo is loaded is a property of the process, and
this test process may have loaded it already."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

TRAIN = """
import hashlib, json, sys
sys.path.insert(0, "tests")
import torch

OPTIONS = {"default": {}, "for-loop": {"foreach": False}, "fused": {"fused": True}}

def train(options):  # 20 Adam steps with a checkpoint's round trip halfway, as a restored trial does it
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.Tanh(), torch.nn.Linear(8, 2))
    opt = torch.optim.Adam(net.parameters(), lr=1e-2, **options)
    for i in range(20):
        opt.zero_grad()
        net(torch.randn(16, 4)).square().mean().backward()
        opt.step()
        if i == 9:
            state = opt.state_dict()
            opt = torch.optim.Adam(net.parameters(), lr=1e-2, **options)
            opt.load_state_dict(state)
    return hashlib.sha256(b"".join(p.detach().numpy().tobytes() for p in net.parameters())).hexdigest()
"""

SHORTCUT = TRAIN + """
from asp_dist.training import torch_runtime
covered = torch_runtime.keep_dynamo_unloaded()
from golden.record import run_golden_rows
domains = sorted(set(run_golden_rows()["domain"]))
shortcut = {name: train(o) for name, o in OPTIONS.items()}
loaded_while_training = "torch._dynamo" in sys.modules
import torch._dynamo
after = {name: train(o) for name, o in OPTIONS.items()}
handed_over = [getattr(fn, torch_runtime.CACHE_ATTRIBUTE).__module__
               for fn, _ in torch_runtime.dynamo_disabled_methods()]
print(json.dumps(dict(covered=covered, domains=domains, loaded_while_training=loaded_while_training,
                      shortcut=shortcut, after=after, handed_over=handed_over)))
"""

REFERENCE = TRAIN + """
import torch._dynamo  # torch's own wrappers in charge from the first call
print(json.dumps({name: train(o) for name, o in OPTIONS.items()}))
"""


def python(code: str) -> dict:
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_cells_train_without_loading_dynamo_and_optimizers_compute_what_torchs_own_do():
    """- the golden cells (every built-in domain; single and packed engines, bases) train in a process that
      never imports torch._dynamo;
    - Adam's steps (default, for-loop and fused kernels, a state-dict round trip) are bit for bit those of
      torch's own path, before dynamo loads and after (when the covered methods hand over to torch)."""
    ours, reference = python(SHORTCUT), python(REFERENCE)
    if ours["covered"] == 0:
        pytest.skip("this torch's dynamo wrappers are not the shape torch_runtime knows: it pays the import, "
                    "as before")
    assert not ours["loaded_while_training"], f"torch._dynamo was imported while training {ours['domains']}"
    assert {"particles", "vae", "levers"} <= set(ours["domains"])
    assert ours["shortcut"] == reference, "the shortcut's optimizer steps differ from torch's own"
    assert ours["after"] == reference, "after dynamo loaded, the optimizer computed otherwise"
    assert ours["handed_over"] and all(m.startswith("torch._dynamo") for m in ours["handed_over"]), \
        f"after dynamo loaded, a covered method kept the shortcut: {ours['handed_over']}"
