"""Where two camera files put the same sky direction on the sensor: the shift between them by distance from the centre.

    python scripts/camera_shift.py OLD.yaml NEW.yaml [--steps 8]

For directions along the lines from the sensor's centre to its corners, at growing angles from the boresight (the
same attitude for both), prints the distance from the sensor centre under NEW and how far OLD puts the same
direction from where NEW does (px; radial and across). Two fits of one lens that differ this much cannot both match
the stars: it says how far a star sits from one camera's prediction when the other camera is right
(results/real-frames/wide-lens).
"""

from __future__ import annotations

import argparse

import numpy as np

from skygen.config import load_config
from skygen.instrument.camera import Camera


def shifts(old: Camera, new: Camera, steps: int = 8) -> list[dict]:
    """Rows {r_px, shift_px, radial_px, across_px}, medians over the four diagonals, at ``steps`` distances from the
    centre to 95 % of the way to NEW's corner."""
    rows = []
    hw, hh = new.width_px / 2, new.height_px * new.aspect / 2  # centre to corner, in square pixels
    corner = np.hypot(hw, hh)
    for frac in np.linspace(1.0 / steps, 0.95, steps):
        got = []
        for sx, sy in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
            x, y = new.cx_px + sx * frac * hw, new.cy_px + sy * frac * hh / new.aspect
            v = new.unproject(np.array([x]), np.array([y]))
            xo, yo, _ = old.project(v)
            d = np.array([xo[0] - x, (yo[0] - y) * new.aspect])
            u = np.array([sx * hw, sy * hh]) / corner
            got.append((np.hypot(*d), d @ u, u[0] * d[1] - u[1] * d[0]))
        g = np.median(np.array(got), axis=0)
        rows.append({"r_px": float(frac * corner), "shift_px": g[0], "radial_px": g[1], "across_px": g[2]})
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("old")
    p.add_argument("new")
    p.add_argument("--steps", type=int, default=8)
    a = p.parse_args(argv)
    old, new = (Camera.from_config(load_config(f).camera) for f in (a.old, a.new))
    print(f"| distance from the centre (px, {a.new}) | OLD minus NEW: shift (px) | radial | across |")
    print("|---|---|---|---|")
    for r in shifts(old, new, a.steps):
        print(f"| {r['r_px']:.0f} | {r['shift_px']:.1f} | {r['radial_px']:+.1f} | {r['across_px']:+.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
