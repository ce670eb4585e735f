"""A one-node Slurm cluster on localhost for the launcher's tests: Debian's slurm-wlm and munge, started from a
generated slurm.conf in a temporary folder (state, spool, logs and munge's socket all in it), stopped by the pids
this module started. `python tests/launch/slurm_cluster.py DIR` starts one and prints the SLURM_CONF to export (Ctrl-C
stops it), for trying the launcher by hand."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time

DAEMONS = ("munged", "mungekey", "slurmctld", "slurmd", "sbatch", "squeue", "scontrol")


def missing() -> str | None:
    """Why no cluster can be started here (None when it can)."""
    absent = [name for name in DAEMONS if shutil.which(name) is None
              and not os.path.exists(os.path.join("/usr/sbin", name))]
    if absent:
        return (f"Slurm is not installed ({', '.join(absent)} not found): apt-get install slurm-wlm munge "
                "(.ci/run does)")
    if os.geteuid() != 0:
        return "the local Slurm cluster runs its daemons as root (SlurmUser=root); run the tests as root"
    return None


def _exe(name: str) -> str:
    return shutil.which(name) or os.path.join("/usr/sbin", name)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _node_line() -> str:
    """slurmd -C's CPUs and memory for this machine, under the name localhost."""
    out = subprocess.run([_exe("slurmd"), "-C"], capture_output=True, text=True, check=True).stdout
    first = out.splitlines()[0].split()
    fields = dict(f.split("=", 1) for f in first[1:])
    mem = int(fields["RealMemory"]) - 512  # slurmd refuses a node that reports less than configured
    return (f"NodeName=localhost NodeAddr=127.0.0.1 NodeHostname=localhost CPUs={fields['CPUs']} "
            f"RealMemory={mem} State=UNKNOWN")


class Cluster:
    """Start with Cluster(folder).start(); env() gives the environment clients need; stop() ends the daemons."""

    def __init__(self, folder: str):
        self.folder = os.path.abspath(folder)
        self.conf = os.path.join(self.folder, "slurm.conf")
        self.procs: dict[str, subprocess.Popen] = {}
        self.munge_pid: int | None = None

    def env(self, base: dict | None = None) -> dict:
        return {**(os.environ if base is None else base), "SLURM_CONF": self.conf}

    def _write_conf(self) -> None:
        f = self.folder
        for sub in ("state", "spool", "munge"):
            os.makedirs(os.path.join(f, sub), exist_ok=True)
        os.chmod(os.path.join(f, "munge"), 0o700)
        text = f"""# generated for the launcher's tests: one node, no accounting database
ClusterName=ctgstest
SlurmctldHost=localhost(127.0.0.1)
SlurmctldPort={_free_port()}
SlurmdPort={_free_port()}
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket={f}/munge/munge.socket,cred_expire=10
StateSaveLocation={f}/state
SlurmdSpoolDir={f}/spool
SlurmctldPidFile={f}/slurmctld.pid
SlurmdPidFile={f}/slurmd.pid
SlurmctldLogFile={f}/slurmctld.log
SlurmdLogFile={f}/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
SchedulerType=sched/backfill
SchedulerParameters=bf_interval=1,sched_interval=2
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
MpiDefault=none
ReturnToService=2
MinJobAge=600
KillWait=30
SlurmctldTimeout=30
SlurmdTimeout=30
{_node_line()}
PartitionName=debug Nodes=localhost Default=YES MaxTime=INFINITE State=UP
"""
        with open(self.conf, "w") as fh:
            fh.write(text)

    def _start_munge(self) -> None:
        m = os.path.join(self.folder, "munge")
        key = os.path.join(m, "munge.key")
        subprocess.run([_exe("mungekey"), "--create", f"--keyfile={key}"], check=True, capture_output=True)
        pidfile = os.path.join(m, "munged.pid")
        subprocess.run([_exe("munged"), "--force", f"--socket={m}/munge.socket", f"--key-file={key}",
                        f"--pid-file={pidfile}", f"--log-file={m}/munged.log", f"--seed-file={m}/munged.seed"],
                       check=True, capture_output=True)
        # munged daemonizes; its pid is in the pid file it wrote
        for _ in range(50):
            if os.path.exists(pidfile) and open(pidfile).read().strip():
                self.munge_pid = int(open(pidfile).read().strip())
                return
            time.sleep(0.1)
        raise RuntimeError(f"munged did not start: {open(os.path.join(m, 'munged.log')).read()[-2000:]}")

    def start(self, timeout: float = 60) -> "Cluster":
        self._write_conf()
        self._start_munge()
        env = self.env()
        log = open(os.path.join(self.folder, "daemons.out"), "ab")
        # -D: in the foreground, so the pid is the Popen's; -i: ignore a stale state folder; -N: the node's name
        self.procs["slurmctld"] = subprocess.Popen([_exe("slurmctld"), "-D", "-i", "-f", self.conf], env=env,
                                                   stdout=log, stderr=log, start_new_session=True)
        self.procs["slurmd"] = subprocess.Popen([_exe("slurmd"), "-D", "-N", "localhost", "-f", self.conf], env=env,
                                                stdout=log, stderr=log, start_new_session=True)
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for name, p in self.procs.items():
                if p.poll() is not None:
                    raise RuntimeError(f"{name} exited ({p.returncode}): {self.logs()}")
            r = subprocess.run(["sinfo", "-h", "-N", "-o", "%T"], env=env, capture_output=True, text=True)
            if r.returncode == 0 and r.stdout.strip() in ("idle", "mixed", "allocated"):
                return self
            time.sleep(0.5)
        raise RuntimeError(f"the node did not come up in {timeout:.0f} s: {self.logs()}")

    def logs(self) -> str:
        out = []
        for name in ("slurmctld.log", "slurmd.log", "daemons.out", "munge/munged.log"):
            path = os.path.join(self.folder, name)
            if os.path.exists(path):
                out.append(f"--- {name}\n" + open(path, errors="replace").read()[-3000:])
        return "\n".join(out)

    def stop(self) -> None:
        """End what start() started, by pid: the daemons, then munged. Jobs still running are ended first."""
        if self.procs.get("slurmctld") and self.procs["slurmctld"].poll() is None:
            env = self.env()
            subprocess.run(["scancel", "--user", str(os.getuid())], env=env, capture_output=True, timeout=30)
            end = time.monotonic() + 60  # slurmd ends the jobs' processes (KillWait), then the queue is empty
            while time.monotonic() < end:
                r = subprocess.run(["squeue", "-h"], env=env, capture_output=True, text=True, timeout=30)
                if r.returncode != 0 or not r.stdout.strip():
                    break
                time.sleep(0.5)
        for name in ("slurmd", "slurmctld"):
            p = self.procs.get(name)
            if p is None or p.poll() is not None:
                continue
            p.terminate()
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(timeout=10)
        if self.munge_pid:
            try:
                os.kill(self.munge_pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
            self.munge_pid = None


if __name__ == "__main__":
    why = missing()
    if why:
        sys.exit(why)
    cluster = Cluster(sys.argv[1] if len(sys.argv) > 1 else "slurm-local").start()
    print(f"export SLURM_CONF={cluster.conf}", flush=True)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    try:
        signal.pause()
    except KeyboardInterrupt:
        pass
    finally:
        cluster.stop()
