"""The paper's Tables 3 and 4 with our measurements beside its numbers (plain text).

Our figures sit in a paper row only when the checkpoint that produced them is of that row's kind
(:func:`model_kind`, read from the checkpoint's architecture, never from the name it was passed under),
and every row of ours names its checkpoint ("GBM trees (default.pt)"): the trees' figures can never
appear under MS3DQE-Net's name.
"""

from __future__ import annotations

import math
from pathlib import Path

# Table 3 of Liu et al. 2023: method -> (data, Acc %, mAP %, parameters, seconds per pair on an RTX 3090)
PAPER_TABLE3 = {
    "PointNet": ("point clouds", 83.7, 80.3, 3_528_790, 0.167),
    "PointNet++": ("point clouds", 85.5, 82.0, 968_269, 0.744),
    "PointCNN": ("point clouds", 86.7, 82.9, 207_226, 3.210),
    "MeshNet": ("mesh", 87.1, 83.7, 4_254_631, 0.433),
    "DIFD-Net": ("point clouds, mesh", 85.6, 82.7, 14_889_054, 0.083),
    "Y-Net": ("point clouds, mesh", 86.7, 84.1, 14_882_750, 0.070),
    "2D3D-MVPNet": ("point clouds, mesh", 87.8, 85.3, 10_240_740, 0.012),
    "MS3DQE-Net": ("point clouds, mesh", 88.7, 86.1, 4_541_057, 0.514),
}
# Table 4: case -> (Acc %, seconds per pair)
PAPER_TABLE4 = {"(1)": (83.1, 0.411), "(2)": (83.6, 0.509), "(3)": (82.9, 0.421), "(4)": (86.1, 0.488),
                "(5)": (86.7, 0.496), "(6)": (87.9, 0.441), "Full": (88.7, 0.514)}
TABLE4_ROWS = ("3D point cloud feature extraction branch", "Face feature extraction subbranch",
               "Face center point global feature extraction subbranch",
               "Face center point local feature extraction subbranch", "Kernel correlation module",
               "Point feature aggregation")
_SWITCHES = ("points", "face", "centre_global", "centre_local", "kernel_correlation", "point_aggregation")

# our suite names -> the paper's row name
OURS_TO_PAPER = {"pointnet": "PointNet", "pointnet2": "PointNet++", "pointcnn": "PointCNN", "meshnet": "MeshNet",
                 "ms3dqe": "MS3DQE-Net"}
# rows of our own models (by kind) below the paper's: method, data
EXTRA_ROWS = {"gbm": ("GBM on cues (ours; tree nodes)", "point clouds, mesh"),
              "ms3dqe_plus": ("MS3DQE-Net+ (ours)", "point clouds, mesh, cues"),
              "ms3dqe_geo": ("MS3DQE-Net, geometry inputs (ours)", "point clouds, mesh"),
              "ms3dqe": ("MS3DQE-Net (ours, another)", "point clouds, mesh"),
              "pointnet": ("PointNet (ours, another)", "point clouds"), "meshnet": ("MeshNet (ours, another)", "mesh"),
              "pointnet2": ("PointNet++ (ours, another)", "point clouds"),
              "pointcnn": ("PointCNN (ours, another)", "point clouds")}


KIND_LABELS = {"ms3dqe": "MS3DQE-Net", "ms3dqe_plus": "MS3DQE-Net+", "ms3dqe_geo": "MS3DQE-Net (geometry inputs)",
               "pointnet": "PointNet", "pointnet2": "PointNet++", "pointcnn": "PointCNN", "meshnet": "MeshNet",
               "gbm": "GBM trees", "ablation": "MS3DQE-Net ablation"}
_ALL_ON = ("points", "face", "centre_global", "centre_local", "kernel_correlation", "point_aggregation")


