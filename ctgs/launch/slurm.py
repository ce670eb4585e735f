"""`make all SCENES="..." LAUNCHER=slurm`: the sweep as Slurm jobs, one per scene, and a last job for the table.

The Makefile calls this module (`python -m ctgs.launch.slurm submit|status|resumed`); nothing here schedules
anything itself. A submission writes, under RUNS/slurm/:

- <stamp>/scene.sh   the batch script of a job array, task i = scene i: it runs the scene's make targets (the
  same file targets as a local `make all`: fetch if missing, train, export, compress, eval) on the node, its
  output appended to RUNS/<scene>/slurm.log. Submitted with --requeue --signal=B:TERM@N: when Slurm warns
  of a time limit or a preemption, the script stops the training (which keeps its last checkpoint), requeues
  the job, and the requeued job runs the same targets, whose train rule resumes from the checkpoint.
- <stamp>/table.sh   the last job (afterany on the scenes): `make table` once every scene is finished, else a
  line naming the scenes that are not.
- jobs.json          scene -> its job (array id_task), and the table job: what `make status` asks Slurm about
  and what a re-run does not submit twice.

Both scripts are the templates of ctgs/launch/templates/, filled in for the submission. A re-run submits only the
scenes that are neither finished (both eval metrics files written) nor still queued.
Slurm options come from a TOML file (configs/slurm/defaults.toml) and the command line; see docs/guide/cluster.md.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
import tomllib

from ctgs.errors import UserError
from ctgs.scene.scene_vars import scene_vars

JOBS_FILE = "jobs.json"
LOG_NAME = "slurm.log"  # in each scene's run folder
MARK = "== ctgs slurm:"  # the lines the job scripts add to a scene's log
FINISHED = ("eval/metrics.json", "eval-compressed/metrics.json")  # a scene with both is done
# The job scripts (scene.sh, table.sh), shipped beside this module; @NAME@ marks what a submission fills in.
TEMPLATE_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "templates")
PLACEHOLDER = re.compile(r"@([A-Z_]+)@")

# [section] -> key -> type (the TOML file's schema; every key optional)
SCHEMA = {
    "scene": {"partition": str, "account": str, "time": str, "gpus": int, "cpus": int, "mem": str,
              "signal_before": int, "max_parallel": int, "extra": list},
    "table": {"partition": str, "time": str, "cpus": int, "mem": str},
}
DEFAULTS = {
    "scene": {"partition": "", "account": "", "time": "12:00:00", "gpus": 1, "cpus": 8, "mem": "32G",
              "signal_before": 120, "max_parallel": 0, "extra": []},
    "table": {"partition": "", "time": "00:30:00", "cpus": 1, "mem": "4G"},
}


def load_options(path: str | None) -> dict:
    """The Slurm options of `path` over DEFAULTS; UserError naming the file and key for anything unknown or mistyped."""
    opts = {sec: dict(keys) for sec, keys in DEFAULTS.items()}
    if not path:
        return opts
    if not os.path.isfile(path):
        raise UserError(f"{path}: Slurm options file not found; pass SLURM_TOML=FILE (a copy of "
                        "configs/slurm/defaults.toml) or leave SLURM_TOML unset")
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{path}: not valid TOML ({exc}); fix the file (configs/slurm/defaults.toml shows the form)")
    for sec, keys in data.items():
        if sec not in SCHEMA or not isinstance(keys, dict):
            raise UserError(f"{path}: unknown section [{sec}]; the sections are [scene] and [table]")
        for key, value in keys.items():
            want = SCHEMA[sec].get(key)
            if want is None:
                raise UserError(f"{path}: unknown key {key!r} in [{sec}]; known: {', '.join(SCHEMA[sec])}")
            if not isinstance(value, want) or isinstance(value, bool):
                raise UserError(f"{path}: [{sec}] {key} = {value!r} should be a {want.__name__}")
            if want is int and value < 0:
                raise UserError(f"{path}: [{sec}] {key} = {value} should be >= 0")
            opts[sec][key] = value
    return opts


def _need(cmd: str) -> str:
    found = shutil.which(cmd)
    if found is None:
        raise UserError(f"{cmd}: not found; LAUNCHER=slurm needs Slurm's commands (sbatch, squeue, scontrol): run "
                        "on the cluster's login node, or leave LAUNCHER empty to run the scenes on this machine")
    return found


MAKE_ENV = ("MAKEFLAGS", "MFLAGS", "MAKELEVEL", "MAKEOVERRIDES", "MAKE_TERMOUT", "MAKE_TERMERR", "LAUNCHER")


def _slurm(args: list[str]) -> str:
    """Run a Slurm command; its stderr as a UserError when it fails (a bad partition, account, time...)."""
    # sbatch hands its environment to the job (--export=ALL): not this make's own, whose MAKEFLAGS would give the
    # job's make this one's command line (LAUNCHER=slurm included) and a jobserver it cannot reach
    env = {k: v for k, v in os.environ.items() if k not in MAKE_ENV}
    r = subprocess.run([_need(args[0])] + args[1:], capture_output=True, text=True, env=env)
    if r.returncode != 0:
        lines = [line.strip() for line in (r.stderr or r.stdout).splitlines() if line.strip()]
        said = next((line.split("error: ", 1)[1] for line in lines if "error: " in line), " ".join(lines))
        raise UserError(f"{args[0]} refused: {said or f'exit {r.returncode}'} (the options come from SLURM_TOML and "
                        "PARTITION= ACCOUNT= TIME_LIMIT= GPUS= CPUS= MEM= SBATCH_OPTS=)")
    return r.stdout


def is_finished(runs: str, scene: str) -> bool:
    return all(os.path.isfile(os.path.join(runs, scene, f)) for f in FINISHED)


def read_jobs(runs: str) -> dict:
    path = os.path.join(runs, "slurm", JOBS_FILE)
    if not os.path.isfile(path):
        return {"scenes": {}, "table": None}
    with open(path) as fh:
        return json.load(fh)


def write_jobs(runs: str, jobs: dict) -> None:
    path = os.path.join(runs, "slurm", JOBS_FILE)
    tmp = path + ".tmp"
    with open(tmp, "w") as fh:
        json.dump(jobs, fh, indent=1)
    os.replace(tmp, path)


def queue_states(job_ids: list[str]) -> dict[str, tuple[str, str]]:
    """job id (as recorded: 12_3 or 12) -> (state, reason), for the jobs Slurm still knows: squeue for queued and
    running ones, then scontrol for those finished within MinJobAge (a cluster without accounting forgets after)."""
    if not job_ids or shutil.which("squeue") is None:
        return {}
    out = {}
    r = subprocess.run(["squeue", "-h", "-r", "-j", ",".join(job_ids), "-o", "%i|%T|%r"], capture_output=True,
                       text=True)
    for line in r.stdout.splitlines():
        parts = line.strip().split("|")
        if len(parts) == 3 and parts[0] in job_ids:
            out[parts[0]] = (parts[1], parts[2] if parts[2] not in ("None", "(null)") else "")
    for jid in job_ids:
        if jid in out:
            continue
        r = subprocess.run(["scontrol", "-o", "show", "job", jid], capture_output=True, text=True)
        fields = dict(f.split("=", 1) for f in r.stdout.split() if "=" in f) if r.returncode == 0 else {}
        if "JobState" in fields:
            out[jid] = (fields["JobState"], fields.get("Reason", "") if fields.get("Reason") != "None" else "")
    return out


QUEUED = ("PENDING", "RUNNING", "CONFIGURING", "COMPLETING", "REQUEUED", "REQUEUE_HOLD", "REQUEUE_FED", "RESIZING",
          "SUSPENDED", "STOPPED", "SIGNALING", "STAGE_OUT")


def last_line(runs: str, scene: str) -> str:
    """The last line of the scene's log that says something: not the job scripts' own marks, not make's
    `*** [...] Error N` echo of the failure."""
    return _last(os.path.join(runs, scene, LOG_NAME))


def _last(path: str) -> str:
    if not path or not os.path.isfile(path):
        return ""
    with open(path, "rb") as fh:
        fh.seek(max(0, os.path.getsize(path) - 65536))
        lines = fh.read().decode(errors="replace").splitlines()
    for line in reversed(lines):
        text = line.strip()
        if text and not text.startswith(MARK) and not (text.startswith("make") and "***" in text):
            return text
    return ""


def stage(runs: str, scene: str) -> str:
    """How far the scene's files got (what its running job is doing)."""
    run = os.path.join(runs, scene)
    for rel, said in (("eval/metrics.json", "compressing, evaluating"), ("model/manifest.json", "evaluating"),
                      ("model.pt", "exporting")):
        if os.path.isfile(os.path.join(run, rel)):
            return said
    checkpointed = any(os.path.isfile(os.path.join(run, "checkpoints", n)) for n in ("last.pt", "prev.pt"))
    return "training (checkpointed)" if checkpointed else "training"


