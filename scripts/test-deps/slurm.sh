#!/bin/sh
# Installs Debian's Slurm and MUNGE for the Slurm test (tests/alone/slurm.rs):
# it starts its own munged, slurmctld and slurmd in a temporary directory and
# submits workers with sbatch. Does nothing when they are all on PATH (munged
# and the daemons are in /usr/sbin). Needs root (apt-get) when it installs.
set -eu
PATH="$PATH:/usr/sbin:/sbin"
have() { command -v "$1" >/dev/null 2>&1; }
if have munged && have slurmctld && have slurmd && have sbatch && have squeue && have scancel; then
    exit 0
fi
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq
apt-get install -y -qq --no-install-recommends slurm-wlm munge >/dev/null
slurmctld -V
