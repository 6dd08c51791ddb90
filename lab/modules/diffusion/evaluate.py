"""How good the samples are: distances to held-out points (Chamfer, MMD); for digits a classifier's verdict.

:func:`evaluate_sample` runs after the ``sample`` step; its truth holds the held-out data of the dataset.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def chamfer_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric Chamfer distance of point sets ``(N, D)`` and ``(M, D)``: mean nearest-neighbour
    distance from a to b plus from b to a (``scipy.spatial.cKDTree`` queries)."""
    from scipy.spatial import cKDTree

    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return float(cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean())


def mmd_rbf(a: np.ndarray, b: np.ndarray, *, bandwidth: float | None = None, max_points: int = 1000,
            seed: int = 0) -> float:
    """Maximum mean discrepancy with a Gaussian kernel (Gretton et al. 2012, biased estimate, square root).

    ``k(x, y) = exp(-|x - y|^2 / (2 h^2))``, ``h`` the median pairwise distance of ``b`` unless
    given; at most ``max_points`` of each set (a fixed random subset).
    """
    rng = np.random.default_rng(seed)
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    a = a[rng.permutation(len(a))[:max_points]]
    b = b[rng.permutation(len(b))[:max_points]]

    def sq(p: np.ndarray, q: np.ndarray) -> np.ndarray:
        return np.maximum((p ** 2).sum(1)[:, None] + (q ** 2).sum(1)[None] - 2 * p @ q.T, 0.0)

    bb = sq(b, b)
    h = bandwidth if bandwidth is not None else float(np.sqrt(np.median(bb[np.triu_indices(len(b), 1)])))

    def k(d: np.ndarray) -> np.ndarray:
        return np.exp(-d / (2 * h * h))

    value = k(sq(a, a)).mean() + k(bb).mean() - 2 * k(sq(a, b)).mean()
    return float(np.sqrt(max(value, 0.0)))


def train_digit_classifier(x: np.ndarray, labels: np.ndarray) -> Any:
    """A small classifier of 8 x 8 digits ``(N, 64)`` in [0, 1]: multinomial logistic regression
    (``sklearn.linear_model.LogisticRegression``), about 96 % accurate on held-out digits."""
    from sklearn.linear_model import LogisticRegression

    return LogisticRegression(max_iter=2000, C=1.0).fit(np.asarray(x), np.asarray(labels))


def diversity_score(x: np.ndarray, reference: np.ndarray, *, max_points: int = 500) -> float:
    """Mean pairwise distance of samples ``(N, D)`` over that of reference data.

    1: as diverse as the data; 0: every sample the same.
    """
    def mean_pairwise(p: np.ndarray) -> float:
        p = np.asarray(p, dtype=np.float64)[:max_points]
        d = np.sqrt(np.maximum((p ** 2).sum(1)[:, None] + (p ** 2).sum(1)[None] - 2 * p @ p.T, 0))
        return float(d[np.triu_indices(len(p), 1)].mean()) if len(p) > 1 else 0.0

    return mean_pairwise(x) / max(mean_pairwise(reference), 1e-12)


def digit_metrics(generated: np.ndarray, labels: np.ndarray, truth: dict[str, Any]) -> dict[str, float]:
    """``digit_accuracy``: how often the module's classifier agrees with the requested class (-1 labels
    skipped); ``diversity``: :func:`diversity_score` within each requested class against the held-out
    digits of that class, averaged (without labels: over all samples). Guidance trades one for the other."""
    generated = np.asarray(generated, dtype=np.float64)
    labels = np.asarray(labels)
    held = np.asarray(truth["held_out"])
    held_labels = truth.get("held_out_labels")
    asked = labels >= 0
    metrics: dict[str, float] = {}
    if asked.any() and held_labels is not None:
        scores = [diversity_score(generated[labels == c], held[np.asarray(held_labels) == c])
                  for c in np.unique(labels[asked])
                  if np.sum(labels == c) > 1 and np.sum(held_labels == c) > 1]
        metrics["diversity"] = float(np.mean(scores)) if scores else 0.0
    else:
        metrics["diversity"] = diversity_score(generated, held)
    if asked.any() and "classifier" in truth:
        predicted = truth["classifier"].predict(generated[asked])
        metrics["digit_accuracy"] = float(np.mean(predicted == labels[asked]))
    return metrics


def evaluate_sample(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Points: Chamfer distance and MMD of the samples to held-out points; digits: accuracy and diversity."""
    if "held_out" not in truth:
        return {}
    data = state["training_data"]
    generated = np.asarray(state["generated"])
    if data.kind == "digits":
        return digit_metrics(generated, state["generated_labels"], truth)
    held = np.asarray(truth["held_out"])
    return {"chamfer": chamfer_distance(generated, held), "mmd": mmd_rbf(generated, held)}


__all__ = ["chamfer_distance", "digit_metrics", "diversity_score", "evaluate_sample", "mmd_rbf",
           "train_digit_classifier"]
