"""``ms3d train``: synth campuses -> processed patch stores -> featurised pairs -> a trained network.

One command reproduces a shipped model::

    ms3d train --profile default --seeds 7 11 --out ms3d-work/train

For each seed it generates the synth ``demo`` campus (``<data>/s{seed}``) and processes it with the campus
flow (``<data>/w{seed}``) unless that was done before, featurises every labelled pair once (per tile and then
the whole set as one ``.npz`` keyed by the campuses' store fingerprints and the input sizes, under
``<data>/cache``), splits 4:1 by area with a buffer of the largest defect's extent
(:func:`ms3d_model.dataset.area_split`, :func:`ms3d_model.dataset.largest_defect_extent_m`), and trains
many epochs from the cached tensors (the profile's optimiser, loss, selection and threshold choice:
:mod:`ms3d_model.train`; ``--paper-training`` for the paper's). ``--work-dir`` adds campuses processed elsewhere (any labelled work dir). ``--suite``
trains the networks of the paper's Tables 3 and 4 too (PointNet, PointNet++, PointCNN, MeshNet-style,
MS3DQE-Net+, ablations (1)-(6)), each in ``OUT/<name>/``.

As a Prefect flow (``train_flow``) each step is a task and the per-epoch metrics are published as an
artifact; :func:`run_training` runs the same steps without Prefect (tests, ``--no-prefect``).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

log = logging.getLogger("ms3d.train")


@dataclass
class TrainSpec:
    """What to train on and how. seeds: synth demo campuses to generate/process; work_dirs: extra processed
    campuses (name = folder name); profile: a name of ``ms3d_model.profiles.PROFILES``; overrides: Profile
    fields (e.g. {"epochs": 3}); models: names of :data:`SUITE` to train (default: the profile's own net)."""

    out: str
    data: str = "ms3d-work"
    seeds: list = field(default_factory=lambda: [7, 11])  # ints, or "SEED@DENSITY" / "SEED:coarse" (campus_variant)
    work_dirs: list[str] = field(default_factory=list)
    preset: str = "demo"
    profile: str = "default"
    overrides: dict = field(default_factory=dict)
    models: list[str] = field(default_factory=lambda: ["ms3dqe"])
    block_m: float = 20.0
    val_fraction: float = 0.2
    buffer_m: float | None = None  # gap between training and validation; None: the largest defect's extent
    progress: bool = True
    workers: int = 2  # campuses prepared and featurised side by side (one process each)


def suite() -> dict[str, dict]:
    """Networks trained by ``--suite``: name -> NetConfig switches (on the profile's widths)."""
    from ms3d_model.cues import N_CUES
    from ms3d_model.net import ABLATIONS, MESHNET

    s = {"ms3dqe": {}, "ms3dqe_plus": {"n_cues": N_CUES}, "ms3dqe_geo": {"geometry": True}, "pointnet": {"arch": "pointnet"},
         "pointnet2": {"arch": "pointnet2"}, "pointcnn": {"arch": "pointcnn"}, "meshnet": MESHNET,
         "gbm": {"arch": "gbm", "n_cues": N_CUES}}
    s.update({f"ablation{k.strip('()')}": v for k, v in ABLATIONS.items()})  # ablationFull: Table 4's budget
    return s


def campus_variant(seed) -> tuple[int, float | None, bool, str]:
    """Parse one training campus: ``7`` (the preset as it is), ``"23@0.3"`` (MLS density 0.3 of the real
    scanner's) or ``"31:coarse"`` (a LoD2-like block model for the mesh, :mod:`synth.coarse`); both may be
    combined (``"31@0.5:coarse"``). Returns (seed, density or None, coarse, the campus's folder name).

    >>> campus_variant("23@0.3")
    (23, 0.3, False, 's23d0.3')
    >>> campus_variant(7)
    (7, None, False, 's7')
    """
    text = str(seed).strip()
    base, _, kind = text.partition(":")
    num, _, dens = base.partition("@")
    if kind not in ("", "coarse") or not num.isdigit():
        raise ValueError(f"training campus {text!r}: expected SEED, SEED@DENSITY or SEED:coarse")
    density = float(dens) if dens else None
    if density is not None and not 0 < density <= 4:
        raise ValueError(f"training campus {text!r}: the MLS density must be in (0, 4]")
    name = f"s{int(num)}" + (f"d{density:g}" if density is not None else "") + ("c" if kind else "")
    return int(num), density, bool(kind), name


def prepare_campus(seed, data: str, preset: str = "demo") -> str:
    """Generate and process the synth campus of ``seed`` (see :func:`campus_variant`) unless done; returns its
    work dir ``<data>/w<name without the s>``."""
    from flows.campus import run_campus
    from synth.generate import generate
    from tasks.config import CampusConfig

    num, density, coarse, name = campus_variant(seed)
    inp, work = Path(data) / name, Path(data) / f"w{name[1:]}"
    if not (inp / "campus.yaml").exists():
        log.info("generating synth campus %s seed %d (density %s%s) in %s", preset, num, density or "preset",
                 ", coarse mesh" if coarse else "", inp)
        generate(preset, seed=num, out=inp, overwrite=True, mls_density=density, coarse_mesh=coarse)
    if not any(work.glob("tiles/*/labels.parquet")):
        log.info("processing campus %s into %s", name, work)
        # the labelled patch stores are all training needs: no grades, so no region is rebuilt, and no report
        cfg = CampusConfig.from_yaml(inp / "campus.yaml", {"work_dir": str(work.absolute()), "runner": "inline",
                                                           "classify": {"enabled": False},
                                                           "repair": {"grades": "model"}, "report": {"enabled": False}})
        run_campus(cfg, progress=False)
    return str(work)


def _prepare_and_featurise(seed, data: str, preset: str, prof) -> tuple[str, str]:
    """One campus made ready in a worker process: processed (:func:`prepare_campus`) and its pairs
    featurised into the per-tile cache that :func:`load_pairs` reads. Returns (name, work dir)."""
    from tasks.classify import campus_pair_set

    name, work = campus_variant(seed)[3], prepare_campus(seed, data, preset)
    if prof is not None:
        campus_pair_set(work, name, prof.max_points, prof.max_faces, prof.k_centre, prof.seed,
                        str(Path(data) / "cache"), max_pairs=prof.max_pairs)
    return name, work


def prepare_campuses(seeds: list, data: str, preset: str = "demo", workers: int = 2, prof=None) -> dict[str, str]:
    """{name: work dir} of every training campus, prepared (and featurised at ``prof``'s sizes when given)
    ``workers`` at a time in their own processes (each campus runs inline, one core); in seed order."""
    if workers <= 1 or len(seeds) <= 1:
        return dict(_prepare_and_featurise(s, data, preset, prof) for s in seeds)
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(max_workers=min(workers, len(seeds)), mp_context=mp.get_context("spawn")) as pool:
        done = list(pool.map(_prepare_and_featurise, seeds, [data] * len(seeds), [preset] * len(seeds),
                             [prof] * len(seeds)))
    return dict(done)


def dataset_key(campuses: dict[str, str], profile) -> str:
    """Identity of a featurised training set: each campus's name and its live tiles' store fingerprints
    (labels included), the input sizes, seed and pair cap, and the cue names. 16 hex digits."""
    import hashlib

    from ms3d_model.cues import CUE_NAMES
    from storage.patches.state import store_fingerprint
    from storage.workdir.layout import WorkDir
    from tasks.classify import CACHE_VERSION

    spec = {"featuriser": CACHE_VERSION, "campuses": {name: {t.key: store_fingerprint(WorkDir(wd).tile_dir(t), ("labels",))
                                for t in WorkDir(wd).live_tiles()} for name, wd in sorted(campuses.items())},
            "sizes": [profile.max_points, profile.max_faces, profile.k_centre], "seed": profile.seed,
            "max_pairs": profile.max_pairs, "cues": list(CUE_NAMES)}
    return hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:16]


