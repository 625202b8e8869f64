"""The HMM's floor: a sticky belief over floors, updated by each scan's floor evidence.

The tracker follows one floor at a time. Each scan moves the belief
``b_f`` (log-probabilities) by a prior that keeps the floor with
probability ``1 - ε`` and the scan's evidence ``ln mean_j L_fj^w`` (the
floor's mean tempered likelihood, ``EmissionModel.floor_log_marginals``);
the tracked floor changes once another floor's belief reaches
``floor_switch_posterior``. A build replays the same two steps over held-out
walks to choose the evidence weight ``w`` (``floor_sequence``).
"""

from __future__ import annotations

import math

import numpy as np


def log_sum_exp(x: np.ndarray) -> float:
    """Return ln Σ exp(x) (-inf when every x is): scipy's costs ten times as much a call."""
    top = float(np.max(x))
    if not np.isfinite(top):
        return top
    return top + float(np.log(np.sum(np.exp(x - top))))


def floor_belief(log_belief: np.ndarray, evidence: np.ndarray, switch_prob: float) -> np.ndarray:
    """Return the floor log-belief after one scan of log ``evidence`` per floor."""
    n = evidence.size
    stay = np.exp(log_belief)
    # π_f = (1 - ε) b_f + ε (1 - b_f) / (n - 1)
    prior = (1.0 - switch_prob) * stay + (switch_prob * (1.0 - stay) / (n - 1) if n > 1 else 0.0)
    logp = np.log(np.maximum(prior, 1e-300)) + evidence
    return logp - log_sum_exp(logp)


def tracked_floor(current: int, log_belief: np.ndarray, switch_posterior: float) -> int:
    """Return the floor to follow: the likeliest once it is sure enough (any, at first)."""
    best = int(np.argmax(log_belief))
    if current < 0 or (best != current and math.exp(log_belief[best]) >= switch_posterior):
        return best
    return current


def floor_sequence(evidence: np.ndarray, switch_prob: float, switch_posterior: float) -> np.ndarray:
    """Return the floor followed after each of a walk's scans, evidence (S, F) in scan order."""
    n_scans, n_floors = evidence.shape
    log_belief = np.full(n_floors, -math.log(n_floors)) if n_floors else np.zeros(0)
    current = -1
    out = np.empty(n_scans, dtype=np.int64)
    for i in range(n_scans):
        log_belief = floor_belief(log_belief, evidence[i], switch_prob)
        current = tracked_floor(current, log_belief, switch_posterior)
        out[i] = current
    return out
