"""`layerbvh sweep --cluster slurm`: the sweep's Dask workers as SLURM jobs (dask-jobqueue), their settings, the job
script, and a point's share of its job's walltime."""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.ab.render import UserError
from layerbvh_mitsuba.runtime.cache import cache_dir

JOB_SCRIPT = "slurm_job.sh"      # written next to the sweep's results: what was submitted
LOG_DIR = "slurm_logs"           # the worker jobs' stdout/stderr, next to the results
DEATH_TIMEOUT_S = 30             # a worker whose scheduler is gone (the sweep killed) exits after this
WALLTIME_MARGIN_S = float(os.environ.get("LAYERBVH_SLURM_MARGIN_S", "10"))  # a point ends this long before its job
PROBE_TIMEOUT_S = 20             # `sinfo` must answer within this (it retries an unreachable controller)


def local_cluster_conf() -> Path:
    """Where `scripts/slurm_local.sh start` links its cluster's slurm.conf (and `stop` removes the
    link): what the sweep uses when SLURM_CONF is unset and no other controller answers."""
    return cache_dir("slurm") / "slurm.conf"


@dataclass(frozen=True)
class SlurmSettings:
    """What a user sets for their cluster (the sweep's --slurm-* options)."""

    partition: str | None = None
    account: str | None = None
    cores: int = 1                      # cores per job; one worker per job, one point per core
    memory_gib: float = 4.0             # memory per job
    walltime: str = "01:00:00"          # per job, [D-]HH:MM:SS
    jobs: int = 1                       # jobs started at once (with adapt: the maximum)
    adapt_min: int | None = None        # set: scale adaptively between adapt_min and jobs
    extra: tuple = field(default_factory=tuple)  # more #SBATCH lines, e.g. "--constraint=avx512"


def walltime_seconds(text: str) -> float:
    """Seconds of a SLURM time ([D-]HH:MM:SS, MM:SS, or minutes); ValueError naming it otherwise."""
    m = re.fullmatch(r"(?:(\d+)-)?(?:(\d+):)?(\d+):(\d+)|(\d+)", text.strip())
    if not m:
        raise ValueError(f"not a SLURM time: {text!r} (use [D-]HH:MM:SS)")
    if m.group(5) is not None:
        return 60.0 * int(m.group(5))
    d, h, mi, s = (int(x) if x else 0 for x in m.groups()[:4])
    return float(((d * 24 + h) * 60 + mi) * 60 + s)


def check(settings: SlurmSettings) -> SlurmSettings:
    """The settings, or a UserError naming the bad option or what is missing."""
    if shutil.which("sbatch") is None:
        raise UserError("--cluster slurm: sbatch is not on PATH (is this a SLURM login node? for a one-node "
                        "cluster on this machine: bash scripts/slurm_local.sh start)")
    try:
        import dask_jobqueue  # noqa: F401  (an optional dependency: only this option needs it)
    except ImportError:
        raise UserError("--cluster slurm needs dask-jobqueue: pip install dask-jobqueue") from None
    try:
        walltime_seconds(settings.walltime)
    except ValueError as e:
        raise UserError(f"--slurm-walltime: {e}") from None
    if settings.cores < 1 or settings.jobs < 1 or settings.memory_gib <= 0:
        raise UserError("--slurm-cores and --slurm-jobs must be >= 1 and --slurm-memory > 0")
    if settings.adapt_min is not None and not 0 <= settings.adapt_min <= settings.jobs:
        raise UserError(f"--slurm-adapt-min must be in [0, --slurm-jobs={settings.jobs}], got {settings.adapt_min}")
    _find_controller()
    return settings


