#!/usr/bin/env bash
# Install the Debian packages that the marked tests need (chromium: browser checks; slurm-wlm and munge:
# a local SLURM cluster), where this can: as root with apt-get. Elsewhere it says what it skipped and
# why, and exits 0: those tests then skip cleanly, as the README's commands expect.
# .ci/run calls it first, so that CI on a fresh machine runs every test.
set -uo pipefail
want=()
command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1 || want+=(chromium)
command -v slurmctld >/dev/null 2>&1 || want+=(slurm-wlm)
command -v munged >/dev/null 2>&1 || want+=(munge)
if [ ${#want[@]} -eq 0 ]; then
  echo "system packages: chromium, slurm-wlm, munge present"
  exit 0
fi
if [ "$(id -u)" != 0 ] || ! command -v apt-get >/dev/null 2>&1; then
  echo "system packages: skipped installing ${want[*]} (needs root and apt-get); the tests that need them will skip"
  exit 0
fi
echo "system packages: installing ${want[*]}"
export DEBIAN_FRONTEND=noninteractive
if ! { apt-get update -qq && apt-get install -y -qq --no-install-recommends "${want[@]}"; } >/tmp/wast3d_apt.log 2>&1; then
  echo "system packages: apt-get failed (log: /tmp/wast3d_apt.log); the tests that need ${want[*]} will skip"
  tail -5 /tmp/wast3d_apt.log
fi
exit 0
