"""The user's labelling loop: the localhost label endpoint, least-sure proposals, the viewer's labelling mode in
headless chromium, and the fine-tune on the user's labels."""

from __future__ import annotations

import csv
import json
import shutil
import socket
import subprocess
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from flows.label_server import LabelApi, least_sure
from flows.view import VIEWER_DIR, start_viewer
from storage.grid import PatchGrid


def _post(url: str, body: bytes, **headers: str) -> tuple[int, dict]:
    headers = {"Content-Type": "application/json"} | {k.replace("_", "-"): v for k, v in headers.items()}
    req = urllib.request.Request(url, data=body, method="POST", headers=headers)
    try:
        with urllib.request.urlopen(req) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        body = e.read()
        return e.code, json.loads(body) if e.headers.get("Content-Type") == "application/json" else body


def _rows(work: Path) -> list[dict]:
    out = []
    for p in sorted((work / "labels").glob("user-*.csv")):
        with open(p, newline="") as f:
            out.extend(csv.DictReader(f))
    return out


@pytest.fixture
def export_copy(tiny_export, tmp_path):
    work = tmp_path / "work"
    shutil.copytree(tiny_export[0], work, ignore=shutil.ignore_patterns("labels"))
    return work


def test_endpoint_appends_valid_rows_rejects_bad_ones_and_binds_loopback(export_copy, capfd):
    server = start_viewer(export_copy, label=True)
    try:
        host, port = server.httpd.server_address[:2]
        assert host == "127.0.0.1"
        base = f"http://127.0.0.1:{port}"
        assert "label=1" in server.url
        assert _post(f"{base}/api/label", b'{"i": 5, "j": -7, "k": 3, "label": 1}') == (200, {
            "ok": True, "file": _rows_dir_name(), "n_labels": 1})
        assert _post(f"{base}/api/label", b'{"i": 6, "j": -7, "k": 3, "label": 0}')[0] == 200
        capfd.readouterr()
        bad = [b"not json", b'{"i": 1, "j": 2, "k": 3, "label": 2}', b'{"i": 1.5, "j": 2, "k": 3, "label": 1}',
               b'{"i": "1", "j": 2, "k": 3, "label": 1}', b'{"i": 1, "j": 2, "label": 1}', b"[1, 2, 3, 1]",
               b'{"i": 99999999, "j": 2, "k": 3, "label": 1}', b'{"i": 1, "j": 2, "k": 3, "label": true}']
        for body in bad:
            status, doc = _post(f"{base}/api/label", body)
            assert status == 400 and "\n" not in doc["error"] and doc["error"], (body, doc)
        assert _post(f"{base}/api/locate", b'{"ecef": [1, "x", 3]}')[0] == 400
        # another site's page: a 'simple' cross-site POST (text/plain) or a rebound host name is refused
        ok_body = b'{"i": 7, "j": -7, "k": 3, "label": 1}'
        assert _post(f"{base}/api/label", ok_body, Content_Type="text/plain")[0] == 415
        assert _post(f"{base}/api/label", ok_body, Host=f"evil.example:{port}")[0] == 403
        err = capfd.readouterr().err
        assert len(err.strip().splitlines()) == len(bad) + 3 and "Traceback" not in err, err
        assert "label must be 0 (good) or 1 (bad), got 2" in err
        # nothing but loopback: the socket is bound to 127.0.0.1, so another interface's address is refused
        other = socket.gethostbyname(socket.gethostname())
        if not other.startswith("127."):
            with pytest.raises(OSError):
                socket.create_connection((other, port), timeout=2).close()
        assert _post(f"{base}/viewer/index.html", b"{}")[0] == 405  # files stay read-only
    finally:
        server.stop()
    rows = _rows(export_copy)
    assert [(r["i"], r["j"], r["k"], r["label"]) for r in rows] == [("5", "-7", "3", "1"), ("6", "-7", "3", "0")]
    assert all(r["time"].endswith("+00:00") for r in rows)


def _rows_dir_name() -> str:
    import datetime as dt

    return f"labels/user-{dt.datetime.now(dt.UTC):%Y-%m-%d}.csv"


def test_non_loopback_clients_are_refused(export_copy):
    from flows.view import _Handler

    class Fake(_Handler):  # the handler's own check, as if a packet arrived from elsewhere
        def __init__(self):
            self.client_address = ("192.0.2.7", 5555)
            self.sent = []

        def send_error(self, code, message=None, explain=None):
            self.sent.append(code)

    h = Fake()
    assert not h._loopback() and h.sent == [403]