def scene_states(runs: str, scenes: list[str], jobs: dict) -> list[tuple[str, str, str, str]]:
    """(scene, state, job, detail) per scene: done / pending / running / failed / not submitted."""
    ids = [jobs["scenes"][s] for s in scenes if s in jobs["scenes"]]
    slurm = queue_states(ids)
    rows = []
    for s in scenes:
        jid = jobs["scenes"].get(s, "")
        st, reason = slurm.get(jid, ("", ""))
        if is_finished(runs, s):
            rows.append((s, "done", jid, f"{os.path.join(runs, s)}/eval"))
        elif st in QUEUED:
            detail = stage(runs, s) if st == "RUNNING" else (reason or "waiting")
            rows.append((s, st.lower(), jid, detail))
        elif jid:
            why = last_line(runs, s) or "no log line"
            rows.append((s, "failed" if st != "CANCELLED" else "cancelled", jid,
                         f"{st + ': ' if st else ''}{why} ({os.path.join(runs, s, LOG_NAME)})"))
        else:
            rows.append((s, "not submitted", "", ""))
    return rows


def print_status(runs: str, scenes: list[str] | None) -> list[tuple[str, str, str, str]]:
    jobs = read_jobs(runs)
    if not scenes:
        scenes = list(jobs["scenes"])
    if not scenes:
        print(f"{runs}: no Slurm sweep recorded ({os.path.join(runs, 'slurm', JOBS_FILE)} missing); name the scenes: "
              "make status SCENES=\"...\"")
        return []
    rows = scene_states(runs, scenes, jobs)
    if shutil.which("squeue") is None:
        print("(no Slurm commands here: the states come from the files only)")
    width = max(len(r[0]) for r in rows)
    for s, st, jid, detail in rows:
        print(f"{s:<{width}}  {st:<14} {jid or '-':<10} {detail}")
    table = jobs.get("table")
    if table:
        tstate = queue_states([table]).get(table, ("", ""))[0]
        made = os.path.isfile(os.path.join(runs, "table", "table.md"))
        if made and tstate in ("", "COMPLETED"):
            said, detail = "done", os.path.join(runs, "table", "table.md")
        elif tstate in QUEUED:
            said, detail = tstate.lower(), "after the scenes"
        else:
            tlog = jobs.get("table_log") or os.path.join(runs, "slurm")
            said, detail = "failed", f"{_last(tlog) or 'no table'} ({tlog})"
        print(f"{'table':<{width}}  {said:<14} {table:<10} {detail}")
    return rows


