"""Record the golden rows: (cd tests && python -m golden.record); see tests/golden/cells.py."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import torch
from golden.cells import golden_specs

OUT = Path(__file__).with_name("rows.parquet")
# Columns that may differ between code revisions or runs without any change in behaviour.
IGNORED = {"code_revision", "asp_dist_version"}


def run_golden_rows() -> pd.DataFrame:
    from asp_dist.spec import CellSpec
    from asp_dist.training.cell import run_cell
    from asp_dist.training.row import comparable

    torch.set_num_threads(1)
    rows = [comparable(run_cell(CellSpec(**d))) for d in golden_specs()]
    frame = pd.DataFrame([{k: v for k, v in r.items() if k not in IGNORED} for r in rows])
    frame["cpu_capability"] = torch.backends.cpu.get_cpu_capability()
    return frame


if __name__ == "__main__":
    frame = run_golden_rows()
    frame.to_parquet(OUT, index=False)
    print(f"wrote {len(frame)} rows x {len(frame.columns)} columns to {OUT}")
