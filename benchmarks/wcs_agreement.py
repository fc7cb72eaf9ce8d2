"""Does the real-frame truth agree with another plate solver? Our all-detection solve against a FITS WCS per frame.

    python benchmarks/wcs_agreement.py FRAMES... --camera CAMERA.yaml --wcs-dir DIR [--flip-y] --out OUT.md

``benchmarks/real_few_star.py`` takes each frame's all-detection tetra3rs solve, through the camera file, as the
frame's truth. Where the frames come with another solver's plate solutions (astrometry.net's or ASTAP's ``.wcs``
files: a FITS header per frame, named after the frame), this checks that truth: every frame is detected and solved
as real_few_star.py does it, then a 5 x 5 grid of pixels across the frame is put on the sky by both, our attitude
and camera model and the WCS (:mod:`skygen.real.wcs`, its SIP terms included where present); the table gives the angle
between the two directions (arcsec: median and largest over the grid), the boresight offset and the roll
difference (the sky position angle of the frame's +x axis). ``--flip-y``: the WCS counts rows from the bottom
(a solver that read the image bottom-up).

Writes OUT (Markdown) and prints it.
"""

from __future__ import annotations

import argparse
import platform
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def position_angle_deg(v0: np.ndarray, v1: np.ndarray) -> float:
    """Position angle (deg, east of north) of direction v1 seen from v0."""
    north = np.array([0.0, 0.0, 1.0]) - v0[2] * v0
    north /= np.linalg.norm(north)
    east = np.cross(north, v0)
    d = v1 - v0
    return float(np.degrees(np.arctan2(d @ east, d @ north)))


def run(frames: list, camera: str, wcs_dir: Path, flip_y: bool, log=print) -> dict:
    from real_few_star import load_frames

    from fusion.solve.base import Solution
    from fusion.solve.predict import Predictor
    from fusion.solve.registry import make_context
    from skygen.real.wcs import angle_arcsec, read_wcs, wcs_directions

    pred = Predictor(None, camera=camera)
    cam = pred.camera
    ctx = make_context(cam)
    gx, gy = np.meshgrid(np.linspace(0, cam.width_px - 1, 5), np.linspace(0, cam.height_px - 1, 5))
    gx, gy = gx.ravel(), gy.ravel()
    centre = int(np.argmin(np.hypot(gx - (cam.width_px - 1) / 2, gy - (cam.height_px - 1) / 2)))
    right = np.array([min(cam.width_px - 1, (cam.width_px - 1) / 2 + cam.width_px / 4)])
    rows = []
    for name, img, _ in load_frames(frames):
        stem = Path(name).stem
        header = next((p for p in (wcs_dir / f"{stem}.wcs", wcs_dir / f"{stem}.fits") if p.is_file()), None)
        row = {"frame": Path(name).name}
        if img is None or header is None:
            row["result"] = "unreadable frame" if img is None else "no WCS file"
            rows.append(row)
            continue
        det, _, _ = pred.detect(img)
        sol = ctx.tetra.solve(det, cam)
        if not isinstance(sol, Solution):
            row["result"] = f"not solved ({sol.status})"
            rows.append(row)
            continue
        ours = cam.unproject(gx, gy) @ sol.matrix.T
        w = read_wcs(header)
        theirs = wcs_directions(w, gx, gy, cam.height_px if flip_y else None)
        off = angle_arcsec(ours, theirs)
        y_mid = np.array([(cam.height_px - 1) / 2])
        r_ours = (cam.unproject(right, y_mid) @ sol.matrix.T)[0]
        r_theirs = wcs_directions(w, right, y_mid, cam.height_px if flip_y else None)[0]
        d_roll = position_angle_deg(ours[centre], r_ours) - position_angle_deg(theirs[centre], r_theirs)
        row.update(
            result="solved",
            matched=int(sol.n_matched),
            median_arcsec=float(np.median(off)),
            max_arcsec=float(off.max()),
            boresight_arcsec=float(off[centre]),
            roll_deg=float((d_roll + 180.0) % 360.0 - 180.0),
        )
        rows.append(row)
    return {"camera": camera, "wcs_dir": str(wcs_dir), "flip_y": flip_y, "rows": rows, "camera_model": cam}


def markdown(res: dict, command: str) -> str:
    from skygen.runtime import hardware_line

    cam = res["camera_model"]
    px = np.degrees(1.0 / cam.f_px) * 3600.0
    out = [
        f'Our all-detection tetra3rs solve through `{res["camera"]}` ({px:.2f}"/px) against the WCS files in '
        f"`{res['wcs_dir']}`{' (rows counted from the bottom)' if res['flip_y'] else ''}: a 5 x 5 grid of pixels put "
        "on the sky by both.",
        "",
        "| frame | ours | matched | grid offset median / max (arcsec) | boresight (arcsec) | roll (deg) |",
        "|---|---|---|---|---|---|",
    ]
    solved = [r for r in res["rows"] if r["result"] == "solved"]
    for r in res["rows"]:
        if r["result"] != "solved":
            out.append(f"| {r['frame']} | {r['result']} | – | – | – | – |")
            continue
        out.append(
            f"| {r['frame']} | solved | {r['matched']} | {r['median_arcsec']:.1f} / {r['max_arcsec']:.1f} | "
            f"{r['boresight_arcsec']:.1f} | {r['roll_deg']:+.3f} |"
        )
    if solved:
        worst = max(r["max_arcsec"] for r in solved)
        out += [
            "",
            f'{len(solved)} of {len(res["rows"])} frames solved; over them the grid offset is at most {worst:.1f}" '
            f"({worst / px:.2f} px), the roll difference at most {max(abs(r['roll_deg']) for r in solved):.3f} deg.",
        ]
    out += [
        "",
        f"Command: `{command}`",
        f"Hardware: {hardware_line()}, python {platform.python_version()} (no timing).",
    ]
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("frames", nargs="+", help="frame files or folders of them")
    ap.add_argument("--camera", required=True, help="the camera YAML (skygen fit-camera's)")
    ap.add_argument("--wcs-dir", required=True, type=Path, help="folder of FRAME_STEM.wcs (or .fits) WCS headers")
    ap.add_argument("--flip-y", action="store_true", help="the WCS counts pixel rows from the bottom")
    ap.add_argument("--out", required=True, type=Path, help="Markdown file to write")
    args = ap.parse_args(argv)
    if not args.wcs_dir.is_dir():
        ap.error(f"--wcs-dir {args.wcs_dir}: not a folder")
    res = run(args.frames, args.camera, args.wcs_dir, args.flip_y)
    command = "python benchmarks/wcs_agreement.py " + " ".join(argv if argv is not None else sys.argv[1:])
    text = markdown(res, command)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
