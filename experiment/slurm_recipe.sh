#!/usr/bin/env bash
# A run of dagger.py on a Slurm cluster (experiment/RUNNING.md, "On a Slurm cluster"): three submissions, each
# waiting for the one before it to succeed (afterok):
#   1. the shared stages (--prepare: D0, pi_0, the BC row and their evaluations), one job;
#   2. the lineages as a job array, task i running --lineage i;
#   3. the report (--report), once every task of the array has finished.
#
#   experiment/slurm_recipe.sh PROFILE OUT [SBATCH OPTION ...]
#
# OUT is the run folder (relative to the repository, or absolute); every node that runs a job must see it (a shared
# filesystem). The jobs' output goes to OUT/slurm/. The options after OUT go to all three sbatch calls (e.g.
# --partition=cpu --time=2-00:00:00); a --cpus-per-task among them gives each lineage that many worker processes.
# Prints the three job IDs. Running it again on the same OUT resumes: every finished stage is loaded, not made again.
set -euo pipefail
if [ $# -lt 2 ]; then
  echo "usage: $0 PROFILE OUT [SBATCH OPTION ...]" >&2
  exit 2
fi
profile=$1 out=$2
shift 2
cd "$(dirname "$0")/.."  # the repository: sbatch runs each job in the folder it was called from, dagger.py's
lineages=$(python -c "import sys; from experiment.profiles import PROFILES; print(PROFILES[sys.argv[1]].lineages)" "$profile")
mkdir -p "$out/slurm"  # sbatch writes a job's output file, but makes no folder for it
run="python dagger.py --profile $(printf %q "$profile") --out $(printf %q "$out")"

# 2 CPUs: pi_0 trains on two threads (dagger.PI0_THREADS); the script's value wins over one given after OUT
prepare=$(sbatch --parsable "$@" --cpus-per-task=2 --job-name="$profile-prepare" \
            --output="$out/slurm/prepare-%j.out" --wrap "$run --prepare")
# single quotes: the task's own SLURM_ARRAY_TASK_ID and SLURM_CPUS_PER_TASK, read when it runs, not here
array=$(sbatch --parsable --cpus-per-task=1 "$@" --dependency=afterok:"$prepare" --array=0-$((lineages - 1)) \
          --job-name="$profile-lineage" --output="$out/slurm/lineage_%a-%A.out" \
          --wrap "$run"' --lineage $SLURM_ARRAY_TASK_ID --workers $SLURM_CPUS_PER_TASK')
report=$(sbatch --parsable "$@" --dependency=afterok:"$array" --job-name="$profile-report" \
           --output="$out/slurm/report-%j.out" --wrap "$run --report")
echo "$prepare $array $report"
