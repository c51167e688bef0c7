"""The deploy recipes are checked offline: every YAML parses, the Kubernetes
manifests validate against the bundled Kubernetes schemas (kubernetes-validate, strict: unknown fields
fail), workers are sized against ``partition.memory_budget_mb``, no recipe holds an inline credential,
servers listen only inside the cluster network, and the SLURM job script renders (dask-jobqueue).

ms3d's own local servers (embedded Prefect API, local Dask cluster, the S3 test server) are held to
127.0.0.1 by tests/flows/test_signals.py and tests/storage/objstore/test_objstore.py; not repeated here.
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest
import yaml
from dask.utils import parse_bytes

from tasks.config import CampusConfig

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
K8S = DEPLOY / "k8s"
K8S_VERSION = "1.30.0"   # podFailurePolicy and CronJob timeZone are GA from 1.30
IMPORT_OVERHEAD_MB = 1024  # torch + Prefect + Arrow pools in a worker process, above the tile's own data
MEASURED_PEAK_MB = 2860    # largest unit of the demo campus (export), worker high-water mark (docs/benchmarks.md)
NANNY_MB = 256             # the Dask nanny process beside each worker in the same container
SERVER_COMMANDS = (("dask", "scheduler"), ("prefect", "server"))


def _docs(path: Path) -> list[dict]:
    return [d for d in yaml.safe_load_all(path.read_text()) if d is not None]


def _manifests() -> list[tuple[str, dict]]:
    return [(f"{p.name}:{d['kind']}/{d['metadata']['name']}", d)
            for p in sorted(K8S.glob("*.yaml")) for d in _docs(p)]


def _by_name(kind: str, name: str) -> dict:
    found = [d for _, d in _manifests() if d["kind"] == kind and d["metadata"]["name"] == name]
    assert len(found) == 1, f"{kind}/{name}: {len(found)} found"
    return found[0]


def _pod_spec(d: dict) -> dict:
    if d["kind"] == "CronJob":
        return d["spec"]["jobTemplate"]["spec"]["template"]["spec"]
    return d["spec"]["template"]["spec"]


def _containers() -> list[tuple[str, dict, dict]]:
    return [(name, _pod_spec(d), c) for name, d in _manifests()
            if d["kind"] in ("Deployment", "Job", "CronJob") for c in _pod_spec(d)["containers"]]


def _flag(cmd: list[str], flag: str) -> str:
    assert flag in cmd, f"{flag} missing from {cmd}"
    return cmd[cmd.index(flag) + 1]


def _mib(quantity: str) -> float:
    """A Kubernetes or Dask memory quantity ('4608Mi', '4Gi', '4GiB', '32GB') in MiB."""
    q = str(quantity)
    q = q + "B" if q.endswith("i") else q
    return parse_bytes(q) / 2**20


def test_every_recipe_yaml_parses():
    files = sorted(DEPLOY.rglob("*.yaml"))
    assert {"compose.yaml", "prefect.yaml", "slurm_cluster.yaml", "dask.yaml", "run.yaml"} <= {p.name for p in files}
    for p in files:
        docs = _docs(p)
        assert docs and all(isinstance(d, dict) for d in docs), p


def test_k8s_manifests_validate_against_the_kubernetes_schemas():
    kv = pytest.importorskip("kubernetes_validate")
    kinds = set()
    for name, d in _manifests():
        kv.validate(d, K8S_VERSION, strict=True)  # raises naming the field
        kinds.add(d["kind"])
    assert {"Deployment", "Service", "Job", "CronJob", "PersistentVolumeClaim", "ConfigMap"} <= kinds
    # the check can fail: a misspelt field and a wrong type are rejected
    bad = _by_name("Deployment", "dask-worker")
    bad["spec"]["template"]["spec"]["containers"][0]["resource"] = {"limits": {"memory": "4Gi"}}
    with pytest.raises(kv.ValidationError):
        kv.validate(bad, K8S_VERSION, strict=True)
    bad = _by_name("Deployment", "dask-worker")
    bad["spec"]["replicas"] = "four"
    with pytest.raises(kv.ValidationError):
        kv.validate(bad, K8S_VERSION, strict=True)


def test_worker_memory_fits_the_default_budget():
    budget = CampusConfig().partition.memory_budget_mb
    worker = _pod_spec(_by_name("Deployment", "dask-worker"))["containers"][0]
    cmd = worker["command"]
    assert _flag(cmd, "--nthreads") == "1" and _flag(cmd, "--nworkers") == "1"  # one tile task per process
    dask_limit = _mib(_flag(cmd, "--memory-limit"))
    assert dask_limit >= budget + IMPORT_OVERHEAD_MB and dask_limit >= MEASURED_PEAK_MB
    res = worker["resources"]
    assert _mib(res["limits"]["memory"]) >= dask_limit + NANNY_MB  # Dask stops the worker before the OOM killer
    assert _mib(res["requests"]["memory"]) <= _mib(res["limits"]["memory"])
    assert res["limits"]["cpu"] == "1"
    shipped = yaml.safe_load(_by_name("ConfigMap", "ms3d-campus")["data"]["campus.yaml"])
    assert shipped["partition"]["memory_budget_mb"] + IMPORT_OVERHEAD_MB <= dask_limit


def _secretish(name: str) -> bool:
    return bool(re.search(r"(?i)secret|password|passwd|token|access_key|api_key|private_key|credential", name))


def inline_credentials(obj, where: str = "") -> list[str]:
    """Places in a parsed recipe where a credential-like name carries a literal value: an env entry
    ``{name, value}``, a mapping key, or a URL with user:password (``${VAR}`` substitutions are fine)."""
    out = []
    if isinstance(obj, dict):
        if isinstance(obj.get("name"), str) and _secretish(obj["name"]) and "value" in obj:
            out.append(f"{where}: env {obj['name']} has an inline value (use valueFrom.secretKeyRef)")
        if obj.get("kind") == "Secret" and (obj.get("data") or obj.get("stringData")):
            out.append(f"{where}: a Secret with its data in the recipe")
        for k, v in obj.items():
            if isinstance(v, str) and _secretish(str(k)) and not v.startswith("${"):
                out.append(f"{where}.{k}: inline value")
            out += inline_credentials(v, f"{where}.{k}")
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            out += inline_credentials(v, f"{where}[{i}]")
    elif isinstance(obj, str):
        for m in re.finditer(r"://([^/@\s:]+):([^/@\s]+)@", obj):
            if not m.group(2).startswith("${"):
                out.append(f"{where}: URL with an inline password")
        if re.search(r"\b(AKIA|ASIA)[0-9A-Z]{16}\b", obj):
            out.append(f"{where}: an AWS access key id")
    return out


def test_no_recipe_holds_an_inline_credential():
    problems = []
    for p in sorted(DEPLOY.rglob("*.yaml")):
        for i, d in enumerate(_docs(p)):
            problems += inline_credentials(d, f"{p.relative_to(ROOT)}[{i}]")
    for p in sorted(DEPLOY.rglob("*.py")):
        problems += inline_credentials(p.read_text(), str(p.relative_to(ROOT)))
    assert problems == []
    # every credential a pod reads comes from a Secret
    refs = [e for _, _, c in _containers() for e in c.get("env", []) if _secretish(e["name"])]
    assert refs and all("secretKeyRef" in e["valueFrom"] for e in refs)
    # the checker can fail
    assert inline_credentials({"env": [{"name": "AWS_SECRET_ACCESS_KEY", "value": "abc"}]})
    assert inline_credentials({"environment": {"POSTGRES_PASSWORD": "prefect"}})
    assert inline_credentials("postgresql://prefect:prefect@postgres/db")
    assert not inline_credentials("postgresql://prefect:${POSTGRES_PASSWORD:?}@postgres/db")


def test_servers_listen_inside_the_cluster_network_only():
    """The scheduler and the Prefect server bind 0.0.0.0 INSIDE the pod network, reachable only through
    ClusterIP Services (never NodePort / LoadBalancer, hostNetwork or hostPort); workers start no
    dashboard; compose publishes on the host's loopback; the SLURM scheduler's dashboard stays on loopback."""
    servers = 0
    for name, pod, c in _containers():
        assert not pod.get("hostNetwork") and not any("hostPort" in p for p in c.get("ports", [])), name
        cmd = c["command"]
        if tuple(cmd[:2]) in SERVER_COMMANDS:
            servers += 1
            assert _flag(cmd, "--host") == "0.0.0.0", name
        if cmd[:2] == ["dask", "worker"]:
            assert "--no-dashboard" in cmd
    assert servers == 2
    services = [d for _, d in _manifests() if d["kind"] == "Service"]
    assert {s["metadata"]["name"] for s in services} == {"dask-scheduler", "prefect-server"}
    assert all(s["spec"].get("type", "ClusterIP") == "ClusterIP" for s in services)
    compose = _docs(DEPLOY / "compose.yaml")[0]["services"]
    published = [p for s in compose.values() for p in s.get("ports", [])]
    assert published and all(p.startswith("127.0.0.1:") for p in published)
    slurm = _docs(DEPLOY / "slurm_cluster.yaml")[0]["cluster"]
    assert slurm["scheduler_options"]["dashboard_address"].startswith("127.0.0.1:")


def test_run_pods_and_workers_share_the_work_dir_and_stop_cleanly(tmp_path):
    scheduler = _by_name("Service", "dask-scheduler")["spec"]["ports"]
    prefect = _by_name("Service", "prefect-server")["spec"]["ports"]
    worker = _pod_spec(_by_name("Deployment", "dask-worker"))
    mounts = {}
    for kind, name in (("Deployment", "dask-worker"), ("Job", "ms3d-run"), ("CronJob", "ms3d-nightly")):
        pod = _pod_spec(_by_name(kind, name))
        c = pod["containers"][0]
        assert pod["terminationGracePeriodSeconds"] >= 30, name  # SIGTERM, then time to close
        claims = {v["name"]: v["persistentVolumeClaim"]["claimName"] for v in pod["volumes"]
                  if "persistentVolumeClaim" in v}
        mounts[name] = {(claims[m["name"]], m["mountPath"]) for m in c["volumeMounts"] if m["name"] in claims}
        env = {e["name"]: e.get("value") for e in c["env"]}
        assert env["PREFECT_API_URL"] == f"http://prefect-server:{prefect[0]['port']}/api", name
        if kind != "Deployment":
            cmd = c["command"]
            assert pod["restartPolicy"] == "Never" and cmd[:2] == ["ms3d", "run"]
            assert _flag(cmd, "--dask-address") == f"tcp://dask-scheduler:{scheduler[0]['port']}"
            (_claim, path), = mounts[name]
            assert _flag(cmd, "--work-dir").startswith(path + "/")  # as shipped: the shared volume
    assert mounts["ms3d-run"] == mounts["ms3d-nightly"] == mounts["dask-worker"] == {("ms3d-work", "/data")}
    assert "ReadWriteMany" in _by_name("PersistentVolumeClaim", "ms3d-work")["spec"]["accessModes"]
    assert worker["containers"][0]["command"][2] == f"tcp://dask-scheduler:{scheduler[0]['port']}"
    # the shipped campus config is a valid ms3d config
    cfg = tmp_path / "campus.yaml"
    cfg.write_text(_by_name("ConfigMap", "ms3d-campus")["data"]["campus.yaml"])
    assert CampusConfig.from_yaml(cfg).work_dir == "/data/ms3d-work/campus"


def _cluster_script():
    spec = importlib.util.spec_from_file_location("ms3d_slurm_cluster", DEPLOY / "slurm" / "cluster.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


LOOPBACK_SCHEDULER = {"host": "127.0.0.1", "dashboard_address": "127.0.0.1:0"}


def test_slurm_job_script_renders_with_the_recipe_values():
    pytest.importorskip("dask_jobqueue")
    mod = _cluster_script()
    opts = mod.load_cluster_options()
    with mod.make_cluster(opts, scheduler_options=LOOPBACK_SCHEDULER) as cluster:
        assert cluster.scheduler_address.startswith("tcp://127.0.0.1:")
        script = cluster.job_script()
    lines = script.splitlines()
    for line in opts["job_script_prologue"]:
        assert line in lines
    assert f"#SBATCH --cpus-per-task={opts['cores']}" in lines
    assert f"#SBATCH -t {opts['walltime']}" in lines
    mem = re.search(r"^#SBATCH --mem=(\d+)G$", script, re.MULTILINE)
    assert mem and int(mem.group(1)) * 2**30 >= parse_bytes(opts["memory"]) - 2**30
    worker = next(line for line in lines if "dask_worker" in line or "dask worker" in line).split()
    assert _flag(worker, "--nthreads") == "1" and _flag(worker, "--nworkers") == str(opts["processes"])
    per_worker = _mib(_flag(worker, "--memory-limit"))
    assert per_worker >= CampusConfig().partition.memory_budget_mb + IMPORT_OVERHEAD_MB
    assert per_worker >= MEASURED_PEAK_MB
    assert _flag(worker, "--lifetime") == "3h50m"  # workers leave before the walltime kills them


def test_slurm_cluster_script_prints_the_job_script_and_rejects_bad_configs(tmp_path, capsys):
    pytest.importorskip("dask_jobqueue")
    mod = _cluster_script()
    good = tmp_path / "ok.yaml"
    good.write_text(yaml.safe_dump({"cluster": {"cores": 4, "processes": 2, "memory": "16GB",
                                                "scheduler_options": LOOPBACK_SCHEDULER}}))
    assert mod.main(["--config", str(good), "--print-job-script"]) == 0
    out = capsys.readouterr().out
    assert "#SBATCH --cpus-per-task=4" in out and "--nworkers 2" in out and "tcp://127.0.0.1:" in out
    cases = {"missing.yaml": None, "broken.yaml": "cluster: [", "empty.yaml": "",
             "threads.yaml": "cluster: {cores: 8, processes: 3, memory: 32GB}",
             "nomem.yaml": "cluster: {cores: 8, processes: 8}"}
    for name, text in cases.items():
        p = tmp_path / name
        if text is not None:
            p.write_text(text)
        assert mod.main(["--config", str(p)]) == 2, name
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and str(p) in err[0] and "Traceback" not in err[0], (name, err)


def test_every_recipes_workers_start_with_the_heap_settings_of_local_workers():
    """A cluster's workers get the glibc settings local workers get (flows/runtime.py WORKER_MALLOC_ENV), not
    Dask's MALLOC_TRIM_THRESHOLD_=65536 (a third more time in numpy-heavy units)."""
    from flows.runtime import WORKER_MALLOC_ENV

    c = _pod_spec(_by_name("Deployment", "dask-worker"))["containers"][0]
    k8s = {e["name"]: e.get("value") for e in c["env"]}
    compose = _docs(DEPLOY / "compose.yaml")[0]["services"]["worker"]["environment"]
    prologue = " ".join(_docs(DEPLOY / "slurm_cluster.yaml")[0]["cluster"]["job_script_prologue"])
    for k, v in WORKER_MALLOC_ENV.items():
        assert k8s[k] == v and compose[k] == v and f"{k}={v}" in prologue, k


