"""Classification and angular metrics on predictions (plain NumPy, no torch).

Angles in degrees. ``logits`` (N, K), ``labels`` and ``pred`` (N,) class indices,
``v`` (N, 3) true boresight unit vectors, ``centroids`` (K, 3) unit vectors.

Neighbouring clusters
    Two clusters are *neighbours* when their Voronoi cells on the sphere share a
    boundary arc, i.e. when their centroids are joined by an edge of the spherical
    Delaunay triangulation. That triangulation is the convex hull of the centroids
    (:class:`scipy.spatial.ConvexHull`), keeping only the hull faces whose plane has the
    sphere's centre on its inner side (a face with the centre outside spans an empty
    cap, not a Delaunay triangle). With fewer than 4 centroids, or centroids on one
    great circle, every pair counts as neighbours. An error is "between neighbours" when
    the predicted and true classes are neighbours.
"""

from __future__ import annotations

import numpy as np


def topk_accuracy(logits: np.ndarray, labels: np.ndarray, ks: tuple[int, ...] = (1, 3, 5)) -> dict[str, float]:
    """Share of samples whose label is among the k largest logits (k clipped to K; ties by index)."""
    logits, labels = np.asarray(logits), np.asarray(labels)
    if len(labels) == 0:
        return {f"top{k}": float("nan") for k in ks}
    order = np.argsort(-logits, axis=1, kind="stable")
    out = {}
    for k in ks:
        hit = (order[:, : min(k, logits.shape[1])] == labels[:, None]).any(axis=1)
        out[f"top{k}"] = float(hit.mean())
    return out


def angular_error_deg(v: np.ndarray, centroids: np.ndarray, cls: np.ndarray) -> np.ndarray:
    """arccos(v . c_cls) per sample, degrees."""
    cos = np.clip(np.sum(np.asarray(v, np.float64) * np.asarray(centroids, np.float64)[cls], axis=1), -1.0, 1.0)
    return np.degrees(np.arccos(cos))


def error_stats(err_deg: np.ndarray) -> dict[str, float]:
    if len(err_deg) == 0:
        return {"mean_deg": float("nan"), "median_deg": float("nan"), "p95_deg": float("nan")}
    return {
        "mean_deg": float(np.mean(err_deg)),
        "median_deg": float(np.median(err_deg)),
        "p95_deg": float(np.percentile(err_deg, 95)),
    }


def confusion_matrix(labels: np.ndarray, pred: np.ndarray, k: int) -> np.ndarray:
    """(K, K) counts; row = true class, column = predicted class."""
    cm = np.zeros((k, k), np.int64)
    np.add.at(cm, (np.asarray(labels, np.int64), np.asarray(pred, np.int64)), 1)
    return cm


def per_class_accuracy(cm: np.ndarray) -> list[dict]:
    """Per true class: number of samples and top-1 accuracy (None when the class has no sample)."""
    n = cm.sum(axis=1)
    return [
        {"class": int(c), "n": int(n[c]), "top1": (float(cm[c, c] / n[c]) if n[c] else None)} for c in range(len(cm))
    ]


def voronoi_neighbours(centroids: np.ndarray) -> np.ndarray:
    """(K, K) bool: clusters whose spherical Voronoi cells share a boundary (module docstring)."""
    c = np.asarray(centroids, np.float64)
    k = len(c)
    adj = np.ones((k, k), bool)
    np.fill_diagonal(adj, False)
    if k < 4:
        return adj
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = ConvexHull(c)
    except QhullError:
        return adj
    adj[:] = False
    for simplex, eq in zip(hull.simplices, hull.equations):
        if eq[3] > 0:  # plane offset: centre of the sphere lies outside this face
            continue
        for a in range(3):
            for b in range(a + 1, 3):
                adj[simplex[a], simplex[b]] = adj[simplex[b], simplex[a]] = True
    return adj


def neighbour_error_share(labels: np.ndarray, pred: np.ndarray, adjacency: np.ndarray) -> float | None:
    """Share of the misclassified samples whose predicted class neighbours the true one (None: no errors)."""
    labels, pred = np.asarray(labels), np.asarray(pred)
    wrong = labels != pred
    if not wrong.any():
        return None
    return float(adjacency[labels[wrong], pred[wrong]].mean())