def load_pairs(campuses: dict[str, str], profile, cache_dir: str):
    """All labelled pairs of the campuses ({name: work dir}) at the profile's input sizes; featurised once and
    cached as ``cache_dir/pairs_<dataset_key>.npz`` (a later run with the same inputs reads that file)."""
    from ms3d_model.dataset import PairSet, load_pair_set, save_pair_set
    from tasks.classify import campus_pair_set

    path = Path(cache_dir) / f"pairs_{dataset_key(campuses, profile)}.npz"
    if path.exists():
        log.info("featurised pairs from the cache %s", path)
        return load_pair_set(path)
    parts = [campus_pair_set(wd, name, profile.max_points, profile.max_faces, profile.k_centre, profile.seed,
                             cache_dir, max_pairs=profile.max_pairs) for name, wd in campuses.items()]
    pairs = PairSet.concat([p for p in parts if len(p)])
    save_pair_set(pairs, path)
    return pairs


def train_one(name: str, switches: dict, spec: TrainSpec, pairs, train_mask, val_mask) -> dict:
    """Train one network of the suite into ``spec.out/name``."""
    from ms3d_model.profiles import get_profile
    from ms3d_model.train import train_model

    prof = replace(get_profile(spec.profile), **spec.overrides)
    prof = replace(prof, name=f"{prof.name}:{name}", net=replace(prof.net, **switches))
    import numpy as np

    tr, va = pairs.take(np.flatnonzero(train_mask)), pairs.take(np.flatnonzero(val_mask))
    if prof.net.arch == "gbm":
        return fit_tree_model(prof, tr, va, Path(spec.out) / name) | {"name": name}
    res = train_model(prof, tr, va, Path(spec.out) / name, progress=spec.progress)
    res["name"] = name
    return res


