"""The sweep service: a grid of cells run as Ray Tune trials (tune.py), results in the store.

    plan.py       what to run: the grid read and resolved once (Plan) and how (RunOptions)
    ledger.py     the sweep's directory, manifest, lock, finished and failed cells
    preflight.py  what a run refuses before anything is written (directories, options, address, grid)
    signals.py    SIGTERM as Ctrl-C
    packing.py    the units a trial runs: one cell, or a pack of cells trained as one model
    trial.py      the one Tune trial function (worker side): a unit trained and written
    tune.py       the driver: Tune experiments, restore, the progress callback, disk-full handling
    ray_host.py   the embedded Ray (loopback only) or a joined cluster, signals, the reaper
    reaper.py     the program that ends the embedded Ray's processes when the driver dies
    base_cache.py, lease.py, spaces.py, progress.py: bases shared by a trial's cells, S3 leases, space
                  files, the progress line
"""

import os

# Before any module of this package imports Ray: no usage stats, none of the logger callbacks Tune adds by
# itself (its TensorBoard logger among them: rows live in Parquet; the JSON and CSV result logs are added
# explicitly, tune._tune_result_logs), the classic output.
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
os.environ.setdefault("TUNE_DISABLE_AUTO_CALLBACK_LOGGERS", "1")
os.environ.setdefault("RAY_AIR_NEW_OUTPUT", "0")
# Short cells finish in bursts and each one snapshots the experiment: Tune then warns every few
# seconds that snapshots "may become a bottleneck" (they cost milliseconds here). Keep the log readable.
os.environ.setdefault("TUNE_WARN_EXCESSIVE_EXPERIMENT_CHECKPOINT_SYNC_THRESHOLD_S", "0")
