"""Trace one fine-stage (whole-sky) solve: each decision, refinement and tetra3rs confirmation, against the truth.

    python benchmarks/fine_trace.py --frame FILE --camera CAMERA.yaml --n 8        # a real frame's brightest N
    python benchmarks/fine_trace.py --adversarial-case 42251                        # one adversarial_calibration case
    python benchmarks/fine_trace.py --camera CAMERA.yaml --order-q                   # the brightness order's chance q

A real frame's truth is its all-detection tetra3rs solve, where beyond doubt (``real_few_star.py``'s rule); an
adversarial case's is the attitude it was drawn at (``benchmarks/adversarial_calibration.py``, seed 0, its default
families and N range). Printed per event:
- ``decide``: hypotheses so far, the best score and focal factor, its angle to the truth, the verdict;
- ``refine``: the free scale's fit and the camera's own (k = 1): matched detections, scale, angle to the truth;
- ``confirm``: tetra3rs's tracking answer: stars matched, rms (px), how far it turns ours, and the largest offset
  (px) it leaves on any of our matched stars;
then the answer. A diagnostic: it wraps the solver's methods, and prints; it changes no answer.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _instrument(solver, cam, truth) -> None:
    import fusion.solve.fine as fine
    from fusion.solve.base import Solution, rotation_angle_deg

    cls = type(solver)
    decide, refine, finish = cls._decide, cls.refine, cls._finish
    state: dict = {}

    def _decide(self, tier, rots, ks, scores, tried, u, flux):
        v = decide(self, tier, rots, ks, scores, tried, u, flux)
        b = int(np.argmax(scores))
        verdict = f"accept #{v}" if isinstance(v, int) else v.reason
        print(
            f"decide  H={tried} best {scores[b]}/{len(u)} k={ks[b]:.4f} "
            f"{rotation_angle_deg(rots[b], truth):.3f} deg from the truth: {verdict}"
        )
        return v

    def _refine(self, tier, rot, k, u, s, iterations=20):
        for label, scale, k0 in (("free scale", s, k), ("own scale", 0.0, 1.0)):
            r = self._refine(tier, rot, k0, u, scale, iterations)
            print(
                f"refine  {label}: {len(r[2])}/{len(u)} matched {r[2].tolist()}, k={r[1]:.4f}, "
                f"{rotation_angle_deg(r[0], truth):.3f} deg from the truth"
            )
        out = refine(self, tier, rot, k, u, s, iterations)
        state.update(tier=tier, uk=out[4], det=out[2], cat=out[3])
        print(f"refine  kept: {len(out[2])} matched, k={out[1]:.4f}, scale fitted: {out[5]}")
        return out

    tetra_hint = solver.tetra.solve_with_hint

    def _hint(det, camera, rot, unc, **kw):
        res = tetra_hint(det, camera, rot, unc, **kw)
        if isinstance(res, Solution) and state:
            v = state["uk"][state["det"]] @ np.asarray(res.matrix).T
            cos = np.clip(np.sum(v * state["tier"].vec[state["cat"]], axis=1), -1, 1)
            off = np.degrees(np.arccos(cos)) * 3600 / camera.pixel_scale_arcsec
            rms = res.residual_arcsec / camera.pixel_scale_arcsec
            print(
                f"confirm tetra3rs: {res.n_matched} stars, {rms:.2f} px rms, "
                f"turns ours {rotation_angle_deg(res.matrix, rot):.3f} deg, our stars up to {off.max():.2f} px off "
                f"(disagrees beyond {fine.DISAGREE_FACTOR:g} x {self_tol(solver, camera):.2f} px)"
            )
        elif not isinstance(res, Solution):
            print(f"confirm tetra3rs refused: {res.reason}")
        return res

    def _finish(self, *a, **kw):
        r = finish(self, *a, **kw)
        print(f"finish  -> {'answer' if isinstance(r, Solution) else r.reason}")
        return r

    solver._decide = _decide.__get__(solver)
    solver.refine = _refine.__get__(solver)
    solver._finish = _finish.__get__(solver)
    solver.tetra.solve_with_hint = _hint


def self_tol(solver, camera) -> float:
    return float(np.degrees(solver.tol_rad) * 3600 / camera.pixel_scale_arcsec)


def main(argv=None) -> int:
    from fusion.solve.base import Solution, rotation_angle_deg
    from fusion.solve.registry import build_solver, make_context

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frame")
    p.add_argument("--camera")
    p.add_argument("--n", type=int, default=8)
    p.add_argument("--adversarial-case", type=int)
    p.add_argument(
        "--order-q",
        action="store_true",
        help="with --camera alone: the brightness order's chance q for 3-8 matched stars on that camera, and exit",
    )
    a = p.parse_args(argv)
    if a.order_q:
        from fusion.solve.predict import Predictor

        if a.camera is None:
            raise SystemExit("--order-q needs --camera CAMERA.yaml")
        cam = Predictor(None, camera=a.camera).camera
        solver = build_solver("whole-sky", cam, context=make_context(cam, prior=None))
        print(f"{a.camera}: brightness order's chance q (CoarseToFineSolver._order_q) by matched stars")
        print("| s | " + " | ".join(str(s) for s in range(3, 9)) + " |")
        print("|---|" + "---|" * 6)
        print("| q | " + " | ".join(f"{solver._order_q(s):.2g}" for s in range(3, 9)) + " |")
        return 0
    if (a.frame is None) == (a.adversarial_case is None) or (a.frame is not None and a.camera is None):
        raise SystemExit("give --frame FILE --camera CAMERA.yaml, or --adversarial-case I")
    if a.frame is not None:
        from real_few_star import all_detection_truth, load_frames

        from fusion.solve.predict import Predictor

        pred = Predictor(None, camera=a.camera)
        cam = pred.camera
        ctx = make_context(cam, prior=None)
        (name, img, err), *_ = load_frames([a.frame])
        if img is None:
            raise SystemExit(f"{name}: {err}")
        det, _, _ = pred.detect(img)
        full, why = all_detection_truth(ctx.tetra, det, cam)
        if why is not None:
            raise SystemExit(f"{name}: {why}: no truth to trace against")
        truth, d = full.matrix, det.brightest(a.n)
        others = sorted(set(range(a.n)) - set(full.matched[:, 0].tolist()))
        print(f"{name}: brightest {a.n} of {len(det)}; not matched by the truth solve: {others}")
    else:
        import adversarial_calibration as adv

        maker = adv.CaseMaker(None, 0, adv.FAMILIES, 3, 12)
        c = maker.cases(a.adversarial_case, a.adversarial_case + 1)[0]
        cam, ctx = maker.camera, make_context(maker.camera, prior=None)
        if c["truth"] is None:
            raise SystemExit(f"case {a.adversarial_case} ({c['family']}) has no truth: every answer is wrong")
        truth, d = c["truth"][0], c["detections"]
        print(f"case {c['case']}: family {c['family']}, N = {c['n']}, parameter {c['param']}")
    solver = build_solver("whole-sky", cam, context=ctx)
    solver.solve(d, cam)  # compile and load first, untraced
    _instrument(solver, cam, truth)
    res = solver.solve(d, cam)
    if isinstance(res, Solution):
        print(
            f"answer: {rotation_angle_deg(res.matrix, truth):.4f} deg from the truth, {res.n_matched} matched, "
            f"p = {res.false_match_probability:.3g}, refined by {res.extra.get('refined_by')}, evidence: "
            f"{res.extra.get('evidence')}"
        )
    else:
        print(f"refused ({res.status}): {res.reason}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
