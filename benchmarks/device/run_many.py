"""Many small trainings on one device at once, in priority order, until a deadline: for measurements that need
many runs of a small image (on a GPU each is launch-bound, so several share the card well).

    python3 benchmarks/device/run_many.py JOBS --slots K --stop-after SECONDS [--root /tmp/many]

JOBS: one job per line, `NAME ctgs-train-arguments...` (blank lines and # comments skipped), in priority order;
each runs as `python3 -m ctgs train ARGS -o ROOT/NAME -q` with one CPU thread. At most K run at once. After
SECONDS from the start the runs still going are stopped (SIGTERM; their log.jsonl keeps what they logged) and the
jobs not started are listed as such. ROOT/status.json says, per job, its state (done / stopped / failed /
not started), its wall seconds and exit code, and is rewritten on every change; ROOT/DONE appears at the end.
Meant to run detached (setsid nohup ... &) so that it outlives a device call while the machine stays warm; a
later call waits for ROOT/DONE and packs ROOT (benchmarks/device/many.sh; docs/guide/gpu.md).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import signal
import subprocess
import sys
import time


def read_jobs(path: str) -> list[tuple[str, list[str]]]:
    jobs = []
    with open(path) as fh:
        for n, line in enumerate(fh, 1):
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            name, *args = shlex.split(line)
            if any(name == j[0] for j in jobs):
                raise SystemExit(f"run_many.py: {path}:{n}: job name {name!r} used twice; give each job its own name")
            jobs.append((name, args))
    if not jobs:
        raise SystemExit(f"run_many.py: {path} lists no jobs (one per line: NAME ctgs-train-arguments...)")
    return jobs


def write_status(root: str, status: dict) -> None:
    tmp = os.path.join(root, "status.json.tmp")
    with open(tmp, "w") as fh:
        json.dump(status, fh, indent=1)
    os.replace(tmp, os.path.join(root, "status.json"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("jobs")
    ap.add_argument("--slots", type=int, default=4)
    ap.add_argument("--stop-after", type=float, required=True, help="seconds from the start")
    ap.add_argument("--root", default="/tmp/many")
    args = ap.parse_args()
    jobs = read_jobs(args.jobs)
    os.makedirs(args.root, exist_ok=True)
    for f in ("DONE", "status.json"):
        if os.path.exists(os.path.join(args.root, f)):
            os.remove(os.path.join(args.root, f))
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    t0 = time.time()
    status = {"started": t0, "slots": args.slots, "stop_after": args.stop_after,
              "jobs": {name: {"state": "not started", "args": a} for name, a in jobs}}
    write_status(args.root, status)
    queue = list(jobs)
    running: dict[str, tuple[subprocess.Popen, float]] = {}
    stopping = False
    while queue or running:
        for name, (proc, ts) in list(running.items()):
            rc = proc.poll()
            if rc is not None:
                st = status["jobs"][name]
                st.update(rc=rc, wall_s=round(time.time() - ts, 1),
                          state="stopped" if stopping else ("done" if rc == 0 else "failed"))
                del running[name]
                write_status(args.root, status)
        if not stopping and time.time() - t0 >= args.stop_after:
            stopping = True
            queue.clear()
            for proc, _ in running.values():
                proc.send_signal(signal.SIGTERM)
        while not stopping and queue and len(running) < args.slots:
            name, a = queue.pop(0)
            run = os.path.join(args.root, name)
            cmd = [sys.executable, "-m", "ctgs", "train", *a, "-o", run, "-q"]
            with open(os.path.join(args.root, name + ".log"), "w") as log:  # the child keeps its own copy
                running[name] = (subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env,
                                                  stdin=subprocess.DEVNULL), time.time())
            status["jobs"][name].update(state="running", start_s=round(time.time() - t0, 1))
            write_status(args.root, status)
        time.sleep(1.0)
    status["wall_s"] = round(time.time() - t0, 1)
    write_status(args.root, status)
    open(os.path.join(args.root, "DONE"), "w").close()


if __name__ == "__main__":
    main()
