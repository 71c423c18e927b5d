import sys

from asp_dist.cli import main

sys.exit(main())
