import os
import sys

# Before torch (and its OpenMP runtime) loads: idle OpenMP threads sleep instead of spinning on cores
# another process needs (docs/workflow.md, *Threads and profiles*). Set OMP_WAIT_POLICY to override.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from .cli import main  # noqa: E402

sys.exit(main())
