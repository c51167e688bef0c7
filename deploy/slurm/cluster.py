"""A Dask cluster on SLURM for ``ms3d run`` (dask-jobqueue), configured by ``deploy/slurm_cluster.yaml``.

    python deploy/slurm/cluster.py --jobs 4           # start, print the scheduler address, wait for Ctrl-C
    python deploy/slurm/cluster.py --print-job-script # the sbatch script each job submits, nothing submitted

Run it on a login node inside the ms3d environment; pass the printed address to
``ms3d run campus.yaml --dask-address tcp://HOST:PORT``. SIGINT or SIGTERM closes the cluster (its jobs are
cancelled); a run in progress then loses its workers and resumes on the next ``ms3d run``.
The YAML's ``cluster`` mapping is passed to :class:`dask_jobqueue.SLURMCluster` as keyword arguments
(``cores``, ``processes``, ``memory``, ``walltime``, ``job_script_prologue``, ``scheduler_options`` ...).
A bad config file is one line naming the file (exit 2), never a traceback.
"""

from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path

import yaml

DEFAULT_CONFIG = Path(__file__).resolve().parents[1] / "slurm_cluster.yaml"
REQUIRED = ("cores", "processes", "memory")


class ConfigError(Exception):
    """A cluster config that cannot be used; the message names the file and the problem."""


def load_cluster_options(path: str | Path = DEFAULT_CONFIG) -> dict:
    """The ``cluster`` mapping of a recipe YAML: SLURMCluster keyword arguments. Raises ConfigError (file
    missing or unreadable, broken YAML, no ``cluster`` mapping, ``cores``/``processes``/``memory`` absent,
    ``processes`` not a positive divisor of ``cores``: one thread per worker process is the sizing rule)."""
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except OSError as e:
        raise ConfigError(f"{path}: cannot read the cluster config ({e.strerror or e})") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: not valid YAML ({str(e).splitlines()[0]})") from None
    opts = doc.get("cluster") if isinstance(doc, dict) else None
    if not isinstance(opts, dict):
        raise ConfigError(f"{path}: needs a 'cluster' mapping of dask_jobqueue.SLURMCluster arguments")
    missing = [k for k in REQUIRED if k not in opts]
    if missing:
        raise ConfigError(f"{path}: cluster.{missing[0]} is missing (needs {', '.join(REQUIRED)})")
    cores, procs = opts["cores"], opts["processes"]
    if not (isinstance(cores, int) and isinstance(procs, int) and 0 < procs <= cores and cores % procs == 0):
        raise ConfigError(f"{path}: cluster.processes ({procs}) must divide cluster.cores ({cores}): "
                          "one thread per worker process")
    return dict(opts)


def make_cluster(options: dict, **overrides):
    """A started ``SLURMCluster`` (its scheduler runs in this process; no job submitted until scaled).
    ``overrides`` replace top-level options, e.g. ``scheduler_options={"host": "127.0.0.1"}`` in tests."""
    from dask_jobqueue import SLURMCluster

    return SLURMCluster(**{**options, **overrides})


def _wait_for_stop() -> int:
    """Block until SIGINT or SIGTERM; returns the signal number."""
    stops = {signal.SIGINT, signal.SIGTERM}
    signal.pthread_sigmask(signal.SIG_BLOCK, stops)
    return signal.sigwait(stops)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="deploy/slurm/cluster.py", description=__doc__.splitlines()[0])
    p.add_argument("--config", default=str(DEFAULT_CONFIG), help="recipe YAML (default: %(default)s)")
    p.add_argument("--jobs", type=int, default=1, help="SLURM jobs to submit (each: `processes` workers)")
    p.add_argument("--print-job-script", action="store_true", help="print the sbatch script and exit")
    a = p.parse_args(argv)
    try:
        opts = load_cluster_options(a.config)
    except ConfigError as e:
        print(f"cluster.py: error: {e}", file=sys.stderr)
        return 2
    with make_cluster(opts) as cluster:
        if a.print_job_script:
            print(cluster.job_script())
            return 0
        cluster.scale(jobs=a.jobs)
        print(f"scheduler {cluster.scheduler_address} ({a.jobs} job(s) x {opts['processes']} workers, "
              "1 thread each); run:", flush=True)
        print(f"  ms3d run CONFIG --work-dir SHARED_PATH --dask-address {cluster.scheduler_address}", flush=True)
        signum = _wait_for_stop()
        print(f"cluster.py: {signal.Signals(signum).name}: closing the cluster (jobs cancelled)", flush=True)
    return 128 + signum


if __name__ == "__main__":
    sys.exit(main())
