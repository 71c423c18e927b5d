"""One torch thread, as a sweep worker runs a cell (1 CPU each): the tests' timings then do not
depend on how many cores the machine has or how busy they are."""

import torch

torch.set_num_threads(1)
