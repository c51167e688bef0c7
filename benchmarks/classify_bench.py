"""Grading throughput: pairs per second of the classify stage's inner loop for the default profile (the
shipped model) beside the paper-size profile (max_point 7,500, max_face 5,000, full widths).

For each profile, on the largest tile of a processed campus (``--work-dir``, default ms3d-work/w42, else
the demo work dir): featurise (+ cues for a model that uses them) and run the network in batches of
``--batch`` pairs, with ``--threads`` torch threads. Prints wall and CPU seconds, the split between
featurisation (points, faces, and the hand-made cues for a model that uses them) and the model, and
pairs/s, end to end and model only. The shipped networks (``ms3dqe_plus.pt``, ``ms3dqe.pt``) are timed too. The paper-size profile is timed
on fewer pairs (its network is 10x wider and its inputs 20x larger) with a randomly initialised network
unless ``--paper-model`` gives a checkpoint. The load average is printed: figures taken on a shared machine
are lower bounds. ``--cues`` also times the hand-made cue extraction alone (:func:`cue_rate`): all pairs of a
batch at once, and one pair per call (the shape of the per-pair loop it replaced).

    .venv/bin/python benchmarks/classify_bench.py
    .venv/bin/python benchmarks/classify_bench.py --work-dir W --model ms3d_model/weights/default.pt --cues --paper-pairs 0
    .venv/bin/python benchmarks/classify_bench.py --work-dir ms3d-work/demo --pairs 1024 --batch 64
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _largest_tile(work_dir: str):
    from storage.patches.read import PatchStore
    from storage.workdir.layout import WorkDir

    wd = WorkDir(work_dir)
    tiles = wd.live_tiles()
    return max((wd.tile_dir(t) for t in tiles), key=lambda d: len(PatchStore(d).patches()["patch"]))


def bench(net, profile, tp, n_pairs: int, batch: int, uses_cues: bool) -> dict:
    import numpy as np
    import torch

    from ms3d_model.dataset import to_batch
    from tasks.classify.pairs import featurise_tile_pairs

    feats_needed = profile.net.arch != "gbm"

    idx_all = np.arange(min(n_pairs, len(tp)))
    t_feat = t_net = c_feat = c_net = 0.0
    with torch.inference_mode():
        # warm-up batch, not timed
        f, c = featurise_tile_pairs(tp, idx_all[:min(batch, 8)], profile.max_points, profile.max_faces,
                                    profile.k_centre, profile.seed, uses_cues, feats_needed)
        net(to_batch(f, c if uses_cues else None))
        for s in range(0, len(idx_all), batch):
            idx = idx_all[s:s + batch]
            w, c0 = time.perf_counter(), time.process_time()
            f, c = featurise_tile_pairs(tp, idx, profile.max_points, profile.max_faces, profile.k_centre,
                                        profile.seed, uses_cues, feats_needed)
            x = to_batch(f, c if uses_cues else None)
            w1, c1 = time.perf_counter(), time.process_time()
            net(x)
            t_feat += w1 - w
            c_feat += c1 - c0
            t_net += time.perf_counter() - w1
            c_net += time.process_time() - c1
    n = len(idx_all)
    return {"pairs": n, "wall_s": t_feat + t_net, "cpu_s": c_feat + c_net, "feat_wall_s": t_feat, "net_wall_s": t_net,
            "pairs_per_s": n / (t_feat + t_net), "net_pairs_per_s": n / t_net, "feat_pairs_per_s": n / t_feat}


def cue_rate(tp, n_pairs: int, batch: int, repeats: int = 3) -> dict:
    """Pairs per second of :func:`ms3d_model.cues.batch_cues` on the first ``n_pairs`` pairs of a tile, at
    ``batch`` pairs per call and at one pair per call; the best of ``repeats`` runs each."""
    import numpy as np

    from ms3d_model.cues import batch_cues

    idx = np.arange(min(n_pairs, len(tp)))
    pts, tris, _, oe = tp.raw(idx)
    keys = tp.keys[idx]

    def run(b: int) -> float:
        t = time.perf_counter()
        for s in range(0, len(idx), b):
            batch_cues(pts[s:s + b], tris[s:s + b], oe[s:s + b], keys[s:s + b])
        return time.perf_counter() - t

    best = {b: min(run(b) for _ in range(repeats)) for b in (batch, 1)}
    return {"pairs": len(idx), "batched_pairs_per_s": len(idx) / best[batch], "single_pairs_per_s": len(idx) / best[1]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work-dir", default=None)
    ap.add_argument("--model", default=None, help="checkpoint of the default profile (default: the shipped one)")
    ap.add_argument("--paper-model", default=None, help="checkpoint of the paper profile (default: random init)")
    ap.add_argument("--pairs", type=int, default=512)
    ap.add_argument("--paper-pairs", type=int, default=16)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--paper-batch", type=int, default=8)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--cues", action="store_true", help="also time the cue extraction alone")
    a = ap.parse_args(argv)

    import torch

    from ms3d_model.profiles import get_profile
    from ms3d_model.train import load_checkpoint, make_model, net_uses_cues
    from tasks.classify.pairs import read_tile_pairs
    from tasks.classify.stage import DEFAULT_MODEL

    torch.set_num_threads(a.threads)
    wd = a.work_dir or next((str(p) for p in (ROOT / "ms3d-work" / "w42", ROOT / "ms3d-work" / "demo") if p.exists()), None)
    if wd is None:
        print("no processed campus found: pass --work-dir")
        return 0
    tile = _largest_tile(wd)
    t0 = time.perf_counter()
    tp = read_tile_pairs(tile)
    read_s = time.perf_counter() - t0
    print(f"campus {wd}, tile {tile.name}: {len(tp)} pairs, read in {read_s:.1f} s; torch threads {a.threads}; "
          f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    rows = []
    net, prof, _ = load_checkpoint(a.model or DEFAULT_MODEL)
    rows.append((f"default ({prof.net.arch})", prof, bench(net, prof, tp, a.pairs, a.batch, net_uses_cues(net)), a.batch))
    for extra in ("ms3dqe_plus.pt", "ms3dqe.pt"):  # the shipped networks of the default profile
        path = DEFAULT_MODEL.parent / extra
        if path.exists() and not a.model:
            enet, eprof, _ = load_checkpoint(path)
            rows.append((extra[:-3], eprof, bench(enet, eprof, tp, a.pairs, a.batch, net_uses_cues(enet)), a.batch))
    if a.paper_model:
        pnet, pprof, _ = load_checkpoint(a.paper_model)
    else:
        pprof = get_profile("paper")
        torch.manual_seed(0)
        pnet = make_model(pprof).eval()
    if a.paper_pairs > 0:
        rows.append(("paper size", pprof, bench(pnet, pprof, tp, a.paper_pairs, a.paper_batch, net_uses_cues(pnet)),
                     a.paper_batch))
    print(f"{'profile':<18} {'points/faces':>13} {'batch':>5} {'pairs':>5} {'wall s':>7} {'CPU s':>7} "
          f"{'pairs/s':>8} {'net only':>9} {'featurise':>9}")
    for name, p, r, b in rows:
        print(f"{name:<18} {f'{p.max_points}/{p.max_faces}':>13} {b:>5} {r['pairs']:>5} {r['wall_s']:>7.1f} "
              f"{r['cpu_s']:>7.1f} {r['pairs_per_s']:>8.1f} {r['net_pairs_per_s']:>9.1f} {r['feat_pairs_per_s']:>9.1f}")
    print(f"paper (RTX 3090): 0.514 s per pair = {1 / 0.514:.2f} pairs/s")
    if a.cues:
        c = cue_rate(tp, a.pairs, a.batch)
        print(f"cue extraction alone, {c['pairs']} pairs: {c['batched_pairs_per_s']:.0f} pairs/s at batch {a.batch}, "
              f"{c['single_pairs_per_s']:.0f} pairs/s one pair per call")
    return 0


if __name__ == "__main__":
    sys.exit(main())