def _render(template: str, values: dict[str, str]) -> str:
    """The shipped job script `template` (ctgs/launch/templates/) with each @NAME@ replaced by values[NAME] (in one
    pass: a value is never read for placeholders)."""
    with open(os.path.join(TEMPLATE_DIR, template), encoding="utf-8") as fh:
        text = fh.read()
    return PLACEHOLDER.sub(lambda m: values[m.group(1)], text)


def _scene_script(root: str, runs: str, scenes: list[str], make_args: list[str], py: str) -> str:
    q = shlex.quote
    return _render("scene.sh", {
        "ROOT": q(root), "RUNS": q(runs), "SCENES": " ".join(q(s) for s in scenes), "PYTHON": q(py),
        "MAKE_ARGS": " ".join(q(a) for a in make_args), "LOG_NAME": LOG_NAME, "MARK": MARK,
        "TARGETS": " ".join(f"{q(runs)}/\"$scene\"/{f}" for f in FINISHED)})


def _table_script(root: str, runs: str, scenes: list[str], make_args: list[str]) -> str:
    q = shlex.quote
    return _render("table.sh", {
        "ROOT": q(root), "RUNS": q(runs), "SCENES": " ".join(q(s) for s in scenes), "FINISHED": " ".join(FINISHED),
        "MAKE_ARGS": " ".join(q(a) for a in make_args), "SCENE_LIST": q(" ".join(scenes))})


def _sbatch_opts(sec: dict, account: str) -> list[str]:
    out = []
    if sec.get("partition"):
        out.append(f"--partition={sec['partition']}")
    if account:
        out.append(f"--account={account}")
    if sec.get("time"):
        out.append(f"--time={sec['time']}")
    if sec.get("cpus"):
        out.append(f"--cpus-per-task={sec['cpus']}")
    if sec.get("mem"):
        out.append(f"--mem={sec['mem']}")
    return out


