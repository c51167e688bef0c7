"""``ms3d serve``: scheduled campus reprocessing as a served Prefect deployment.

``flow.serve`` registers a deployment of :func:`flows.campus.reprocess_from_config` with a cron schedule
on the Prefect API (the one configured, or one embedded server keeping its database in the work dir)
and runs each scheduled or triggered flow run in a subprocess until stopped (Ctrl-C / SIGTERM). Each run
resumes: units done and unchanged are skipped. ``deploy/prefect.yaml`` holds the same deployment for a
work pool on a shared server.
"""

from __future__ import annotations

from pathlib import Path

from storage.errors import InputError
from storage.workdir import WorkDir
from tasks.config import CampusConfig


def check_cron(cron: str) -> None:
    try:
        from croniter import croniter

        ok = croniter.is_valid(cron)
    except ImportError:  # prefect depends on croniter; be lenient if that ever changes
        ok = len(cron.split()) in (5, 6)
    if not ok:
        raise InputError(None, f"--cron {cron!r} is not a cron expression (e.g. '0 2 * * *' for 02:00 every day)")


def serve_campus(config_path: Path, cfg: CampusConfig, cron: str, name: str | None = None,
                 overrides: dict | None = None) -> int:
    """Serve the campus deployment until interrupted. Returns the exit code."""
    from flows.campus import reprocess_from_config
    from flows.runtime import embedded_prefect
    from storage.housekeeping import check_work_dir_writable

    check_cron(cron)
    wd = WorkDir(cfg.work_dir)
    check_work_dir_writable(wd)
    name = name or cfg.name
    params = {"config_path": str(Path(config_path).absolute()), "overrides": overrides or {}}
    with embedded_prefect(wd.prefect_dir, cfg.cluster.prefect_api_url) as url:
        print(f"serving deployment 'reprocess-campus-from-config/{name}' (cron '{cron}', UTC) on {url}; "
              "Ctrl-C stops", flush=True)
        reprocess_from_config.serve(name=name, cron=cron, parameters=params, print_starting_message=False)
    return 0
