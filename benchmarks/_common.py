"""Helpers shared by the benchmark scripts (not part of the package)."""

from __future__ import annotations

import json
import os
import platform
import resource
import subprocess
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEMO_INPUT = ROOT / "ms3d-work" / "demo-input"


def machine() -> str:
    cpu = ""
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        cpu = platform.processor()
    return f"{os.cpu_count()} cores, {cpu}, Python {platform.python_version()}"


def peak_rss_mb(children: bool = False) -> float:
    who = resource.RUSAGE_CHILDREN if children else resource.RUSAGE_SELF
    return resource.getrusage(who).ru_maxrss / 1024.0


def ensure_demo(out: Path = DEMO_INPUT, seed: int = 7) -> Path:
    """The demo campus (generated with ``ms3d synth`` in a subprocess when missing)."""
    m = out / "truth" / "manifest.json"
    if m.exists() and json.loads(m.read_text()).get("preset") == "demo":
        return out
    subprocess.run([str(ROOT / ".venv" / "bin" / "ms3d"), "synth", "--preset", "demo", "--seed", str(seed),
                    "--out", str(out), "--overwrite"], check=True)
    return out


def truth_in_campus_frame(synth_dir: Path, campus_origin: np.ndarray) -> np.ndarray:
    """The synth's true MLS -> mesh similarity re-expressed about the campus origin.

    registration.json holds M_o about the synth frame origin o; about c it is T(o - c) M_o T(c - o).
    """
    reg = json.loads((synth_dir / "truth" / "registration.json").read_text())
    m_o = np.asarray(reg["matrix_mls_to_mesh"], np.float64)
    d = np.asarray(reg["frame_origin"], np.float64) - np.asarray(campus_origin, np.float64)
    t1, t2 = np.eye(4), np.eye(4)
    t1[:3, 3] = d
    t2[:3, 3] = -d
    return t1 @ m_o @ t2