def _controller_answer(env: dict) -> str | None:
    """None when a SLURM controller answers `sinfo` under `env`, else why not (sinfo's last line)."""
    try:
        r = subprocess.run(["sinfo", "-h", "-o", "%T"], env=env, capture_output=True, text=True,
                           timeout=PROBE_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        return f"sinfo did not answer within {PROBE_TIMEOUT_S} s"
    except OSError as e:
        return f"sinfo: {e.strerror}"
    if r.returncode == 0:
        return None
    return (r.stderr.strip().splitlines() or [f"sinfo exited {r.returncode}"])[-1]


def _find_controller() -> None:
    """Make sure sbatch will reach a controller before any job script or folder is written: the
    one SLURM_CONF (or SLURM's own default) names, else, with SLURM_CONF unset, the one-node
    cluster scripts/slurm_local.sh started (its slurm.conf, linked where local_cluster_conf says;
    SLURM_CONF is then set for this process, so sbatch, squeue and dask-jobqueue use it). A
    UserError saying how to get one otherwise."""
    conf = os.environ.get("SLURM_CONF")
    # sinfo retries a configuration file that is not there until the probe's time is up (20 s)
    why = "no such file" if conf and not Path(conf).is_file() else _controller_answer(dict(os.environ))
    if why is None:
        return
    local = local_cluster_conf()
    if "SLURM_CONF" not in os.environ and local.exists() \
            and _controller_answer({**os.environ, "SLURM_CONF": str(local.resolve())}) is None:
        os.environ["SLURM_CONF"] = str(local.resolve())
        print(f"layerbvh: --cluster slurm: using the one-node cluster of scripts/slurm_local.sh "
              f"(SLURM_CONF={os.environ['SLURM_CONF']})", file=sys.stderr)
        return
    where = f"SLURM_CONF={os.environ['SLURM_CONF']}" if "SLURM_CONF" in os.environ else "SLURM_CONF is unset"
    raise UserError(f"--cluster slurm: no SLURM controller answers ({where}; {why}): set SLURM_CONF to your "
                    f"cluster's slurm.conf, or start a one-node cluster here with `bash scripts/slurm_local.sh start`")


def make_cluster(settings: SlurmSettings, out: Path, exclusive_resource: str):
    """A dask-jobqueue SLURMCluster whose jobs each run one worker of `cores` threads holding the
    sweep's exclusive resource (timed points: one at a time per job), started as the settings
    say; the job script is written to out/JOB_SCRIPT first."""

    from dask_jobqueue import SLURMCluster  # local: optional dependency (layerbvh[slurm])
    (out / LOG_DIR).mkdir(parents=True, exist_ok=True)
    cluster = SLURMCluster(
        queue=settings.partition, account=settings.account, cores=settings.cores, processes=1,
        memory=f"{settings.memory_gib:g}GiB", walltime=settings.walltime, job_name="layerbvh-sweep",
        job_extra_directives=list(settings.extra), python=sys.executable, death_timeout=DEATH_TIMEOUT_S,
        log_directory=str(out / LOG_DIR), worker_extra_args=["--resources", f"{exclusive_resource}=1"],
        local_directory=os.environ.get("TMPDIR", "/tmp"), silence_logs="error",
        scheduler_options={"dashboard_address": ":0"})  # any free port: 8787 may be taken by another cluster
    atomic.write_text(out / JOB_SCRIPT, cluster.job_script())
    if settings.adapt_min is not None:
        cluster.adapt(minimum_jobs=settings.adapt_min, maximum_jobs=settings.jobs)
    else:
        cluster.scale(jobs=settings.jobs)
    return cluster


def time_left_in_job() -> tuple[float, str] | None:
    """(seconds left, the job's walltime as SLURM prints it) when this process runs inside a SLURM
    job with a time limit, else None."""
    job = os.environ.get("SLURM_JOB_ID")
    if not job or shutil.which("squeue") is None:
        return None
    try:
        out = subprocess.run(["squeue", "-h", "-j", job, "-o", "%L|%l"], capture_output=True, text=True,
                             timeout=10).stdout.strip()
        left, limit = out.splitlines()[0].split("|")
        return walltime_seconds(left), limit
    except (OSError, subprocess.SubprocessError, ValueError, IndexError):
        return None  # UNLIMITED, NOT_SET, or squeue not answering: no walltime to respect