def _dockerfile() -> list[tuple[str, str]]:
    """(instruction, arguments) of deploy/Dockerfile, continuation lines joined, comments dropped."""
    text = re.sub(r"\\\n", " ", (DEPLOY / "Dockerfile").read_text())
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


def test_dockerfile_installs_what_make_installs():
    """Checked offline (no container runtime or registry here): the image installs the Makefile's Debian
    packages, the pinned CPU torch before ms3d, ms3d itself with an import check, the viewer's npm packages
    from the lock file, copies every code package, runs unprivileged, and the recipes name an image."""
    steps = _dockerfile()
    assert steps[0][0] == "FROM" and steps[0][1].startswith("python:3.11")
    runs = " ".join(a for i, a in steps if i == "RUN")
    make = (ROOT / "Makefile").read_text()
    apt = re.search(r"^APT_PACKAGES := (.+)$", make, re.M).group(1).split()
    assert all(p in runs for p in apt), apt
    torch_pin = re.search(r'"(torch==[^"]+)"', (ROOT / "pyproject.toml").read_text()).group(1)
    assert torch_pin in runs and runs.index(torch_pin) < runs.index("pip install .")
    assert "import open3d, torch, prefect, laspy" in runs and "npm ci --prefix viewer" in runs
    copied = {a.split()[0] for i, a in steps if i == "COPY"}
    for pkg in ("flows", "tasks", "storage", "ms3d_model", "synth", "viewer", "pyproject.toml"):
        assert pkg in copied, pkg
    assert any(i == "USER" and a != "root" for i, a in steps)
    assert not any(i == "ENTRYPOINT" for i, _ in steps)  # the recipes' commands run as given
    assert ("CMD", '["ms3d", "--help"]') in steps
    version = re.search(r'^version = "([^"]+)"', (ROOT / "pyproject.toml").read_text(), re.M).group(1)
    images = {c["image"] for _, _, c in _containers()}
    assert images == {f"registry.example.org/ms3d:{version}"}, images  # the image this Dockerfile builds
    compose = yaml.safe_load((DEPLOY / "compose.yaml").read_text())["services"]
    for name, svc in compose.items():
        if name != "postgres":
            assert svc["image"] == f"ms3d:{version}" and svc["build"]["dockerfile"] == "deploy/Dockerfile", name