@pytest.fixture
def graded_work(tiny_work, tiny_export, tmp_path):
    """A copy of the processed tiny campus with seeded random grades (threshold 0.4) and the tiny export's
    output/ (the same synth campus, so the same world and ECEF), georeferenced from this campus's frame.
    Returns (work dir, (u,) keys, (u,) scores)."""
    from storage.patches.read import PatchStore
    from storage.patches.write import write_side_table
    from storage.workdir.layout import WorkDir, campus_frame, read_campus
    from tasks.export import make_georef

    rng = np.random.default_rng(3)
    _, wd0 = tiny_work
    work = tmp_path / "graded"
    shutil.copytree(wd0.root, work, ignore=shutil.ignore_patterns("*.npz", "regions", "labels", "output"))
    shutil.copytree(tiny_export[0] / "output", work / "output")
    wd = WorkDir(work)
    all_keys, all_scores = [], []
    for t in wd.live_tiles():
        store = PatchStore(wd.tile_dir(t))
        k = store.patches()["patch"]
        s = rng.random(len(k)).astype(np.float32)
        write_side_table(wd.tile_dir(t), "grades", {"patch": k, "score": s, "grade": (s >= 0.4).astype(np.int8)},
                         store.meta, threshold=0.4)
        all_keys.append(k)
        all_scores.append(s)
    frame = campus_frame(read_campus(wd))
    (work / "output" / "georef.json").write_text(json.dumps(make_georef(frame.crs, frame.origin, (50.0, 50.0, 0.0)).to_json()))
    return work, np.concatenate(all_keys), np.concatenate(all_scores).astype(np.float64)


def test_least_sure_orders_by_distance_to_the_threshold(graded_work):
    rng = np.random.default_rng(3)
    keys = np.arange(50, dtype=np.int64)
    scores = rng.random(50)
    scores[[4, 9]] = np.nan
    got = least_sure(keys, scores, 0.3, 10)
    margin = np.abs(scores - 0.3)
    assert got.tolist() == np.argsort(np.where(np.isnan(margin), np.inf, margin), kind="stable")[:10].tolist()
    assert 4 not in least_sure(keys, scores, 0.3, 100) and len(least_sure(keys, scores, 0.3, 100)) == 48

    work, k_all, s_all = graded_work
    api = LabelApi(work)
    props = api.proposals(15)
    want = k_all[least_sure(k_all, s_all, 0.4, 15)]
    ijk = np.array([[p["i"], p["j"], p["k"]] for p in props["proposals"]])
    assert PatchGrid.pack(ijk).tolist() == want.tolist() and props["threshold"] == pytest.approx(0.4)
    m = [p["margin"] for p in props["proposals"]]
    assert m == sorted(m) and m[0] == pytest.approx(np.abs(s_all - 0.4).min(), abs=1e-6)
    # each centre maps back to its own cell; a labelled patch is no longer proposed
    for p in props["proposals"][:3]:
        loc = api.locate(json.dumps({"ecef": p["ecef"]}).encode())
        assert (loc["i"], loc["j"], loc["k"]) == (p["i"], p["j"], p["k"])
    first = props["proposals"][0]
    api.label(json.dumps({"i": first["i"], "j": first["j"], "k": first["k"], "label": 1}).encode())
    again = api.proposals(15)["proposals"]
    assert (again[0]["i"], again[0]["j"], again[0]["k"]) == (props["proposals"][1]["i"], props["proposals"][1]["j"],
                                                             props["proposals"][1]["k"])


def _drive(work: Path, mode: str) -> dict:
    from tests.flows.test_view import _tools_or_fail

    _tools_or_fail()
    server = start_viewer(work, label=True)
    try:
        run = subprocess.run(["node", str(VIEWER_DIR / "label.mjs"), server.url, "1024", "700", "90000", mode],
                             check=False, capture_output=True, text=True, timeout=150)
    finally:
        server.stop()
    assert run.returncode == 0, run.stderr[-2000:]
    return json.loads(run.stdout)


def test_headless_browser_labels_the_least_sure_patches_with_the_keys(graded_work):
    work, k_all, s_all = graded_work
    result = _drive(work, "propose")
    assert result["ready"] and not result.get("error") and not _console(result), result
    want = PatchGrid.unpack(k_all[least_sure(k_all, s_all, 0.4, 2)]).tolist()
    assert [[c["i"], c["j"], c["k"]] for c in result["clicks"]] == want and [c["label"] for c in result["clicks"]] == [1, 0]
    rows = [[int(r[c]) for c in ("i", "j", "k", "label")] for r in _rows(work)]
    assert rows == [want[0] + [1], want[1] + [0]]


def test_headless_browser_labels_two_patches_into_the_csv(export_copy):
    result = _drive(export_copy, "click")
    assert result["ready"] and not result.get("error") and not _console(result), result
    clicks = result["clicks"]
    assert len(clicks) == 2 and [c["label"] for c in clicks] == [1, 0], result
    assert (clicks[0]["i"], clicks[0]["j"], clicks[0]["k"]) != (clicks[1]["i"], clicks[1]["j"], clicks[1]["k"])
    rows = {(int(r["i"]), int(r["j"]), int(r["k"]), int(r["label"])) for r in _rows(export_copy)}
    assert rows == {(c["i"], c["j"], c["k"], c["label"]) for c in clicks}
    assert result["state"]["panel"].startswith("2 patches labelled (good 1 · bad 1)")


