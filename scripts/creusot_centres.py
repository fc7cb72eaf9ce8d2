"""Check fit-camera's attitudes of the creusot-16mm frames against upstream's own plate solutions.

    python scripts/creusot_centres.py [--fit results/real-frames/fit-camera-creusot-16mm/fit.json]

Upstream (TomCreusot/Star_Tracker_Microcontroller) solved each frame with astrometry.net and wrote the image
centre (RA/Dec to 0.001 deg) and a field of view into ``real-frames/creusot-16mm/astrometry/NAME.log.json``.
Prints, per frame, the angle between that centre and the boresight ``skygen fit-camera`` fitted, and upstream's
field beside the fitted camera's diagonal field (the upstream value matches a diagonal, not a horizontal, field).
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def unit(ra_deg: float, dec_deg: float) -> np.ndarray:
    ra, dec = np.radians(ra_deg), np.radians(dec_deg)
    return np.array([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)])


def upstream(name: str) -> tuple[float, float, float]:
    """(ra, dec, fov) from upstream's log.json (read with a regex: one of the files is not valid JSON)."""
    text = (ROOT / "real-frames" / "creusot-16mm" / "astrometry" / f"{name}.log.json").read_text()
    get = lambda key: float(re.search(rf'"{key}"\s*:\s*([-\d.]+)', text).group(1))  # noqa: E731
    return get("ra_degrees"), get("dec_degrees"), get("fov_deg")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--fit", default=str(ROOT / "results/real-frames/fit-camera-creusot-16mm/fit.json"))
    a = p.parse_args(argv)
    fit = json.loads(Path(a.fit).read_text())
    g = fit["geometry"]
    w, h = fit["config"]["camera"]["width_px"], fit["config"]["camera"]["height_px"]
    diag = np.degrees(2 * np.arctan(np.hypot(w, h * g["aspect"]) / 2 / g["f_px"]))
    print(f"fitted field {g['fov_deg']:.4f} x {g['fov_v_deg']:.4f} deg; pinhole diagonal {diag:.3f} deg\n")
    print("| frame | fitted boresight vs upstream centre (arcmin) | upstream fov_deg |")
    print("|---|---|---|")
    seps = []
    for f in fit["solved"]:
        name = Path(f["frame"]).stem
        ra, dec, fov = upstream(name)
        sep = np.degrees(np.arccos(np.clip(unit(ra, dec) @ unit(f["ra_deg"], f["dec_deg"]), -1, 1))) * 60
        seps.append(sep)
        print(f"| {name} | {sep:.2f} | {fov:.3f} |")
    print(f"\nlargest {max(seps):.2f} arcmin, median {np.median(seps):.2f} arcmin over {len(seps)} frames")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
