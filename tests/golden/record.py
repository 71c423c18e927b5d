"""Record the golden rows: (cd tests && python -m golden.record); see tests/golden/cells.py. Writes
rows.parquet and, in machine.json, the fingerprint of the machine that recorded them (the rows are
bit-exact only on a machine of the same fingerprint: tests/test_golden_rows.py)."""

from __future__ import annotations

import datetime
import hashlib
import json
import platform
from pathlib import Path

import pandas as pd
import torch
from golden.cells import golden_specs

OUT = Path(__file__).with_name("rows.parquet")
MACHINE = Path(__file__).with_name("machine.json")
# Columns that may differ between code revisions or runs without any change in behaviour.
IGNORED = {"code_revision", "asp_dist_version"}


def _cpuinfo() -> dict[str, str]:
    """The first processor's fields of /proc/cpuinfo ({} where there is none, e.g. macOS)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return {}
    fields: dict[str, str] = {}
    for line in text.split("\n\n")[0].splitlines():
        key, _, value = line.partition(":")
        fields[key.strip()] = value.strip()
    return fields


def machine_fingerprint() -> dict[str, str | None]:
    """What decides how float32 results round here: the CPU (vendor, model, its flags), torch's build
    and the SIMD kernels it dispatches to (ATEN_CPU_CAPABILITY can lower them). None where unknown;
    two machines with equal, complete fingerprints compute the golden rows bit for bit."""
    cpu = _cpuinfo()
    flags = cpu.get("flags") or cpu.get("Features")  # (x86 | arm)
    flags_hash = hashlib.sha256(" ".join(sorted(flags.split())).encode()).hexdigest()[:16] if flags else None
    model = [cpu.get(k) for k in ("cpu family", "model", "stepping")]
    return {
        "arch": platform.machine() or None,
        "cpu_vendor": cpu.get("vendor_id"),
        "cpu_model_name": cpu.get("model name"),
        "cpu_family_model_stepping": "/".join(model) if all(model) else None,
        "cpu_flags_sha256": flags_hash,
        "torch_version": torch.__version__,
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
    }


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
    MACHINE.write_text(json.dumps({"recorded": datetime.date.today().isoformat(),
                                   "fingerprint": machine_fingerprint()}, indent=2) + "\n")
    print(f"wrote {len(frame)} rows x {len(frame.columns)} columns to {OUT}, the machine to {MACHINE}")
