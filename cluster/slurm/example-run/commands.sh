# exact commands of the real run (root, Debian 12 container, no systemd)
apt-get update && DEBIAN_FRONTEND=noninteractive apt-get install -y slurm-wlm
cp /work/main/cluster/slurm/slurm.conf.single-node /etc/slurm/slurm.conf
mkdir -p /var/spool/slurmctld /var/spool/slurmd /var/log/slurm /run/munge
chown munge:munge /run/munge
su -s /bin/sh munge -c 'munged --force'        # munged refuses to run as root
munge -n | unmunge | head -3
slurmctld                                        # daemonizes; log /var/log/slurm/slurmctld.log
nice -n 10 slurmd -N localhost                   # hostname is "vm": -N names the node; nice so the jobs yield to the calibration sweep
sinfo
srun -N1 hostname -I                             # job 1
# job 2: a fresh smoke sweep
cd /work/main
export SPACE=smoke RESULTS=/tmp/slurm-try/results RAY_TMP=/tmp/slurm-try/ray \
       RAY_START_ARGS=--object-store-memory=100000000 ACTIVATE='export PATH=/root/.pyenv/versions/3.11.7/bin:$PATH'
sbatch --output=/tmp/slurm-try/logs/%x-%j.out cluster/slurm/asp-dist-sweep.sbatch
squeue
# (wait until squeue is empty)
asp-dist status smoke --results /tmp/slurm-try/results
# job 3: the same job again: the manifest exists, so it resumes (18 already done)
sbatch --output=/tmp/slurm-try/logs/%x-%j.out cluster/slurm/asp-dist-sweep.sbatch
# job 4: the requeue path. A new sweep name, 1 worker so that it runs long enough to interrupt;
# USR1 to the batch shell (what --signal=B:USR1@120 sends before the time limit) once some cells are done
NAME=smoke-requeue WORKERS_PER_NODE=1 sbatch --output=/tmp/slurm-try/logs/%x-%j.out cluster/slurm/asp-dist-sweep.sbatch
until grep -qE "done [3-9]/18" /tmp/slurm-try/logs/asp-dist-sweep-4.out; do sleep 0.5; done
scancel --batch --signal=USR1 4
squeue; scontrol show job 4 | grep -E "JobState|Restarts|Requeue"
# (job 4 finished all 18 cells before the log showed progress: the counter line is not redrawn per cell in a log.
#  Second try: signal as soon as 3 cell files exist)
# job 5:
NAME=smoke-usr1 WORKERS_PER_NODE=1 sbatch --output=/tmp/slurm-try/logs/%x-%j.out cluster/slurm/asp-dist-sweep.sbatch
until [ "$(find /tmp/slurm-try/results/smoke-usr1/cells -name '*.parquet' 2>/dev/null | wc -l)" -ge 3 ]; do sleep 0.2; done
scancel --batch --signal=USR1 5
squeue; scontrol show job 5 | grep -E "JobState|Restarts|Requeue"
# (job 5 was requeued, started again after Slurm's requeue delay (EligibleTime = requeue + ~120 s) and resumed: 4 already done -> 18/18)
# job 6: the same USR1 test with the final script (stop_ray now signals srun itself; RAY_GRACEFUL_SHUTDOWN_DRAIN_TIMEOUT_S=0)
NAME=smoke-usr1b WORKERS_PER_NODE=1 sbatch --output=/tmp/slurm-try/logs/%x-%j.out cluster/slurm/asp-dist-sweep.sbatch
until [ "$(find /tmp/slurm-try/results/smoke-usr1b/cells -name '*.parquet' 2>/dev/null | wc -l)" -ge 3 ]; do sleep 0.2; done
scancel --batch --signal=USR1 6
squeue   # R, then CG, then PD (BeginTime), then R again
# job 7: requeue from outside (what an admin, preemption or `scontrol requeue` does): SIGTERM to every process of the job
NAME=smoke-ext WORKERS_PER_NODE=1 sbatch --output=/tmp/slurm-try/logs/%x-%j.out cluster/slurm/asp-dist-sweep.sbatch
until [ "$(find /tmp/slurm-try/results/smoke-ext/cells -name '*.parquet' 2>/dev/null | wc -l)" -ge 3 ]; do sleep 0.2; done
scontrol requeue 7
squeue
# job 8: the final script once more on the finished smoke sweep
sbatch --output=/tmp/slurm-try/logs/%x-%j.out cluster/slurm/asp-dist-sweep.sbatch
squeue
asp-dist status smoke --results /tmp/slurm-try/results
# job 9: final script version (Ray steps get -c $STEP_CPUS), a fresh sweep end to end
NAME=smoke-final sbatch --output=/tmp/slurm-try/logs/%x-%j.out cluster/slurm/asp-dist-sweep.sbatch
squeue
asp-dist status smoke-final --results /tmp/slurm-try/results
# stop the daemons started above (by PID: slurmd, slurmctld (its slurmscriptd child exits with it), munged)
kill -TERM 16290; kill -TERM 16277; kill -TERM 16249
# job 10: after adding the "not inside a Slurm job" guard, the committed script once more (daemons restarted the same way)
su -s /bin/sh munge -c 'munged --force'; slurmctld; nice -n 10 slurmd -N localhost; sinfo
NAME=smoke-last sbatch --output=/tmp/slurm-try/logs/%x-%j.out cluster/slurm/asp-dist-sweep.sbatch
asp-dist status smoke-last --results /tmp/slurm-try/results     # 18/18
kill -TERM 30005; kill -TERM 29993; kill -TERM 29986             # slurmd, slurmctld, munged of this second start
