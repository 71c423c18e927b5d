"""Adam over one flat parameter buffer: a handful of tensor ops per step, whatever the model.

torch.optim.Adam walks its parameter list in Python (grouping, hooks, per-tensor state) and
that overhead, about 0.2–0.4 ms per step, is larger than the arithmetic for the paper's tiny
networks. FlatAdam re-points every parameter of a module into one contiguous buffer, so a
step is six vectorised ops, and gives a matching flat gradient buffer whose per-parameter
views hand-written backward passes fill with ``out=``. The module keeps working as before:
its parameters *are* views of the buffer, so state_dict, load_state_dict and forward calls
see every update. The arithmetic is torch's single-tensor Adam (no weight decay, no amsgrad).
"""

from __future__ import annotations

import math
from typing import Any, Iterable

import torch


class FlatAdam:
    def __init__(self, params: Iterable[torch.nn.Parameter], lr: float, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8):
        params = list(params)
        total = sum(p.numel() for p in params)
        self.lr, self.betas, self.eps = lr, betas, eps
        self.param = torch.empty(total)
        self.grad = torch.zeros(total)
        self.param_views: list[torch.Tensor] = []
        self.grad_views: list[torch.Tensor] = []
        offset = 0
        for p in params:
            n = p.numel()
            view = self.param[offset:offset + n].view_as(p)
            view.copy_(p.detach())
            p.data = view  # the module now reads and writes the flat buffer
            self.param_views.append(view)
            self.grad_views.append(self.grad[offset:offset + n].view_as(p))
            offset += n
        self.exp_avg = torch.zeros(total)
        self.exp_avg_sq = torch.zeros(total)
        self.steps = 0

    def step(self) -> None:
        """One Adam update from the current contents of ``self.grad``."""
        beta1, beta2 = self.betas
        self.steps += 1
        self.exp_avg.lerp_(self.grad, 1 - beta1)
        self.exp_avg_sq.mul_(beta2).addcmul_(self.grad, self.grad, value=1 - beta2)
        denom = (self.exp_avg_sq.sqrt() / math.sqrt(1 - beta2 ** self.steps)).add_(self.eps)
        self.param.addcdiv_(self.exp_avg, denom, value=-self.lr / (1 - beta1 ** self.steps))

    def state_dict(self) -> dict[str, Any]:
        return {"steps": self.steps, "exp_avg": self.exp_avg.clone(), "exp_avg_sq": self.exp_avg_sq.clone()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.steps = int(state["steps"])
        self.exp_avg.copy_(state["exp_avg"])
        self.exp_avg_sq.copy_(state["exp_avg_sq"])
