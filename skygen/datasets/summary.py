"""``skygen inspect``: what a dataset holds, at a glance."""

from __future__ import annotations

import json

import numpy as np

from skygen.datasets.shards import SPLIT_NAMES, open_dataset


def _hist_line(values: np.ndarray, edges: list[int]) -> str:
    counts, _ = np.histogram(values, bins=edges + [10**9])
    labels = [f"{a}-{b - 1}" if b - a > 1 else f"{a}" for a, b in zip(edges, edges[1:])] + [f">={edges[-1]}"]
    return "  ".join(f"{lab}:{c}" for lab, c in zip(labels, counts))


def summarize(path) -> dict:
    with open_dataset(path) as ds:
        fr, cfg, man = ds.frames, ds.config, ds.manifest
        matched = []
        for i in np.linspace(0, len(ds) - 1, min(len(ds), 200)).astype(int):
            d = ds.detections(int(i))
            matched.append((len(d["hip_id"]), int((d["hip_id"] >= 0).sum())))
        matched = np.array(matched)
        ns, nd = fr["n_stars"], fr["n_detections"]
        return {
            "path": str(path),
            "frames": len(ds),
            "shards": len(ds.shards),
            "splits": {s: int((fr["split"] == k).sum()) for k, s in enumerate(SPLIT_NAMES)},
            "schema_version": ds.schema_version,
            "dataset_id": man.get("dataset_id"),
            "seed": cfg["seed"],
            "sensor": list(ds.sensor_shape),
            "stored_image": list(ds.image_shape),
            "detection_limit_mag": man.get("detection_limit_mag"),
            "mag_limit": man.get("mag_limit"),
            "stars_per_frame": {
                "mean": float(ns.mean()),
                "median": float(np.median(ns)),
                "p10": float(np.percentile(ns, 10)),
                "p90": float(np.percentile(ns, 90)),
            },
            "detections_per_frame": {
                "mean": float(nd.mean()),
                "median": float(np.median(nd)),
                "p10": float(np.percentile(nd, 10)),
                "p90": float(np.percentile(nd, 90)),
                "fewer_than_2": int((nd < 2).sum()),
            },
            "matched_fraction_of_detections": float(matched[:, 1].sum() / max(matched[:, 0].sum(), 1)),
            "background_adu_median": float(np.median(fr["background_adu"])),
            "noise_adu_median": float(np.median(fr["noise_adu"])),
            "corruptions": cfg["corruptions"],
            "_ns": ns,
            "_nd": nd,
        }


def inspect_dataset(path, as_json: bool = False) -> str:
    s = summarize(path)
    ns, nd = s.pop("_ns"), s.pop("_nd")
    if as_json:
        return json.dumps(s, indent=1)
    edges = [0, 2, 5, 10, 20, 30, 50, 100]
    lines = [
        f"dataset      {s['path']}  (id {s['dataset_id']}, schema {s['schema_version']}, seed {s['seed']})",
        f"frames       {s['frames']} in {s['shards']} shard(s); "
        + ", ".join(f"{k} {v}" for k, v in s["splits"].items()),
        f"sensor       {s['sensor'][1]}x{s['sensor'][0]} px, stored {s['stored_image'][1]}x{s['stored_image'][0]}",
        f"magnitudes   detection limit Hp {s['detection_limit_mag']}, rendered to Hp {s['mag_limit']}",
        f"true stars   per frame: median {s['stars_per_frame']['median']:.0f}, p10-p90 "
        f"{s['stars_per_frame']['p10']:.0f}-{s['stars_per_frame']['p90']:.0f}",
        f"             {_hist_line(ns, edges)}",
        f"detections   per frame: median {s['detections_per_frame']['median']:.0f}, p10-p90 "
        f"{s['detections_per_frame']['p10']:.0f}-{s['detections_per_frame']['p90']:.0f}; "
        f"frames with < 2: {s['detections_per_frame']['fewer_than_2']}",
        f"             {_hist_line(nd, edges)}",
        f"matching     {100 * s['matched_fraction_of_detections']:.1f}% of detections are catalog stars",
        f"background   median {s['background_adu_median']:.1f} ADU, noise {s['noise_adu_median']:.2f} ADU",
        "corruptions  " + ", ".join(f"{k}={v:g}" for k, v in s["corruptions"].items() if v) or "none",
    ]
    return "\n".join(lines)