def without_cues(cues, names: tuple[str, ...]):
    """``cues`` (B, N_CUES) with the named columns set to 0: a constant column is never split on, so the
    trees cannot read it (their ``feature`` arrays never index it). An unknown name is an error."""
    import numpy as np

    from ms3d_model.cues import CUE_NAMES

    unknown = sorted(set(names) - set(CUE_NAMES))
    if unknown:
        raise ValueError(f"gbm_ignored_cues: unknown cue names {unknown}")
    if not names:
        return cues
    cues = np.array(cues, copy=True)
    cues[:, [CUE_NAMES.index(n) for n in names]] = 0.0
    return cues


def fit_tree_model(prof, tr, va, out: Path) -> dict:
    """The gradient-boosting baseline on the training pairs' cues, saved as a TreeNet checkpoint."""
    import torch

    from ms3d_model.context import clean_context_copies
    from ms3d_model.gbm import fit_gbm, tree_arrays, tree_depth
    from ms3d_model.net import build_net
    from ms3d_model.train import predict, save_checkpoint, validation_row

    t0, c0 = time.perf_counter(), time.process_time()
    cues, labels = clean_context_copies(tr.cues, tr.labels, prof.gbm_clean_context_share, prof.seed)
    cues = without_cues(cues, prof.gbm_ignored_cues)
    clf = fit_gbm(cues, labels, seed=prof.seed, max_iter=prof.gbm_max_iter, learning_rate=prof.gbm_lr,
                  max_leaf_nodes=prof.gbm_leaves, l2=prof.gbm_l2, balanced=prof.gbm_balanced)
    arrays = tree_arrays(clf)
    prof = replace(prof, net=replace(prof.net, tree_depth=tree_depth(arrays)))
    net = build_net(prof.net, {k: torch.from_numpy(v) for k, v in arrays.items()})
    _, rep = validation_row(va.labels, predict(net, va, 1024), prof.min_precision, prof.threshold_objective)
    rep["epoch"] = int(clf.n_iter_)
    secs, cpu = time.perf_counter() - t0, time.process_time() - c0
    h = save_checkpoint(out / "best.pt", net, prof, rep, [], rep["threshold"])
    log.info("gbm: %d trees, val AP(bad) %.4f mAP %.4f; threshold %.3f: P %.3f R %.3f, %.0f s", clf.n_iter_,
             rep["ap_bad"], rep["map"], rep["threshold"], rep["precision_bad"], rep["recall_bad"], secs)
    return {"best": rep, "history": [], "parameters": int(arrays["feature"].size), "train_seconds": secs,
            "train_cpu_seconds": cpu, "best_path": str(out / "best.pt"), "model_hash": h, "kernel_stats_init": {},
            "threshold": rep["threshold"]}


