"""`python -m asp_dist` is the `asp-dist` command."""

from __future__ import annotations

import sys

from asp_dist.cli import main

sys.exit(main())
