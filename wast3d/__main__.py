import os
import sys

# Before torch (and its OpenMP runtime) loads: OpenMP threads that finish a parallel region sleep
# instead of spinning. Spinning threads take the cores from any other process on the machine (a second
# Snakemake job, a shared cluster node): a 50k-Gaussian render went from 0.08 s to 4.6 s beside another
# torch process, 0.21 s with the passive policy (issue #14). Set OMP_WAIT_POLICY to override.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from .cli import main  # noqa: E402

sys.exit(main())
