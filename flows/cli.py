"""The ``ms3d`` command line: a thin layer over Python functions that tests call too.

    ms3d synth --preset demo --seed 7 --out DIR     generate a synthetic campus with ground truth
    ms3d run CONFIG [--dask-address tcp://...]      reprocess a campus (embedded Prefect + Dask)
    ms3d serve CONFIG --cron "0 2 * * *"            scheduled reprocessing (a served Prefect deployment)
    ms3d status WORKDIR                             tiles done / failed / pending, with errors
    ms3d demo                                       synth demo campus + run + print where things are
    ms3d view WORKDIR | ARCHIVE.3tz                 the campus's 3D Tiles in a browser (localhost)
    ms3d ui WORKDIR                                 show the run history in the Prefect UI
    ms3d train --profile default --seeds 7 11       train MS3DQE-Net (--suite: and the baselines)
    ms3d evaluate --suite DIR --seed 42             the paper's Tables 3 and 4 on a held-out campus

Every user error (config, YAML, inputs, CRS, work dir) prints one line ``ms3d: error: ...`` and exits
with code 2; ``--debug`` shows the traceback. A run with failed tiles or an incomplete campus exits 1.
SIGINT / SIGTERM stop ``run`` and ``serve`` cleanly: one line ``ms3d: stopped by SIGTERM; ...`` and exit
code 128 + the signal (130 / 143), see ``flows.runtime.stop_on_signals``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path

from storage.inputs.location import is_url


def _cmd_synth(a) -> int:
    from synth.generate import generate

    out = generate(a.preset, seed=a.seed, out=a.out, overwrite=a.overwrite, scale=a.scale, mls_density=a.mls_density,
                   coarse_mesh=a.coarse_mesh)
    print(f"synthetic campus '{a.preset}' (seed {a.seed}) written to {out}")
    return 0


def _overrides(a) -> dict:
    o = {}
    if getattr(a, "dask_address", None):
        o["cluster.address"] = a.dask_address
    if getattr(a, "workers", None):
        o["cluster.n_workers"] = a.workers
    if getattr(a, "work_dir", None):
        o["work_dir"] = a.work_dir if is_url(a.work_dir) else str(Path(a.work_dir).absolute())
    for kv in getattr(a, "set", None) or []:
        k, _, v = kv.partition("=")
        try:
            o[k] = json.loads(v)
        except json.JSONDecodeError:
            o[k] = v
    return o


def _cmd_run(a) -> int:
    from flows.campus import CampusRunFailed, run_campus
    from flows.runtime import Stopped, stop_on_signals, stopped_line
    from flows.summary import format_summary
    from tasks.config import CampusConfig

    cfg = CampusConfig.from_yaml(a.config, _overrides(a))
    try:
        with stop_on_signals():
            summary = run_campus(cfg, progress=sys.stderr.isatty())
    except Stopped as e:  # SIGINT / SIGTERM: the run unwound (cluster closed, lock released)
        print(stopped_line(e.signum, cfg.work_dir), file=sys.stderr)
        return e.exit_code
    except CampusRunFailed as e:
        print(format_summary(e.summary))
        print(str(e))  # each failed unit once, with its error
        n, inc = len(e.summary["failed"]), e.summary.get("incomplete")
        what = (f"{n} unit(s) failed" if n else "") + (" and " if n and inc else "") + \
            ("the campus is incomplete" if inc else "")
        print(f"ms3d: error: {what}; the rest is done. Fix the inputs named above and run again "
              f"(ms3d status {e.summary['work_dir']})", file=sys.stderr)
        return 1
    print(format_summary(summary))
    return 0


def _cmd_serve(a) -> int:
    from flows.runtime import Stopped, stop_on_signals, stopped_line
    from flows.serve import serve_campus
    from tasks.config import CampusConfig

    cfg = CampusConfig.from_yaml(a.config, _overrides(a))
    try:
        with stop_on_signals():  # while serving, serve_campus handles the signals itself
            return serve_campus(Path(a.config), cfg, cron=a.cron, name=a.name, overrides=_overrides(a))
    except Stopped as e:  # a signal while the embedded server started or stopped
        print(stopped_line(e.signum, cfg.work_dir), file=sys.stderr)
        return e.exit_code



def _config_command(sub, name: str, help_text: str, func):
    """A subcommand that reads a campus config: ``CONFIG [--work-dir DIR] [--set KEY=VALUE ...]``."""
    p = sub.add_parser(name, help=help_text)
    p.add_argument("config")
    p.add_argument("--work-dir")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a config field, e.g. tiling.tile_size_m=50")
    p.set_defaults(func=func)
    return p

def _cmd_status(a) -> int:
    from flows.status import campus_status, format_status, status_exit_code

    st = campus_status(a.work_dir)
    print(format_status(st))
    return status_exit_code(st)


def _cmd_demo(a) -> int:
    from flows.demo import run_demo

    return run_demo(Path(a.out), Path(a.work), seed=a.seed, preset=a.preset)


def _cmd_view(a) -> int:
    from flows.view import serve_viewer
    from storage.errors import InputError
    from storage.workdir.layout import WorkDir

    if a.work_dir.endswith(".3tz"):  # a 3D Tiles archive (export.archive: 3tz), served as it is
        serve_viewer(a.work_dir, port=a.port, label=a.label)
        return 0
    wd = WorkDir(a.work_dir)
    if not wd.tileset_json.exists() and not wd.tileset_3tz.exists():
        raise InputError(wd.root, "no output/tileset.json: run `ms3d run CONFIG` first")
    serve_viewer(wd.root, port=a.port, label=a.label)
    return 0


def _cmd_ui(a) -> int:
    import subprocess

    from flows.runtime import prefect_env
    from storage.workdir.layout import WorkDir

    env = {**os.environ, **prefect_env(WorkDir(a.work_dir).prefect_dir)}
    env.pop("PREFECT_API_URL", None)
    return subprocess.call([sys.executable, "-m", "prefect", "server", "start"], env=env)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="ms3d", description="MLS + photogrammetric mesh fusion for 3D building models")
    p.add_argument("-v", "--verbose", action="store_true", help="show Prefect and Dask logs")
    p.add_argument("--debug", action="store_true", help="show tracebacks of errors (implies --verbose)")
    sub = p.add_subparsers(dest="cmd", required=True)

    s = sub.add_parser("synth", help="generate a synthetic campus with ground truth")
    s.add_argument("--preset", choices=("tiny", "demo", "campus"), default="tiny")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", required=True)
    s.add_argument("--overwrite", action="store_true", help="replace the contents of a non-empty --out")
    s.add_argument("--scale", type=float, default=1.0, help="campus preset: side length multiplier")
    s.add_argument("--mls-density", type=float, default=None,
                   help="MLS scanner rate as a fraction of the real one (1.0 = real density; default: the preset's)")
    s.add_argument("--coarse-mesh", action="store_true",
                   help="write a LoD2-like block model (big faces, no recesses or balconies; labelled) instead of "
                        "the MVS mesh, co-registered with the MLS")
    s.set_defaults(func=_cmd_synth)

    r = _config_command(sub, "run", "reprocess a campus described by a YAML config", _cmd_run)
    r.add_argument("--dask-address", help="scheduler address of an existing Dask cluster")
    r.add_argument("--workers", type=int, help="local Dask worker processes")

    sv = _config_command(sub, "serve", "serve a scheduled Prefect deployment that reprocesses the campus", _cmd_serve)
    sv.add_argument("--cron", default="0 2 * * *", help="schedule (cron syntax, UTC); default nightly at 02:00")
    sv.add_argument("--name", default=None, help="deployment name (default: the campus name)")

    st = sub.add_parser("status", help="tiles done, failed and pending of a work dir")
    st.add_argument("work_dir")
    st.set_defaults(func=_cmd_status)

    d = sub.add_parser("demo", help="generate the demo campus and run the pipeline on it")
    d.add_argument("--out", default="ms3d-work/demo-input")
    d.add_argument("--work", default="ms3d-work/demo")
    d.add_argument("--seed", type=int, default=7)
    d.add_argument("--preset", default="demo")
    d.set_defaults(func=_cmd_demo)

    v = sub.add_parser("view", help="serve the campus's 3D Tiles with a viewer page on localhost")
    v.add_argument("work_dir", help="a work dir, or a 3D Tiles archive (.3tz) to serve as it is")
    v.add_argument("--port", type=int, default=8765)
    v.add_argument("--label", action="store_true", help="labelling mode: mark patches good/bad (g / b), least-sure "
                                                        "first; appended to WORKDIR/labels/user-<date>.csv")
    v.set_defaults(func=_cmd_view)

    u = sub.add_parser("ui", help="start a Prefect server on the work dir's run history")
    u.add_argument("work_dir")
    u.set_defaults(func=_cmd_ui)

    from flows.model_cli import add_commands

    add_commands(sub)  # ms3d train, ms3d evaluate
    return p


def _quiet_logs() -> None:
    """Dask and Prefect log every worker start and task run, and Prefect prints tracebacks of failed runs
    on the console: keep the terminal to ms3d's own lines (the run history keeps everything)."""
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
    os.environ.setdefault("PREFECT_LOGGING_HANDLERS_CONSOLE_LEVEL", "CRITICAL")
    # worker processes read this at import: a worker whose scheduler closes first logs a heartbeat
    # CommClosedError at ERROR when a run ends or is stopped; the run's own outcome says what matters
    os.environ.setdefault("DASK_LOGGING", repr({"distributed": "error", **{
        f"distributed.{m}": "critical" for m in ("worker", "core", "comm", "batched", "nanny")}}))
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    for name in ("distributed", "prefect"):
        logging.getLogger(name).setLevel(logging.ERROR)


