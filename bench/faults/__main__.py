"""``python -m selfview.bench.faults`` (or ``python bench/faults``): the fault campaign, one JSON object."""

import sys

from selfview.bench.faults.runner import main

sys.exit(main())
