"""A sensor's defect map: pixels that give a detection in frame after frame wherever the camera points.

A hot pixel sits at the same place on the sensor while the stars move with the attitude, so a detection that no
catalogue star explains, at the same pixel (within ``radius_px``) in at least ``min_frames`` frames (pointings, where
the frames' attitudes are given: a staring camera's uncatalogued star stays put too), is a defect of the sensor and
not a star: flight star trackers keep such a map and drop its detections before identifying. skygen
renders hot pixels the same way (a static map seeded per sensor), and they are 4.5 % of the two brightest
detections of its default renders: with three detections, one of them a hot pixel, only two stars are left to
identify by, and a solver that does not know the pixel spends its identification on it.

:func:`learn` builds the map from detection tables whose detections are marked as explained or not (a
dataset's ``hip_id``, or the catalogue stars a solve matched); :func:`leave_one_out` gives each frame the map
learned from the *other* frames (the benchmark's ``--known-defects``: a frame's own detections never flag
themselves). :meth:`DefectMap.remove` drops the detections a map flags.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .base import Detections

DEFECT_RADIUS_PX = 1.0  # a detection this close to a mapped pixel is that pixel (centroids of a single hot pixel
#   scatter by a fraction of a pixel with the noise under them)
DEFECT_MIN_FRAMES = 3  # unexplained detections at one pixel in this many frames: a defect, not a coincidence
#   (two stars of frames at unrelated attitudes land within a pixel of each other rarely; three, far more rarely)
FIXED_SOURCE_SIGMAS = 3.0  # a camera file's fixed source flags detections within this many of its sigmas
DEFECT_REGION_PX = 8.0  # a defect region: unexplained detections of other frames crowd within this radius ...
DEFECT_REGION_P = 1e-6  # ... more than chance allows (Poisson, at this probability), from DEFECT_MIN_FRAMES pointings


def _cells(x: np.ndarray, y: np.ndarray) -> set:
    return {(int(round(a)), int(round(b))) for a, b in zip(np.asarray(x, float), np.asarray(y, float))}


@dataclass(frozen=True)
class DefectMap:
    """Pixel positions ``xy`` (K, 2) (skygen's pixel convention: x along columns) a detection within ``radius_px``
    of which is a sensor defect; and, where ``region_min`` > 0, **defect regions**: a detection with at least
    ``region_min`` of the learning frames' unexplained detections ``region_xy`` (M, 2) within ``region_px``,
    from at least ``region_pointings`` pointings (``region_pointing`` (M,)), is one too. A defect that does not
    sit on one pixel (a glow at the sensor's edge, whose detections wander by a few pixels from frame to frame)
    crowds unexplained detections far beyond their chance density; ``region_min`` is the least count whose
    chance is below :data:`DEFECT_REGION_P` at that density (:func:`region_threshold`)."""

    xy: np.ndarray
    radius_px: float = DEFECT_RADIUS_PX
    region_xy: np.ndarray | None = None
    region_pointing: np.ndarray | None = None
    region_px: float = DEFECT_REGION_PX
    region_min: int = 0
    region_pointings: int = DEFECT_MIN_FRAMES

    def __len__(self) -> int:
        return len(self.xy)

    def flags(self, det: Detections) -> np.ndarray:
        """(n,) bool: which of ``det`` the map flags."""
        out = np.zeros(len(det), bool)
        if not len(det):
            return out
        if len(self.xy):
            d2 = (det.x_px[:, None] - self.xy[None, :, 0]) ** 2 + (det.y_px[:, None] - self.xy[None, :, 1]) ** 2
            out |= np.any(d2 <= self.radius_px**2, axis=1)
        if self.region_min > 0 and self.region_xy is not None and len(self.region_xy):
            rx, ry = self.region_xy[:, 0], self.region_xy[:, 1]
            near = (det.x_px[:, None] - rx[None, :]) ** 2 + (det.y_px[:, None] - ry[None, :]) ** 2 <= self.region_px**2
            for k in np.flatnonzero(near.sum(axis=1) >= self.region_min):
                out[k] |= len(np.unique(self.region_pointing[near[k]])) >= self.region_pointings
        return out

    def remove(self, det: Detections) -> tuple[Detections, int]:
        """(``det`` without the flagged detections, brightest first as before; how many were dropped)."""
        bad = self.flags(det)
        if not bad.any():
            return det, 0
        keep = ~bad
        return det.take(keep), int(bad.sum())

    @classmethod
    def from_fixed_sources(cls, sources, sigmas: float = FIXED_SOURCE_SIGMAS) -> "DefectMap":
        """The map of a camera file's ``sensor.fixed_sources`` ([x, y, e-/s, sigma_px] each: light fixed on the sensor):
        a detection within ``sigmas`` times the widest source's sigma (at least :data:`DEFECT_REGION_PX`, the distance
        a glow's detections wander by) of a source's centre is that source."""
        xy = np.asarray([[q[0], q[1]] for q in sources], np.float64).reshape(-1, 2)
        width = max((float(q[3]) for q in sources), default=0.0)
        return cls(xy, radius_px=max(sigmas * width, DEFECT_REGION_PX))

    def to_json(self, path) -> None:
        data = {"radius_px": self.radius_px, "pixels_xy": np.round(self.xy, 2).tolist()}
        if self.region_min > 0 and self.region_xy is not None:
            data["regions"] = {
                "radius_px": self.region_px,
                "min_detections": int(self.region_min),
                "min_pointings": int(self.region_pointings),
                "detections_xy": np.round(self.region_xy, 2).tolist(),
                "pointing": np.asarray(self.region_pointing, int).tolist(),
            }
        Path(path).write_text(json.dumps(data) + "\n")

    @classmethod
    def from_json(cls, path) -> "DefectMap":
        from ..errors import ConfigError

        try:
            text = Path(path).read_text()
        except OSError as exc:
            raise ConfigError(f"--defects {path}: cannot read the defect map ({exc.strerror or exc})") from None
        try:
            data = json.loads(text)
            xy = np.asarray(data["pixels_xy"], np.float64).reshape(-1, 2)
            radius = float(data.get("radius_px", DEFECT_RADIUS_PX))
            reg = data.get("regions")
            kw = {}
            if reg is not None:
                kw = {
                    "region_xy": np.asarray(reg["detections_xy"], np.float64).reshape(-1, 2),
                    "region_pointing": np.asarray(reg["pointing"], np.int64).reshape(-1),
                    "region_px": float(reg["radius_px"]),
                    "region_min": int(reg["min_detections"]),
                    "region_pointings": int(reg["min_pointings"]),
                }
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ConfigError(
                f"{path}: not a defect map ({exc}); expected JSON {{'radius_px': 1.0, 'pixels_xy': [[x, y], ...]}} "
                "(and optionally 'regions': {'radius_px', 'min_detections', 'min_pointings', 'detections_xy', "
                "'pointing'})"
            ) from None
        if not (np.all(np.isfinite(xy)) and np.isfinite(radius) and radius > 0):
            raise ConfigError(f"{path}: a defect map needs finite pixel positions and a positive radius_px")
        if kw and not (
            np.all(np.isfinite(kw["region_xy"]))
            and len(kw["region_pointing"]) == len(kw["region_xy"])
            and kw["region_px"] > 0
            and kw["region_min"] >= 1
        ):
            raise ConfigError(f"{path}: a defect map's regions need finite positions, one pointing each, a positive "
                              "radius_px and min_detections >= 1")  # fmt: skip
        return cls(xy, radius, **kw)


DEFECT_MIN_APART_DEG = 0.5  # frames whose boresights are closer than this count as one pointing: a staring
#   camera keeps an uncatalogued star on one pixel, and only a pixel that stays lit while the sky moves is a defect
_NEAR = [(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)]  # a centroid near a pixel's edge rounds either way


def _pointings(n: int, boresights) -> list[int]:
    """Each frame's pointing: frames within DEFECT_MIN_APART_DEG of an earlier one share its number (greedy);
    without boresights every frame is its own."""
    if boresights is None:
        return list(range(n))
    cos_apart = np.cos(np.radians(DEFECT_MIN_APART_DEG))
    reps: list = []
    ids = []
    for v in np.asarray(boresights, np.float64).reshape(-1, 3):
        k = next((k for k, w in enumerate(reps) if float(v @ w) >= cos_apart), None)
        if k is None:
            reps.append(v)
            k = len(reps) - 1
        ids.append(k)
    return ids


def _lit(tables) -> dict:
    """integer pixel cell -> the frames holding a detection no catalogue star explains there. ``tables``:
    (x_px, y_px, explained) per frame."""
    lit: dict = {}
    for f, (x, y, e) in enumerate(tables):
        bad = ~np.asarray(e, bool)
        for c in _cells(np.asarray(x)[bad], np.asarray(y)[bad]):
            lit.setdefault(c, set()).add(f)
    return lit


def _map(lit: dict, pointing: list, min_frames: int, radius_px: float, cells, leave_out: int | None = None):
    """The map of ``cells`` (of ``lit``) lit at ``min_frames`` pointings or more within one pixel, frame
    ``leave_out`` not counted; each defect once, at its most often lit cell."""
    hits = []
    for cx, cy in cells:
        near = [lit.get((cx + a, cy + b), set()) for a, b in _NEAR]
        frames = set().union(*near) - {leave_out}
        if len({pointing[f] for f in frames}) < min_frames:
            continue
        own = len(lit.get((cx, cy), set()) - {leave_out})
        if own == 0 or any(len(n - {leave_out}) > own for n in near):
            continue
        hits.append((cx, cy))
    return DefectMap(np.asarray(sorted(hits), np.float64).reshape(-1, 2), radius_px)


def region_threshold(count: int, area_px2: float, radius_px: float = DEFECT_REGION_PX, p: float = DEFECT_REGION_P):
    """The least number of ``count`` unexplained detections spread at random over ``area_px2`` that falls within
    ``radius_px`` of a point with a Poisson chance below ``p``: a crowd that many is no coincidence."""
    from scipy.stats import poisson

    lam = count * math.pi * radius_px**2 / max(area_px2, 1.0)
    k = 1
    while poisson.sf(k - 1, lam) >= p:
        k += 1
    return k


def _unexplained(tables, pointing: list) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """(xy (M, 2), pointing (M,), frame (M,)) of every unexplained detection, and the area they are spread over
    (the detections' bounding box: the sensor, as far as the frames show it)."""
    xy, pt, fr, allx, ally = [], [], [], [], []
    for f, (x, y, e) in enumerate(tables):
        x, y, bad = np.asarray(x, float), np.asarray(y, float), ~np.asarray(e, bool)
        allx.append(x)
        ally.append(y)
        xy.append(np.column_stack([x[bad], y[bad]]))
        pt.append(np.full(int(bad.sum()), pointing[f]))
        fr.append(np.full(int(bad.sum()), f))
    ax, ay = np.concatenate(allx) if allx else np.zeros(0), np.concatenate(ally) if ally else np.zeros(0)
    area = float((np.ptp(ax) + 1) * (np.ptp(ay) + 1)) if len(ax) else 1.0
    cat = np.concatenate(xy) if xy else np.zeros((0, 2))
    return cat.reshape(-1, 2), np.concatenate(pt).astype(np.int64), np.concatenate(fr).astype(np.int64), area


def _with_regions(dmap: DefectMap, xy, pt, area: float, min_frames: int) -> DefectMap:
    import dataclasses

    return dataclasses.replace(
        dmap,
        region_xy=xy,
        region_pointing=pt,
        region_min=region_threshold(len(xy), area),
        region_pointings=min_frames,
    )


def learn(
    tables, min_frames: int = DEFECT_MIN_FRAMES, radius_px: float = DEFECT_RADIUS_PX, boresights=None
) -> DefectMap:
    """The defect map of frames ``tables`` = [(x_px, y_px, explained), ...]: integer pixels (with their
    neighbours) holding an unexplained detection in at least ``min_frames`` frames, and the frames' unexplained
    detections for the defect regions (:class:`DefectMap`). ``boresights`` (one unit vector per frame,
    optional): frames within :data:`DEFECT_MIN_APART_DEG` of each other count once."""
    lit = _lit(tables)
    pointing = _pointings(len(tables), boresights)
    xy, pt, _, area = _unexplained(tables, pointing)
    return _with_regions(_map(lit, pointing, min_frames, radius_px, list(lit)), xy, pt, area, min_frames)


def leave_one_out(
    tables, min_frames: int = DEFECT_MIN_FRAMES, radius_px: float = DEFECT_RADIUS_PX, boresights=None
) -> list[DefectMap]:
    """One map per frame of ``tables``, each learned from the other frames only (``boresights``: as
    :func:`learn`'s)."""
    lit = _lit(tables)
    pointing = _pointings(len(tables), boresights)
    # a cell that does not qualify with every frame counted cannot qualify with one left out
    candidates = [c for c in lit if _reaches(lit, c, pointing, min_frames)]
    xy, pt, fr, area = _unexplained(tables, pointing)
    maps = []
    for j in range(len(tables)):
        other = fr != j
        maps.append(
            _with_regions(
                _map(lit, pointing, min_frames, radius_px, candidates, j), xy[other], pt[other], area, min_frames
            )
        )
    return maps


def _reaches(lit: dict, c, pointing: list, min_frames: int) -> bool:
    frames = set().union(*(lit.get((c[0] + a, c[1] + b), ()) for a, b in _NEAR))
    return len({pointing[f] for f in frames}) >= min_frames


def from_dataset_tables(tables: list[dict]) -> list[tuple]:
    """(x_px, y_px, explained) of a skygen dataset's detection tables: explained = the detection is a rendered
    catalogue star (``hip_id`` >= 0; hot pixels, cosmic rays and false stars carry -1)."""
    return [(t["x_px"], t["y_px"], np.asarray(t["hip_id"]) >= 0) for t in tables]


def from_predictions(path) -> tuple[list[tuple], list, int]:
    """((x_px, y_px, explained) per solved frame, their boresight unit vectors, frames skipped) of a ``fusion
    predict --solve`` JSON-lines file: explained = the detection row is among the solution's matched stars.
    Frames without a solution are skipped (their detections cannot be told from stars)."""
    from skygen.sky.attitude import quaternion_to_matrix

    from ..errors import ConfigError

    tables, boresights, skipped = [], [], 0
    try:
        lines = Path(path).read_text().splitlines()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the predictions ({exc.strerror or exc})") from None
    for k, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
            det = np.asarray(rec.get("detections") or [], np.float64).reshape(-1, 3)
            sol = rec.get("solution") or {}
        except (ValueError, TypeError, AttributeError) as exc:
            raise ConfigError(
                f"{path}, line {k}: not a fusion predict record ({exc}); give the JSON lines of fusion predict --solve"
            ) from None
        if sol.get("status") != "solved":
            skipped += 1
            continue
        explained = np.zeros(len(det), bool)
        rows = np.asarray(sol.get("matched") or [], np.int64).reshape(-1, 2)[:, 0]
        explained[rows[(rows >= 0) & (rows < len(det))]] = True
        tables.append((det[:, 0], det[:, 1], explained))
        boresights.append(quaternion_to_matrix(np.asarray(sol["quaternion_wxyz"], np.float64))[:, 2])
    return tables, boresights, skipped


def learn_command(predictions, out, min_frames: int = DEFECT_MIN_FRAMES, radius_px: float = DEFECT_RADIUS_PX) -> str:
    """``fusion defects``: learn a defect map from predictions and write it to ``out``; returns the summary line."""
    from skygen.runtime import atomic_path

    from ..errors import ConfigError

    if min_frames < 2:
        raise ConfigError(f"--min-frames {min_frames}: at least 2 (one frame cannot tell a defect from a star)")
    if not radius_px > 0:
        raise ConfigError(f"--radius-px {radius_px:g}: a positive radius in pixels, e.g. 1")
    tables, boresights, skipped = [], [], 0
    for p in predictions:
        t, b, s = from_predictions(p)
        tables += t
        boresights += b
        skipped += s
    if len(tables) < min_frames:
        raise ConfigError(
            f"{len(tables)} solved frame(s) in {', '.join(map(str, predictions))}: a defect recurs in "
            f"{min_frames} frames at least; solve more frames (fusion predict --solve) or lower --min-frames"
        )
    dmap = learn(tables, min_frames, radius_px, boresights)
    with atomic_path(out) as tmp:
        dmap.to_json(tmp)
    return (
        f"fusion defects: {len(dmap)} defect pixel(s) from {len(tables)} solved frames "
        f"({skipped} unsolved skipped; unmatched detections recurring within {radius_px:g} px at {min_frames}+ "
        f"pointings {DEFECT_MIN_APART_DEG:g} deg apart), and regions where {dmap.region_min}+ of their "
        f"{len(dmap.region_xy)} unmatched detections crowd within {dmap.region_px:g} px -> {out}"
    )