def model_kind(net: dict) -> str:
    """The kind of model a checkpoint's architecture (``NetConfig.to_json()``) is: a key of :data:`KIND_LABELS`.

    >>> model_kind({"arch": "gbm", "n_cues": 25}), model_kind({"arch": "ms3dqe", "n_cues": 25})
    ('gbm', 'ms3dqe_plus')
    >>> model_kind({"arch": "ms3dqe", **{s: True for s in _ALL_ON}}), model_kind({"arch": "ms3dqe", "face": False})
    ('ms3dqe', 'ablation')
    """
    arch = net.get("arch", "ms3dqe")
    if arch in ("gbm", "pointnet", "pointnet2", "pointcnn"):
        return arch
    if net.get("corners") == "meshnet":
        return "meshnet"
    if net.get("n_cues", 0) > 0:
        return "ms3dqe_plus"
    if net.get("geometry"):
        return "ms3dqe_geo"
    return "ms3dqe" if all(net.get(s, True) for s in _ALL_ON) else "ablation"


def suite_kind(name: str) -> str:
    """The kind a suite name stands for ("ablation3" -> "ablation", "ablationFull" -> "ms3dqe")."""
    if name.startswith("ablation"):
        return "ms3dqe" if name == "ablationFull" else "ablation"
    return name


def model_label(net: dict, path: str | Path) -> str:
    """What a row of ours is called: kind and checkpoint file, e.g. "GBM trees (default.pt)" ("ms3dqe/best.pt"
    for the files of a training suite, all called best.pt).

    >>> model_label({"arch": "gbm"}, "ms3d_model/weights/default.pt")
    'GBM trees (default.pt)'
    """
    p = Path(path)
    name = f"{p.parent.name}/{p.name}" if p.name == "best.pt" else p.name
    return f"{KIND_LABELS[model_kind(net)]} ({name})"


def _f(v, fmt="{:.1f}", scale=1.0) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    return fmt.format(v * scale)


def table3(results: dict[str, dict]) -> str:
    """results: suite name -> {"acc", "map", "parameters", "sec_b1", "sec_best", "best_batch", "net", "path"}.

    A paper row shows our figures only from a result of its kind; the last column names the checkpoint. Results
    of other names (not an ablation) follow as rows of their own."""
    head = (f"{'Method':<30} {'Data':<26} {'Acc paper':>9} {'Acc ours':>9} {'mAP paper':>9} {'mAP ours':>9} "
            f"{'Params paper':>12} {'Params ours':>11} {'s/pair paper':>12} {'s/pair b=1':>10} {'s/pair best':>11}  "
            "Ours: model (checkpoint)")
    lines = ["Table 3. Classification results (paper: RTX 3090; ours: 2-core CPU, held-out campus)", head,
             "-" * len(head)]
    by_paper = {v: k for k, v in OURS_TO_PAPER.items()}
    shown = set()
    for method, (data, acc, mp, params, sec) in PAPER_TABLE3.items():
        key = by_paper.get(method, "")
        r = results.get(key, {})
        r = r if r and _kind(key, r) == key else {}  # figures of another kind never sit in this row
        if r:
            shown.add(key)
        lines.append(f"{method:<30} {data:<26} {acc:>9.1f} {_f(r.get('acc'), scale=100):>9} {mp:>9.1f} "
                     f"{_f(r.get('map'), scale=100):>9} {params:>12,} {_f(r.get('parameters'), '{:,.0f}'):>11} "
                     f"{sec:>12.3f} {_f(r.get('sec_b1'), '{:.4f}'):>10} {_best(r):>11}  {_label(r)}")
    for key, r in results.items():
        kind = _kind(key, r)
        if key in shown or kind == "ablation":
            continue
        label, data = EXTRA_ROWS[kind]
        lines.append(f"{label:<30} {data:<26} {'-':>9} {_f(r.get('acc'), scale=100):>9} {'-':>9} "
                     f"{_f(r.get('map'), scale=100):>9} {'-':>12} {_f(r.get('parameters'), '{:,.0f}'):>11} "
                     f"{'-':>12} {_f(r.get('sec_b1'), '{:.4f}'):>10} {_best(r):>11}  {_label(r)}")
    return "\n".join(lines)