def test_finetune_on_user_labels_writes_a_checkpoint_that_loads_and_regrades(tiny_work, tmp_path):
    import time

    import yaml

    from flows.finetune import FinetuneSpec, finetune
    from storage.patches.read import PatchStore
    from storage.workdir.layout import WorkDir
    from storage.workdir.user_labels import append_user_label
    from tasks.classify import DEFAULT_MODEL, run_classify_tile
    from tasks.classify.pairs import gradable_mask

    cfg0, wd0 = tiny_work
    work = tmp_path / "work"
    shutil.copytree(wd0.root, work, ignore=shutil.ignore_patterns("labels"))
    cfg = cfg0.model_copy(update={"work_dir": str(work)})
    config = tmp_path / "campus.yaml"
    config.write_text(yaml.safe_dump(cfg.model_dump(mode="json")))
    wd = WorkDir(work)
    rng = np.random.default_rng(0)
    picked = []  # 10 bad and 10 good gradable pairs, labelled as the synth truth says
    for t in wd.live_tiles():
        store = PatchStore(wd.tile_dir(t))
        p, lab = store.patches(), store.side("labels")["label"]
        ok = gradable_mask(p, 1, 1)
        for want in (0, 1):
            rows = np.flatnonzero(ok & (lab == want))
            for r in rng.choice(rows, min(3, len(rows)), replace=False):
                picked.append(((int(p["i"][r]), int(p["j"][r]), int(p["k"][r])), want))
    picked = picked[:20]
    for ijk, want in picked:
        append_user_label(work, ijk, want)
    append_user_label(work, (0, 0, 0), 1)  # no such patch: dropped and counted

    t0 = time.perf_counter()
    s = finetune(FinetuneSpec(campus=str(config), base=str(DEFAULT_MODEL), out=str(tmp_path / "ft"), seeds=[],
                              work_dirs=[str(work)], data=str(tmp_path / "data"), holdout=0.25))
    assert time.perf_counter() - t0 < 40
    assert s["n_user_labels"] == len(picked) + 1 and s["n_user_dropped_not_pairs"] == 1
    assert s["n_synth_excluded_user_patches"] == len(picked)  # the campus is also a synth one: no leak
    assert s["n_user_train"] + s["n_user_heldout"] == len(picked) and s["n_user_heldout"] == round(0.25 * len(picked))
    card = (tmp_path / "ft" / "MODEL_CARD.md").read_text()
    assert "Held-out user labels" in card and f"{s['n_user_heldout']} held out" in card
    assert s["heldout_user"]["finetuned"]["n"] == s["n_user_heldout"]
    # pointing classify.model at it re-grades (a new model hash), and the user's pairs come out as labelled
    ccfg = cfg.classify.model_copy(update={"enabled": True, "model": s["checkpoint"], "evidence": False})
    cfg = cfg.model_copy(update={"classify": ccfg})
    truth, graded = {}, {}
    for t in wd.live_tiles():
        res = run_classify_tile(t, cfg, wd)
        assert res["status"] == "done" and not res["skipped"] and res["model_hash"] == s["model_hash"]
        store = PatchStore(wd.tile_dir(t))
        p, g = store.patches(), store.side("grades")["grade"]
        graded.update({(int(a), int(b), int(c)): int(v) for a, b, c, v in zip(p["i"], p["j"], p["k"], g)})
    truth = dict(picked)
    agree = np.mean([graded[k] == v for k, v in truth.items()])
    assert agree >= 0.75, agree
    assert all(r["skipped"] for r in (run_classify_tile(t, cfg, wd) for t in wd.live_tiles()))


def test_user_labels_latest_row_wins_and_a_bad_file_is_one_line(tmp_path):
    import datetime as dt

    from storage.errors import InputError
    from storage.workdir.user_labels import append_user_label, read_user_labels

    t0 = dt.datetime(2026, 5, 1, 12, 0, tzinfo=dt.UTC)
    append_user_label(tmp_path, (1, 2, 3), 1, t0)
    append_user_label(tmp_path, (4, 5, 6), 0, t0 + dt.timedelta(seconds=1))
    append_user_label(tmp_path, (1, 2, 3), 0, t0 + dt.timedelta(days=1))  # next day's file: changed their mind
    assert sorted(p.name for p in (tmp_path / "labels").iterdir()) == ["user-2026-05-01.csv", "user-2026-05-02.csv"]
    keys, labels = read_user_labels(tmp_path)
    assert dict(zip(map(tuple, PatchGrid.unpack(keys).tolist()), labels.tolist())) == {(1, 2, 3): 0, (4, 5, 6): 0}
    (tmp_path / "labels" / "user-2026-05-03.csv").write_text("i,j,k,label,time\n1,2,3,7,2026-05-03T00:00:00+00:00\n")
    with pytest.raises(InputError) as e:
        read_user_labels(tmp_path)
    assert "user-2026-05-03.csv" in str(e.value) and "line 2" in str(e.value) and "\n" not in str(e.value)


def _console(result: dict) -> list[str]:
    """The page's console messages, less the 404 of the optional before / after tileset probe (an export
    without ``export.before`` has none)."""
    return [m for m in result["console"] if "before/tileset.json" not in m
            and "status of 404" not in m]
