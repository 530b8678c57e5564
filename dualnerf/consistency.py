"""The CLIP consistency indicator (CCI, paper Sec. 4.3) and the loss weights it induces.

S(I' | I, y) = cos01(E_I(I'), E_I(I)) * cos01(E_I(I'), E_T(y))            (eq. 9)
with cos01(a, b) = (1 + cos(a, b)) / 2, the cosine similarity mapped into [0, 1].
The RGB loss of rays from view i is weighted by S_i / mean_j(S_j)         (eq. 10)

Each view's S is cached until that view is updated again. A view that has not been edited yet still
trains on its original image I, so its score is S(I | I, y) = 1 * cos01(E_I(I), E_T(y)): the same
formula with I' = I. Original views therefore weigh less than good edits (their text consistency is
lower) and more than failed edits that match neither the original nor the text.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def cos01(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cosine similarity along the last axis, normalised into [0, 1] as (1 + cos) / 2."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    denom = np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1)
    cos = np.sum(a * b, axis=-1) / np.maximum(denom, 1e-12)
    return (1.0 + np.clip(cos, -1.0, 1.0)) / 2.0


def consistency_score(edited_feature: np.ndarray, original_feature: np.ndarray,
                      text_feature: np.ndarray) -> np.ndarray:
    """S(I' | I, y) (eq. 9) from encoder features; broadcasts over leading axes."""
    return cos01(edited_feature, original_feature) * cos01(edited_feature, text_feature)


def consistency_weights(scores: np.ndarray) -> np.ndarray:
    """Per-view loss weights S_i / mean(S) (eq. 10); they average to 1."""
    scores = np.asarray(scores, dtype=np.float64)
    if scores.ndim != 1 or len(scores) == 0:
        raise ValueError(f"consistency scores must be a non-empty 1-D array, got shape {scores.shape}")
    mean = scores.mean()
    if not mean > 0:
        return np.ones_like(scores)
    return scores / mean


@dataclass
class ConsistencyCache:
    """S per training view, replaced only when that view is edited again. Plain state for checkpoints."""

    scores: np.ndarray            # (V,) float64

    @classmethod
    def for_originals(cls, original_features: np.ndarray, text_feature: np.ndarray) -> ConsistencyCache:
        """Initial scores: every view is its own original, S(I | I, y) (see module docstring)."""
        return cls(scores=consistency_score(original_features, original_features, text_feature[None, :]))

    def update(self, view: int, score: float) -> None:
        self.scores[view] = float(score)

    def weights(self) -> np.ndarray:
        return consistency_weights(self.scores)

    def state_dict(self) -> dict:
        return {"scores": [float(s) for s in self.scores]}

    @classmethod
    def from_state_dict(cls, state: dict) -> ConsistencyCache:
        return cls(scores=np.asarray(state["scores"], dtype=np.float64))


def flagging_quality(updates: list[dict]) -> dict:
    """How well the consistency score flags the editor's failed calls, from the edit stage's update records
    (updates.jsonl lines with `score_ratio` and the editor's `failed` flag).

    A call is *flagged* when its S is below the mean S of the training views at that update
    (`score_ratio` < 1: eq. 10 gives it a weight below 1). precision = failed among flagged, recall =
    flagged among failed (flagged_failed: the true positives); auc = P(S_failed < S_ok) over all (failed,
    ok) pairs (ties count 1/2): 0.5 is chance, 1 a perfect ranking. Scores are logged whenever an encoder
    is given, so rows without CCI have them too. Calls without a score or without a failure flag (a real
    editor) are left out.
    """
    rows = [(float(u["score_ratio"]), float(u["score"]), bool(u["editor"]["failed"])) for u in updates
            if u.get("score_ratio") is not None and isinstance(u.get("editor"), dict)
            and u["editor"].get("failed") is not None]
    n = len(rows)
    failed = [r for r in rows if r[2]]
    flagged = [r for r in rows if r[0] < 1.0]
    hits = sum(1 for r in flagged if r[2])
    ok_scores = np.array([r[1] for r in rows if not r[2]])
    bad_scores = np.array([r[1] for r in failed])
    auc = None
    if len(ok_scores) and len(bad_scores):
        less = (bad_scores[:, None] < ok_scores[None]).mean()
        ties = (bad_scores[:, None] == ok_scores[None]).mean()
        auc = float(less + 0.5 * ties)
    return {"calls": n, "failed": len(failed), "flagged": len(flagged), "flagged_failed": hits,
            "precision": hits / len(flagged) if flagged else None,
            "recall": hits / len(failed) if failed else None, "auc": auc}