def _kind(key: str, r: dict) -> str:
    return model_kind(r["net"]) if r.get("net") else suite_kind(key)


def _label(r: dict) -> str:
    if not r:
        return "-"
    return model_label(r["net"], r["path"]) if r.get("net") and r.get("path") else r.get("model", "?")


def _best(r: dict) -> str:
    return f"{_f(r.get('sec_best'), '{:.4f}')} (b={r['best_batch']})" if r.get("best_batch") else "-"


def table4(results: dict[str, dict], configs: dict[str, dict]) -> str:
    """results: case ("(1)".."(6)", "Full") -> metrics; configs: case -> NetConfig.to_json() (switches). A case
    whose result is not an MS3DQE-Net of that case's kind (an ablation, or the full network for "Full") stays
    empty; the last line names the checkpoint of every case."""
    wrong = {c for c, r in results.items()
             if r.get("net") and model_kind(r["net"]) != ("ms3dqe" if c == "Full" else "ablation")}
    results = {c: r for c, r in results.items() if c not in wrong}
    configs = {c: v for c, v in configs.items() if c not in wrong}
    cases = list(PAPER_TABLE4)
    lines = ["Table 4. Ablations of MS3DQE-Net (paper beside ours)",
             f"{'Network structure':<56}" + "".join(f"{c:>8}" for c in cases)]
    for label, sw in zip(TABLE4_ROWS, _SWITCHES):
        cells = []
        for c in cases:
            cfg = configs.get(c)
            cells.append("?" if cfg is None else ("1" if cfg.get(sw) else ""))
        lines.append(f"{label:<56}" + "".join(f"{x:>8}" for x in cells))
    lines.append(f"{'Acc (%) paper':<56}" + "".join(f"{PAPER_TABLE4[c][0]:>8.1f}" for c in cases))
    lines.append(f"{'Acc (%) ours':<56}" + "".join(f"{_f(results.get(c, {}).get('acc'), scale=100):>8}" for c in cases))
    lines.append(f"{'mAP (%) ours':<56}" + "".join(f"{_f(results.get(c, {}).get('map'), scale=100):>8}" for c in cases))
    lines.append(f"{'Time (s) paper, RTX 3090':<56}" + "".join(f"{PAPER_TABLE4[c][1]:>8.3f}" for c in cases))
    lines.append(f"{'Time (s) ours, CPU, batch 1':<56}" +
                 "".join(f"{_f(results.get(c, {}).get('sec_b1'), '{:.4f}'):>8}" for c in cases))
    named = [f"{c} {_label(results[c])}" for c in cases if c in results]
    lines.append("Ours: " + ("; ".join(named) if named else "no MS3DQE-Net checkpoint scored"))
    return "\n".join(lines)


def per_class(results: dict[str, dict]) -> str:
    """Per-class precision / recall / F1 and the confusion matrix of each of our models."""
    lines = ["Per class (good / bad) at each checkpoint's own threshold on p(bad) (thr; 0.5 when it ships none): "
             "precision, recall, F1; confusion [[good->good, good->bad], [bad->good, bad->bad]]"]
    for name, r in results.items():
        if "precision_good" not in r:
            continue
        who = _label(r) if r.get("net") else name
        lines.append(f"{who:<30} thr {_f(r.get('threshold', 0.5), '{:.3f}')}  P {_f(r['precision_good'], '{:.3f}')}/{_f(r['precision_bad'], '{:.3f}')}  "
                     f"R {_f(r['recall_good'], '{:.3f}')}/{_f(r['recall_bad'], '{:.3f}')}  "
                     f"F1 {_f(r['f1_good'], '{:.3f}')}/{_f(r['f1_bad'], '{:.3f}')}  confusion {r['confusion']}  n={r['n']}")
    return "\n".join(lines)