def submit(args) -> int:
    runs, root = args.runs, os.path.abspath(args.root)
    scenes = args.scenes.split()
    if not scenes:
        raise UserError('SCENES is empty; name the scenes: make all SCENES="bicycle garden ..." LAUNCHER=slurm')
    sc, tb = _job_options(args)
    extra = sc["extra"] + shlex.split(args.sbatch_opts or "")
    # A scene no manifest lists, or a SCENE_DIR_<scene> that is not a folder, fails here, not on the node an hour later.
    for s in scenes:
        scene_vars(s)
    check_scene_dirs(root, scenes, args.make_args)
    _need("sbatch")
    os.makedirs(os.path.join(runs, "slurm"), exist_ok=True)
    jobs = read_jobs(runs)
    todo, waiting = _scenes_to_submit(runs, scenes, jobs)
    folder = _new_log_folder(runs)
    name = f"ctgs-{os.path.basename(os.path.abspath(runs))}"
    after = list(waiting)
    if todo:
        after.append(_submit_scenes(args, root, folder, name, todo, sc, extra, jobs))
    # the previous table job, if it still waits, is replaced by one that waits for every scene
    old = jobs.get("table")
    if old and queue_states([old]).get(old, ("", ""))[0] == "PENDING":
        subprocess.run(["scancel", old], capture_output=True)
    if not todo and not waiting:
        print(f"every scene is finished; the table: make table SCENES=\"{' '.join(scenes)}\" RUNS={runs}")
        jobs["table"] = jobs["table_log"] = None
        write_jobs(runs, jobs)
        return 0
    script = os.path.join(folder, "table.sh")
    with open(script, "w") as fh:
        fh.write(_table_script(root, runs, scenes, args.make_args))
    tsec = {**tb, "partition": tb["partition"] or sc["partition"]}
    cmd = ["sbatch", "--parsable", f"--job-name={name}-table", f"--dependency=afterany:{':'.join(after)}",
           f"--chdir={root}", f"--output={folder}/table.out"] + _sbatch_opts(tsec, sc["account"])
    jobs["table"] = _slurm(cmd + extra + [script]).strip().split(";")[0]
    jobs["table_log"] = os.path.join(folder, "table.out")
    write_jobs(runs, jobs)
    print(f"table: job {jobs['table']} writes {os.path.join(runs, 'table', 'table.md')} once the scenes are done; "
          f"make status RUNS={runs} shows where each scene is")
    if args.wait:
        return wait(runs, scenes, jobs)
    return 0


def check_scene_dirs(root: str, scenes: list[str], make_args: list[str]) -> None:
    """UserError for a SCENE_DIR_<scene>=PATH among the jobs' make arguments that names no folder (relative paths
    from `root`, where the jobs run make)."""
    for arg in make_args:
        name, sep, path = arg.partition("=")
        if not sep or not name.startswith("SCENE_DIR_") or name[len("SCENE_DIR_"):] not in scenes:
            continue
        if not os.path.isdir(os.path.join(root, os.path.expanduser(path))):
            raise UserError(f"{name}={path}: no such folder (from {root}); pass the folder of that scene's COLMAP "
                            f"layout (images/, sparse/0/), or leave {name} out to fetch the scene")


def _job_options(args) -> tuple[dict, dict]:
    """The scene jobs' and the table job's options: the config's, with the command line's on top."""
    opts = load_options(args.config)
    sc, tb = opts["scene"], opts["table"]
    for key, value in (("partition", args.partition), ("account", args.account), ("time", args.time),
                       ("mem", args.mem)):
        if value:
            sc[key] = value
    for key, value, var in (("gpus", args.gpus, "GPUS"), ("cpus", args.cpus, "CPUS")):
        if value:
            if not value.isdigit():
                raise UserError(f"{var}={value}: should be a whole number (e.g. {var}=1)")
            sc[key] = int(value)
    return sc, tb


def _scenes_to_submit(runs: str, scenes: list[str], jobs: dict) -> tuple[list[str], list[str]]:
    """The scenes to submit (neither finished nor queued), and the queued scenes' job ids."""
    states = queue_states([jobs["scenes"][s] for s in scenes if s in jobs["scenes"]])
    todo, waiting = [], []
    for s in scenes:
        jid = jobs["scenes"].get(s)
        st = states.get(jid, ("", ""))[0] if jid else ""
        if is_finished(runs, s):
            print(f"{s}: finished ({os.path.join(runs, s)}), not submitted")
        elif st in QUEUED:
            print(f"{s}: already queued as job {jid} ({st.lower()}), not submitted again")
            waiting.append(jid)
        else:
            todo.append(s)
    return todo, waiting


