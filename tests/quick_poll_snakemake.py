"""Snakemake's command line with the SLURM executor's status polls at most ``QUICK_POLL_S`` apart.

    python tests/quick_poll_snakemake.py [snakemake arguments]

The SLURM executor plugin (2.x) waits 10 s longer after every status round in which no job finished,
up to 180 s: a back-off hard-coded for shared clusters, with no setting. On the one-node test cluster
that waiting was most of the SLURM tests' six minutes. This caps the wait only: every job is still
submitted with sbatch, run by slurmd and its state read with squeue, as the profile says.
"""

import sys

from snakemake_interface_executor_plugins.executors.remote import RemoteExecutor

QUICK_POLL_S = 2

_interval = RemoteExecutor.next_seconds_between_status_checks
RemoteExecutor.next_seconds_between_status_checks = _interval.setter(
    lambda self, seconds: _interval.fset(self, min(seconds, QUICK_POLL_S)))

if __name__ == "__main__":
    from snakemake.cli import main

    sys.exit(main())