def error_line(e: BaseException) -> tuple[str, int]:
    """The one line a user sees for an exception, and the exit code."""
    from storage.errors import Ms3dError
    from tasks.units import os_error_message

    if isinstance(e, Ms3dError):
        return f"ms3d: error: {e}", 2
    if isinstance(e, OSError):
        return f"ms3d: error: {os_error_message(e)}", 2
    if isinstance(e, KeyboardInterrupt):
        return "ms3d: interrupted; run the same command again to resume", 130
    first = (str(e).splitlines() or [""])[0]
    return f"ms3d: internal error: {type(e).__name__}: {first} (run with --debug for the traceback)", 3


def _ms3d_only(record: logging.LogRecord) -> bool:
    """Without --verbose the terminal shows ms3d's own log lines; Prefect and Dask keep theirs in the run
    history (a failed flow run's traceback included)."""
    return not record.name.startswith(("prefect", "distributed", "dask", "uvicorn", "httpx"))


def main(argv: list[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    verbose = a.verbose or a.debug
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if not verbose:
        _quiet_logs()
        for h in logging.getLogger().handlers:
            h.addFilter(_ms3d_only)
    try:
        return a.func(a)
    except (Exception, KeyboardInterrupt) as e:
        if a.debug:
            raise
        line, code = error_line(e)
        print(line, file=sys.stderr)
        return code


if __name__ == "__main__":
    sys.exit(main())