def _new_log_folder(runs: str) -> str:
    """RUNS/slurm/<date-time>[-n]: this submission's scripts and logs."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    folder = os.path.join(runs, "slurm", stamp)
    n = 0
    while os.path.exists(folder):
        n += 1
        folder = os.path.join(runs, "slurm", f"{stamp}-{n}")
    os.makedirs(folder)
    return folder


def _submit_scenes(args, root: str, folder: str, name: str, todo: list[str], sc: dict, extra: list[str],
                   jobs: dict) -> str:
    """One job array of the scenes in `todo` (recorded in jobs); returns its id."""
    script = os.path.join(folder, "scene.sh")
    with open(script, "w") as fh:
        fh.write(_scene_script(root, args.runs, todo, args.make_args, args.python))
    array = f"0-{len(todo) - 1}" + (f"%{sc['max_parallel']}" if sc["max_parallel"] else "")
    cmd = ["sbatch", "--parsable", f"--job-name={name}", f"--array={array}", "--requeue",
           f"--signal=B:TERM@{sc['signal_before']}", "--open-mode=append", f"--chdir={root}",
           f"--output={folder}/%A_%a.out"] + _sbatch_opts(sc, sc["account"])
    if sc["gpus"]:
        cmd.append(f"--gres=gpu:{sc['gpus']}")
    array_id = _slurm(cmd + extra + [script]).strip().split(";")[0]
    for i, s in enumerate(todo):
        jobs["scenes"][s] = f"{array_id}_{i}"
        print(f"{s}: submitted as job {array_id}_{i} (log: {os.path.join(args.runs, s, LOG_NAME)})")
    return array_id


def wait(runs: str, scenes: list[str], jobs: dict, poll: float = 2.0) -> int:
    """Block until the sweep's jobs have left the queue; 0 when every scene finished and the table is written."""
    ids = [jobs["scenes"][s] for s in scenes if s in jobs["scenes"]] + ([jobs["table"]] if jobs.get("table") else [])
    while True:
        if not any(st in QUEUED for st, _ in queue_states(ids).values()):
            break
        time.sleep(poll)
    rows = print_status(runs, scenes)
    ok = all(r[1] == "done" for r in rows) and os.path.isfile(os.path.join(runs, "table", "table.md"))
    return 0 if ok else 1


def resumed(run_dir: str) -> int:
    """The job script's line on a restart: the iteration of the checkpoint the training resumes from."""
    # Imported here: a checkpoint needs torch, which `make status` and submitting on a login node do not.
    from ctgs.runs.checkpoint import readable_checkpoint

    try:
        found = readable_checkpoint(run_dir)
    except UserError as exc:  # a checkpoint ctgs will not unpickle: the training says so too, and stops
        print(f"{MARK} {exc}")
        return 0
    if found is None:
        print(f"{MARK} no readable checkpoint in {run_dir}/checkpoints: the training starts over")
    else:
        print(f"{MARK} resuming {run_dir} from the checkpoint at iteration {found[1]}")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m ctgs.launch.slurm", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("submit", help="submit the scenes' jobs and the table job")
    s.add_argument("--root", default=".", help="the checkout whose Makefile the jobs run")
    s.add_argument("--runs", default="runs")
    s.add_argument("--scenes", required=True)
    s.add_argument("--config", default=None, help="Slurm options TOML (configs/slurm/defaults.toml)")
    s.add_argument("--python", default=sys.executable)
    for opt in ("partition", "account", "time", "gpus", "cpus", "mem", "sbatch-opts"):
        s.add_argument(f"--{opt}", default="")
    s.add_argument("--wait", action="store_true", help="return when the jobs have left the queue")
    s.add_argument("make_args", nargs="*", help="after --: the make arguments the jobs pass on (VAR=VALUE, -o FILE)")
    st = sub.add_parser("status", help="each scene's state, from Slurm and from the files")
    st.add_argument("--runs", default="runs")
    st.add_argument("--scenes", default="")
    r = sub.add_parser("resumed", help="print the checkpoint iteration a run resumes from")
    r.add_argument("run_dir")
    args = p.parse_args(argv)
    try:
        if args.cmd == "submit":
            return submit(args)
        if args.cmd == "status":
            print_status(args.runs, args.scenes.split())
            return 0
        return resumed(args.run_dir)
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exc.exit_code


if __name__ == "__main__":
    sys.exit(main())