def run_training(spec: TrainSpec, step=None) -> dict:
    """The whole training run; ``step(fn, *args)`` runs each step (a Prefect task's ``.fn`` or a submit)."""

    from ms3d_model.dataset import area_split, largest_defect_extent_m
    from ms3d_model.profiles import get_profile

    step = step or (lambda fn, *a: fn(*a))
    t0, c0 = time.perf_counter(), time.process_time()
    prof = replace(get_profile(spec.profile), **spec.overrides)
    campuses = step(prepare_campuses, spec.seeds, spec.data, spec.preset, spec.workers, prof)
    campuses.update({Path(w).name: w for w in spec.work_dirs})
    t_data = time.perf_counter()
    pairs = step(load_pairs, campuses, prof, str(Path(spec.data) / "cache"))
    from storage.grid import PatchGrid

    size = PatchGrid().size_m
    for wd in campuses.values():
        cj = Path(wd) / "campus.json"
        if cj.exists():
            size = json.loads(cj.read_text()).get("grid", {}).get("size_m", size)
            break
    buffer_m = spec.buffer_m
    if buffer_m is None:  # no defect on both sides; capped so a facade of touching defects cannot eat the campus
        buffer_m = largest_defect_extent_m(pairs.ijk, pairs.labels, size, pairs.campus, cap_m=spec.block_m / 2)
    train_mask, val_mask = area_split(pairs.ijk, size, pairs.campus, spec.block_m, spec.val_fraction, prof.seed,
                                      buffer_m)
    log.info("%d pairs (%.1f %% bad): %d train, %d validation, %d dropped in the %.1f m buffer", len(pairs),
             100 * float(pairs.labels.mean()), train_mask.sum(), val_mask.sum(),
             len(pairs) - train_mask.sum() - val_mask.sum(), buffer_m)
    t_feat = time.perf_counter() - t_data
    all_models = suite()
    results = {}
    for name in spec.models:
        if name not in all_models:
            raise ValueError(f"unknown model {name!r}; choose from {sorted(all_models)}")
        results[name] = step(train_one, name, all_models[name], spec, pairs, train_mask, val_mask)
    summary = {"spec": asdict(spec), "campuses": campuses, "n_pairs": len(pairs), "n_train": int(train_mask.sum()),
               "n_val": int(val_mask.sum()), "bad_fraction": float(pairs.labels.mean()), "buffer_m": float(buffer_m),
               "featurise_seconds": t_feat, "wall_seconds": time.perf_counter() - t0,
               "cpu_seconds": time.process_time() - c0,
               "models": {k: {kk: v[kk] for kk in ("best", "parameters", "train_seconds", "train_cpu_seconds",
                                                   "best_path", "model_hash", "kernel_stats_init", "threshold")}
                          for k, v in results.items()}}
    Path(spec.out).mkdir(parents=True, exist_ok=True)
    (Path(spec.out) / f"summary_{'+'.join(spec.models)}.json").write_text(json.dumps(summary, indent=1, default=str))
    return summary


def train_flow_fn():
    """The Prefect flow (built lazily so importing this module does not import Prefect)."""
    from prefect import flow, task
    from prefect.cache_policies import NONE as NO_CACHE

    tasks = {}

    def step(fn, *args):
        if fn not in tasks:
            tasks[fn] = task(fn, name=fn.__name__.replace("_", "-"), cache_policy=NO_CACHE)
        return tasks[fn](*args)

    @flow(name="train-model", log_prints=True)
    def train_flow(spec_json: dict) -> dict:
        summary = run_training(TrainSpec(**spec_json), step)
        try:
            from prefect.artifacts import create_table_artifact

            rows = [{"model": k, **{m: v["best"].get(m) for m in ("acc", "map", "ap_bad", "threshold", "precision_bad",
                                                                  "recall_bad", "epoch")},
                     "train_seconds": round(v["train_seconds"])} for k, v in summary["models"].items()]
            create_table_artifact(key="train-summary", table=rows, description=f"training run {spec_json['out']}")
        except Exception as e:  # noqa: BLE001 - an artifact is a convenience
            log.warning("could not publish the training artifact: %s", e)
        return summary

    return train_flow


def train(spec: TrainSpec, use_prefect: bool = True) -> dict:
    """Run the training, as a Prefect flow on one embedded server unless ``use_prefect`` is False."""
    if not use_prefect:
        return run_training(spec)
    from flows.runtime import embedded_prefect

    home = Path(spec.out) / "prefect"
    with embedded_prefect(home, None):
        return train_flow_fn()(asdict(spec))
