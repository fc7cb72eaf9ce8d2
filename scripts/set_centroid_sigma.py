"""Give a camera file that ``skygen fit-camera`` wrote before ``camera.centroid_sigma_px`` existed that key,
from its own fit record, without refitting (a refit with today's fit-camera also updates terms added since,
which would change what the results made with the file reproduce):

    python scripts/set_centroid_sigma.py CAMERA.yaml FIT.json

The value is what fit-camera now writes: the geometry fit's residual rms (``geometry.rms_px`` in the report's
``fit.json``, radial) divided by sqrt 2, per axis. The line goes after ``pixel_aspect`` in the camera section,
with a comment line saying where it came from; a file that has the key already is refused.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path


def main(argv=None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        print(__doc__.strip().splitlines()[3].strip(), file=sys.stderr)
        return 2
    cam, rec = Path(args[0]), Path(args[1])
    text = cam.read_text()
    if "centroid_sigma_px:" in text:
        print(f"{cam} has camera.centroid_sigma_px already", file=sys.stderr)
        return 1
    rms = float(json.loads(rec.read_text())["geometry"]["rms_px"])
    sigma = rms / math.sqrt(2.0)
    lines = text.splitlines(keepends=True)
    at = next((i for i, ln in enumerate(lines) if ln.startswith("  pixel_aspect:")), None)
    if at is None:
        print(f"{cam}: no camera.pixel_aspect line to put the key after", file=sys.stderr)
        return 1
    lines.insert(at + 1, f"  centroid_sigma_px: {sigma!r}\n")
    head = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    lines.insert(
        head,
        f"# camera.centroid_sigma_px added later from this fit's record ({rec}: {rms:.4f} px rms / sqrt 2): solvers "
        "take it as the least per-star centroid error of an attitude covariance "
        "(fusion.solve.base.attitude_covariance)\n",
    )
    cam.write_text("".join(lines))
    print(f"{cam}: camera.centroid_sigma_px = {sigma:.4f} px")
    return 0


if __name__ == "__main__":
    sys.exit(main())
