"""Which transform to apply: the estimate, the identity, or the recorded transform (no I/O here).

An estimate is a fit, and a fit can bend a co-registered cloud onto a generalised model (a LoD2 city
model: 22 cm median displacement, scale 0.9953, on inputs that were already co-registered). So nothing is
applied on the fit's own word: every transform in play is scored on the same *held-out* MLS points (not
used by the fit) by their robust distance to the mesh surface (:func:`score_transform`, the worst
surface-orientation median of :func:`tasks.register.check.check_coregistered_samples`), and the transform
in place (the recorded one, else the identity) is replaced only by one that beats it clearly
(:func:`clearly_better`). The estimate is also held to its priors (scale, displacement at the data) and
to its own fitness figures; whatever is off becomes one line (:attr:`RegistrationVerdict.warning`).

Frames: arrays are float64 campus-local metres; matrices (4, 4) map MLS -> mesh.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from storage.errors import InputError
from tasks.config import RegistrationConfig
from tasks.register.base import FitFailed, apply_similarity
from tasks.register.check import check_coregistered_samples


@dataclass(frozen=True)
class TransformScore:
    """A transform's robust distance to the mesh surface on held-out MLS points (metres; inf when none
    of them lies over the mesh or they cannot be measured). median_m: the worst orientation-group median;
    p90_m: 90th percentile over all measured points."""

    median_m: float
    p90_m: float
    n_points: int

    def to_json(self) -> dict:
        return {"median_m": _finite(self.median_m), "p90_m": _finite(self.p90_m), "n_points": self.n_points}


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def score_transform(matrix: np.ndarray, holdout_xyz: np.ndarray, samples_xyz: np.ndarray,
                    samples_normal: np.ndarray, seed: int = 0) -> TransformScore:
    """Score ``matrix`` (4, 4) on holdout_xyz (n, 3) MLS points against the mesh surface samples (k, 3)
    with their unit normals (k, 3): the points are moved by the matrix and measured point-to-plane."""
    try:
        check = check_coregistered_samples(apply_similarity(matrix, holdout_xyz), samples_xyz, samples_normal,
                                           seed=seed)
    except InputError:  # moved off the mesh's extent entirely
        return TransformScore(math.inf, math.inf, 0)
    if check.n_points == 0 or not math.isfinite(check.median_m):
        return TransformScore(math.inf, math.inf, 0)
    return TransformScore(float(check.median_m), float(check.p90_m), int(check.n_points))


def displacement_at(matrix: np.ndarray, xyz: np.ndarray) -> tuple[float, float]:
    """(median, max) distance in metres that ``matrix`` (4, 4) moves the points xyz (n, 3).

    >>> m = np.eye(4); m[:3, 3] = (0.0, 0.0, 0.25)
    >>> displacement_at(m, np.zeros((3, 3)))
    (0.25, 0.25)
    """
    d = np.linalg.norm(apply_similarity(matrix, xyz) - np.asarray(xyz, np.float64), axis=1)
    return (float(np.median(d)), float(d.max())) if len(d) else (0.0, 0.0)


def clearly_better(new_m: float, old_m: float, cfg: RegistrationConfig) -> bool:
    """Does a distance ``new_m`` beat ``old_m`` by ``cfg.min_improvement_m`` and ``cfg.min_improvement_ratio``?

    >>> cfg = RegistrationConfig()  # 5 cm and half
    >>> clearly_better(0.01, 1.2, cfg), clearly_better(0.03, 0.06, cfg), clearly_better(0.01, 0.05, cfg)
    (True, False, False)
    """
    if not math.isfinite(new_m):
        return False
    if not math.isfinite(old_m):
        return True
    return old_m - new_m >= cfg.min_improvement_m and new_m <= (1.0 - cfg.min_improvement_ratio) * old_m


@dataclass(frozen=True)
class Estimate:
    """What the fit gave: its matrix (4, 4), scale, final and coarse fitness, its score on the held-out
    points and the displacement it gives them (median, max metres). ``error``: why the fit failed
    (then the rest is meaningless)."""

    matrix: np.ndarray | None = None
    scale: float = 1.0
    fitness: float = math.nan
    coarse_fitness: float = math.nan
    score: TransformScore | None = None
    displacement_m: tuple[float, float] = (0.0, 0.0)
    error: str = ""


@dataclass(frozen=True)
class RegistrationVerdict:
    """chosen: "estimate", "identity" or "recorded"; reason: one sentence; problems: what was off with the
    estimate (empty when nothing); warning: the one line to log (None when the estimate was applied
    and nothing was off)."""

    chosen: str
    reason: str
    problems: tuple[str, ...]

    @property
    def warning(self) -> str | None:
        if self.chosen == "estimate" and not self.problems:
            return None
        return "registration: " + self.reason + ("; " + "; ".join(self.problems) if self.problems else "")

    def to_json(self) -> dict:
        return {"chosen": self.chosen, "reason": self.reason, "problems": list(self.problems),
                "warning": self.warning}


def estimate_problems(est: Estimate, cfg: RegistrationConfig) -> list[str]:
    """What is off with an estimate, one phrase each (empty: nothing)."""
    if est.error:
        return [f"the estimate failed: {est.error}"]
    out = []
    if abs(est.scale - 1.0) > cfg.max_scale_error:
        out.append(f"its scale {est.scale:.5f} is outside the prior 1 ± {cfg.max_scale_error:g} "
                   "(registration.max_scale_error)")
    if est.displacement_m[1] > cfg.max_displacement_m:
        out.append(f"it moves the MLS points up to {est.displacement_m[1]:.2f} m (median "
                   f"{est.displacement_m[0]:.2f} m), beyond the prior {cfg.max_displacement_m:g} m "
                   "(registration.max_displacement_m)")
    if est.coarse_fitness < cfg.min_coarse_fitness:
        out.append(f"the coarse stage failed (SAC-IA fitness {est.coarse_fitness:.2f})")
    if est.fitness < cfg.min_fitness:
        out.append(f"low final fitness {est.fitness:.2f} (registration.min_fitness {cfg.min_fitness:g})")
    return out


def judge_registration(identity: TransformScore, est: Estimate, cfg: RegistrationConfig,
                       recorded: TransformScore | None = None) -> RegistrationVerdict:
    """Choose the transform to apply. The incumbent is the recorded transform (when ``recorded`` is
    given: its score on the same held-out points), else the identity. The estimate replaces it only
    when it did not fail, its scale lies within the prior, and it is :func:`clearly_better`; with a
    recorded incumbent, the identity may replace it the same way. The displacement, fitness and
    coarse-stage checks flag the estimate but do not refuse it.

    >>> cfg = RegistrationConfig()
    >>> v = judge_registration(TransformScore(0.06, 0.2, 900), Estimate(np.eye(4), 0.9953, 0.42, 0.0,
    ...                        TransformScore(0.04, 0.1, 900), (0.22, 0.29)), cfg)
    >>> v.chosen, len(v.problems)
    ('identity', 3)
    """
    problems = tuple(estimate_problems(est, cfg))
    inc_name, inc = ("recorded", recorded) if recorded is not None else ("identity", identity)
    usable = not est.error and abs(est.scale - 1.0) <= cfg.max_scale_error and est.score is not None
    if usable and clearly_better(est.score.median_m, inc.median_m, cfg):
        return RegistrationVerdict("estimate", f"applied the estimate (held-out distance to the mesh "
                                   f"{_m(inc.median_m)} -> {_m(est.score.median_m)} m)", problems)
    if inc_name == "recorded" and clearly_better(identity.median_m, inc.median_m, cfg):
        return RegistrationVerdict("identity", f"kept the identity: it beats the recorded transform "
                                   f"({_m(identity.median_m)} vs {_m(inc.median_m)} m)", problems)
    kept = "kept the recorded transform" if inc_name == "recorded" else "kept the identity (inputs left in place)"
    if est.error:  # the failure is the reason: said once, not again as a problem
        why = "the re-registration failed" if inc_name == "recorded" else "the estimate failed"
        return RegistrationVerdict(inc_name, f"{kept}: {why}: {est.error}", ())
    if not usable:
        why = "the estimate is outside the scale prior"
    else:
        why = (f"the estimate does not clearly improve the held-out distance to the mesh ({_m(inc.median_m)} -> "
               f"{_m(est.score.median_m)} m; needs {cfg.min_improvement_m:g} m and "
               f"{100 * cfg.min_improvement_ratio:.0f} % less)")
    return RegistrationVerdict(inc_name, f"{kept}: {why}", problems)


def _m(x: float) -> str:
    return f"{x:.3f}" if math.isfinite(x) else "inf"


def guarded_register(source_xyz: np.ndarray, samples_xyz: np.ndarray, samples_normal: np.ndarray,
                     cfg: RegistrationConfig, recorded: dict | None = None) -> dict:
    """Register, then apply the estimate only when :func:`judge_registration` says so.

    source_xyz: (n, 3) MLS sample; samples_xyz, samples_normal: (k, 3) mesh surface samples and unit normals;
    float64 campus-local metres. recorded: the registration recorded by an earlier run (its ``matrix``,
    same frame), or None. A random ``cfg.holdout_share`` of the source (seed ``cfg.seed``) is held out of
    the fit and scores identity, the recorded transform and the estimate.

    Returns the registration as a dict: the chosen transform's ``matrix``, ``scale``, ``method`` and fit
    figures (the estimate's :meth:`RegistrationResult.to_json`, the recorded dict, or the identity's),
    plus ``verdict`` (:meth:`RegistrationVerdict.to_json`), ``warning`` (one line or None),
    ``displacement_p50_m`` / ``displacement_max_m`` (what the chosen transform does to the sampled MLS
    points), ``distance_before_m`` / ``distance_after_m`` (held-out median under identity / the chosen
    transform; ``..._p90_m`` likewise) and ``estimate`` (its figures). Raises InputError when the inputs
    cannot be registered with nothing recorded, or, with ``cfg.strict``, when anything is flagged (a failed
    fit included); a failed fit (:class:`FitFailed`) with nothing recorded keeps the identity and warns.
    """
    from tasks.register.align import register_to_samples

    src = np.asarray(source_xyz, np.float64)
    held = np.random.default_rng(cfg.seed).random(len(src)) < cfg.holdout_share
    hold = src[held]
    rec_m = np.asarray(recorded["matrix"], np.float64) if recorded and "matrix" in recorded else None
    identity = score_transform(np.eye(4), hold, samples_xyz, samples_normal, cfg.seed)
    rec_score = None if rec_m is None else score_transform(rec_m, hold, samples_xyz, samples_normal, cfg.seed)
    result = None
    try:
        result = register_to_samples(src[~held], samples_xyz, samples_normal, cfg)
    except InputError as e:
        if rec_m is None and not isinstance(e, FitFailed):  # the inputs themselves cannot be registered
            raise
        est = Estimate(error=e.problem if isinstance(e, FitFailed) else str(e))
    else:
        est = Estimate(result.matrix, result.scale, result.fitness, result.coarse_fitness,
                       score_transform(result.matrix, hold, samples_xyz, samples_normal, cfg.seed),
                       displacement_at(result.matrix, src))
    verdict = judge_registration(identity, est, cfg, rec_score)
    if cfg.strict and (verdict.problems or est.error):
        raise InputError(None, f"{verdict.warning} (registration.strict is set)")
    if verdict.chosen == "estimate":
        out, score, moved = result.to_json(), est.score, est.displacement_m
    elif verdict.chosen == "recorded":
        out, score, moved = dict(recorded), rec_score, displacement_at(rec_m, src)
    else:
        out = {"matrix": np.eye(4).tolist(), "scale": 1.0, "method": "identity (estimate not applied)"}
        score, moved = identity, (0.0, 0.0)
    return out | {
        "verdict": verdict.to_json(), "warning": verdict.warning,
        "displacement_p50_m": moved[0], "displacement_max_m": moved[1],
        "distance_before_m": _finite(identity.median_m), "distance_after_m": _finite(score.median_m),
        "distance_before_p90_m": _finite(identity.p90_m), "distance_after_p90_m": _finite(score.p90_m),
        "distance_recorded_m": None if rec_score is None else _finite(rec_score.median_m),
        "estimate": {"error": est.error} if est.error else {
            "scale": est.scale, "fitness": est.fitness, "coarse_fitness": est.coarse_fitness,
            "distance_m": _finite(est.score.median_m), "displacement_p50_m": est.displacement_m[0],
            "displacement_max_m": est.displacement_m[1], "method": result.method},
    }


__all__ = ["Estimate", "RegistrationVerdict", "TransformScore", "clearly_better", "displacement_at",
           "estimate_problems", "guarded_register", "judge_registration", "score_transform"]
