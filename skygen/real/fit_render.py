"""Step 6 and 7 of ``skygen fit-camera``: the measurements in the model's own terms, renders of the fitted
camera at the frames' attitudes, and the check that the renders reproduce the frames.

* :func:`build_fitted` — the camera config from the measurements: the sensor
  (:mod:`skygen.real.fit_sensor`), the background electrons at the centre as dark charge (the start
  camera's, lowered when it alone would outshine the darkest corner) plus ``photometry.sky_mag_arcsec2``,
  its fall to the corners ``optics.vignetting``, its gradient ``corruptions.stray_light``, the PSF, hot
  pixels, the zero point as ``sensor.exposure_s`` and the detector settings.
* :func:`fit_model_terms` — renders at the fitted attitudes, measured like the real frames
  (:func:`skygen.real.frame_stats.frame_stats`): the exposure corrected once so that the renders' zero
  point is the real one; the detections the catalogue lacks become ``corruptions.false_stars``; then the
  four statistics of :data:`skygen.real.frame_stats.TOLERANCES` are checked
  (:func:`skygen.real.frame_stats.check_renders`). A statistic that is off is corrected once where a term
  fits it directly (:func:`correct_once`: the background's level and noise through the sensor fit, the star
  width through the other fitted PSF profile (:func:`other_profile`) or the PSF width by the ratio, the exposure
  then refitted to the zero point, the faint sources by the difference) and rendered again; what is still off is
  returned as warnings, which ``skygen fit-camera`` prints and writes at the top of the report and the camera file.

Units: ADU of the frames (after their value scale), electrons through the fitted gain, pixels.
"""

from __future__ import annotations

import copy
import dataclasses

import numpy as np

from skygen.errors import ConfigError
from skygen.instrument.camera import Camera


def fit_model_terms(
    cfg0,
    g,
    px: dict,
    solved: list,
    fr,
    table,
    epoch_yr: float,
    pixel_pitch_um,
    with_start: bool,
    log,
    black_level: int | None = None,
    exposure_scales: list[float] | None = None,
) -> dict:
    """Step 6 (module doc). ``px``: :func:`skygen.real.fit_camera.measure_pixels`'s measurements (``meas`` is
    updated in place by a correction); ``black_level``: the processor's, given (ADU) instead of fitted;
    ``exposure_scales``: each solved frame's exposure relative to the pooled one (:func:`frame_exposure_scales`;
    None: every frame renders the camera's). Returns the
    config, the exposure, the real and rendered statistics (start camera, fitted camera), the checks, the correction
    made (or None) and the warnings."""
    from skygen.real.fit_fixed import find as find_fixed
    from skygen.real.fit_fixed import near_any as near_fixed
    from skygen.real.fit_geometry import radec_roll
    from skygen.real.frame_stats import check_renders, median_of
    from skygen.sky.catalog import SkyIndex

    cam, meas, sat = g.camera, px["meas"], fr.sat
    meas["star_vignetting"] = star_vignetting(px["stars"])
    exposure = _exposure_from_stars(cfg0, px["stars"], meas["gain_e_per_adu"])
    # the renders are compared with at most CHECK_FRAMES frames, spread evenly over the solved ones: medians and
    # counts per frame need no more, and renders at every attitude of 100 frames took most of a fit's time
    picked = spread_evenly(len(solved), CHECK_FRAMES)
    attitudes = [radec_roll(g.rotations[k]) + ((exposure_scales[k],) if exposure_scales else ()) for k in picked]
    sky = SkyIndex(table, epoch_yr, _explaining_depth(cfg0, cam, meas, exposure, pixel_pitch_um, table))
    real_stats = [
        _measure_real(fr.image_of(solved[k].name), meas["settings"], sat, solved[k], g, int(k), sky) for k in picked
    ]
    # the detections no catalogue star explains, as magnitudes on the frames' zero point: the false stars'
    # brightness is fitted to them (:func:`fit_false_star_shape`)
    meas["sharp_per_frame"] = float(np.mean([r["sharp_sources"] for r in real_stats]))
    # light fixed on the sensor (a glow, a leak): rendered in every frame, and not a false star
    un = [r.pop("_unexplained") for r in real_stats]
    meas["fixed_sources"] = find_fixed(un, [g.rotations[k][:, 2] for k in picked], cam.width_px, cam.height_px)
    flux = np.concatenate(
        [u["flux_adu"][u["usable"] & ~near_fixed(u["x_px"], u["y_px"], meas["fixed_sources"])] for u in un]
    )
    faint = (px["zp_real"], flux) if np.isfinite(px["zp_real"]) else None
    cfg = build_fitted(cfg0, cam, meas, exposure, pixel_pitch_um)
    render_zp = _render_stats(cfg, attitudes, table, sat)
    # light fixed on the sensor: as much light as makes the renders detect what the frames do (a Gaussian's light
    # below the threshold is not detected, and how much of it is depends on the light: scaled until the renders'
    # detected flux is within FIXED_FLUX_TOL of the frames', at most FIXED_STEPS renders)
    for step in range(FIXED_STEPS + 1 if meas["fixed_sources"] else 0):
        got = np.median([r["_fixed_flux"] for r in render_zp], axis=0)
        for q, g_ in zip(meas["fixed_sources"], got):
            q["rendered_adu"] = float(g_)
        near = all(abs(g_ / q["flux_adu"] - 1) <= FIXED_FLUX_TOL for q, g_ in zip(meas["fixed_sources"], got))
        if near or step == FIXED_STEPS:
            break
        for q, g_ in zip(meas["fixed_sources"], got):
            light = q.get("light_adu", q["flux_adu"]) * q["flux_adu"] / max(float(g_), 1e-9)
            q["light_adu"] = float(np.clip(light, q["flux_adu"], 20 * q["flux_adu"]))
        cfg = build_fitted(cfg0, cam, meas, exposure, pixel_pitch_um)
        render_zp = _render_stats(cfg, attitudes, table, sat)
    # a processor's black level above the sky (crushed darks that lose faint stars): fitted to the depth the
    # frames detect catalogue stars to, where their background sits at the floor (fit_black_level)
    floor, why = black_level_gate(real_stats)
    meas["black_level"] = {"adu": 0, "note": f"none: {why}"}
    # (light fixed on the sensor was scaled above at no black level; a camera with both would render it a little
    # fainter than detected)
    real_width = median_of(real_stats, "star_sigma_px")

    def measure(b: int) -> tuple:
        meas["black_level_adu"] = b
        return _at_black_level(cfg0, cam, meas, exposure, pixel_pitch_um, attitudes, table, sat, px, real_width)

    if black_level is not None:
        meas["black_level"] = {"adu": int(black_level), "note": f"sensor.black_level_adu {black_level}: given"}
        if black_level:
            _, meas["black_level"]["exposure_s"], meas["black_level"]["psf"] = measure(int(black_level))
    elif floor:
        meas["black_level"] = fit_black_level(measure, median_of(real_stats, "half_detected_mag"), int(sat))
    meas["black_level_adu"] = meas["black_level"]["adu"]
    fitted_exposure, fitted_psf = meas["black_level"].pop("exposure_s", None), meas["black_level"].pop("psf", None)
    if black_level is not None or floor:
        log(f"fit-camera: {meas['black_level']['note']}")
    if meas["black_level_adu"]:  # its exposure and PSF; the photometric scatter and zero point below from renders
        exposure, meas["psf"] = fitted_exposure, fitted_psf
        cfg = build_fitted(cfg0, cam, meas, exposure, pixel_pitch_um)
        render_zp = _render_stats(cfg, attitudes, table, sat)
    # the centroid scatter the frames show beyond the renders' own (the geometry fit's residual per axis against the
    # renders' detections' offsets from their true places): drawn as optics.star_jitter_px
    meas["star_jitter"] = star_jitter(meas.get("centroid_sigma_px"), median_of(render_zp, "centroid_sigma_px"))
    meas["star_jitter_px"] = meas["star_jitter"]["px"]
    if meas["star_jitter_px"]:
        log(f"fit-camera: {meas['star_jitter']['note']}")
        cfg = build_fitted(cfg0, cam, meas, exposure, pixel_pitch_um)
        render_zp = _render_stats(cfg, attitudes, table, sat)
    meas["star_scatter"] = _star_scatter(px["stars"], render_zp, cfg.optics.vignetting)
    linear = (exposure, copy.deepcopy(meas), render_zp, attitudes, px["mv"])  # the fit without a tone curve
    # a processor's tone curve (JPEG and other processed frames): where the frames' stars respond to brightness with a
    # lower power than the linear renders', the curve's exponent is fitted to it (fit_tone_curve)
    meas["tone"] = tone_gate(meas["star_scatter"], meas["black_level_adu"])
    if meas["tone"] is None:
        v = cfg.optics.vignetting
        sc = meas["star_scatter"]
        meas["tone_knee_adu"] = tone_knee(real_stats, meas)
        # frames of several exposures: their zero points, from which each frame's exposure was taken, moved as the
        # exposure to the frames' flux exponent (relative to a linear sensor's), not as the exposure itself
        attitudes = toned_exposures(attitudes, sc["flux_exponent_real"], sc["flux_exponent_rendered"])

        def answer(rows: list) -> float:
            return _star_scatter(px["stars"], rows, v)["flux_exponent_rendered"] if rows else float("nan")

        def measure_tone(gamma: float) -> tuple:
            meas["tone_gamma"] = gamma
            rows, e, p = _refitted(cfg0, cam, meas, exposure, pixel_pitch_um, attitudes, table, sat, px, real_width,
                                   response=answer)  # fmt: skip
            return answer(rows), e, p

        meas["tone"] = fit_tone_curve(measure_tone, sc["flux_exponent_real"], sc["flux_exponent_rendered"],
                                      meas["tone_knee_adu"])  # fmt: skip
        log(f"fit-camera: {meas['tone']['note']}")
    meas["tone_gamma"] = meas["tone"]["gamma"]
    fitted_exposure, fitted_psf = meas["tone"].pop("exposure_s", None), meas["tone"].pop("psf", None)
    if meas["tone_gamma"] < 1.0:  # its exposure and PSF; the photometric scatter and zero point below from renders
        exposure, meas["psf"] = fitted_exposure, fitted_psf
        cfg = build_fitted(cfg0, cam, meas, exposure, pixel_pitch_um)
        render_zp = _render_stats(cfg, attitudes, table, sat)
        meas["star_scatter"] = _star_scatter(px["stars"], render_zp, cfg.optics.vignetting)
    else:
        meas["tone_knee_adu"] = 0.0
        attitudes = linear[3]

    def finish(exposure: float, render_zp: list, attitudes: list) -> tuple:
        """The zero point, the faint sources, the check and its corrections (at most :data:`CORRECTION_ROUNDS`):
        (cfg, after, checks, correction, exposure)."""
        meas["star_scatter_mag"] = meas["star_scatter"]["fitted_mag"]
        cfg = build_fitted(cfg0, cam, meas, exposure, pixel_pitch_um)
        zp_sim = median_of(render_zp, "zero_point_mag")
        # through a tone curve the stars' detected flux grows as the exposure to the renders' flux exponent, not 1
        slope = zero_point_response(meas)
        if np.isfinite(zp_sim) and np.isfinite(px["zp_real"]):
            exposure *= 10 ** (0.4 * (px["zp_real"] - zp_sim) / slope)
            cfg = build_fitted(cfg0, cam, meas, exposure, pixel_pitch_um)
        # stars the catalogue lacks (Hipparcos is complete to about V 8; a real frame shows fainter ones): the
        # detections real frames have beyond the renders' become corruptions.false_stars (point sources at
        # random places, magnitudes up to the detection limit)
        cfg, after = _faint_sources(
            cfg0, cam, meas, exposure, pixel_pitch_um, real_stats, attitudes, table, sat, 0.0, faint
        )
        after = check_stats(cfg, attitudes, table, sat, after)
        checks = check_renders(real_stats, after)
        correction = None
        # at most CORRECTION_ROUNDS corrections, each kept only where its renders miss by less than before it (a
        # second where one step of the noise did not land: ost's clipped background went 1.19 x -> 0.81 x)
        for round_ in range(CORRECTION_ROUNDS):
            if all(c["ok"] for c in checks):
                break
            first = (cfg, after, checks, exposure, copy.deepcopy(meas), px["mv"])
            psf_before = dict(meas["psf"])
            gain_before = meas["gain_e_per_adu"]
            changed, exposure = correct_once(checks, meas, px, exposure, cfg0.sensor, int(round(sat)))
            if changed and (meas["psf"] != psf_before or meas["gain_e_per_adu"] != gain_before):
                # another PSF or noise puts another share of a star's light above the threshold, and one step of the
                # width need not land on the frames' (pixels, jitter and noise add to it): the zero point and the
                # star width refitted together over BLACK_PASSES renders (on Amalthea's JPEGs one zero-point step
                # after a new gain and profile left the renders 0.23 mag faint and 0.73 x the detections)
                _, exposure, meas["psf"] = _refitted(cfg0, cam, meas, exposure, pixel_pitch_um, attitudes, table, sat,
                                                     px, real_width, response=lambda _rows: slope)  # fmt: skip
                changed.append(f"exposure and PSF width refitted to the zero point and star width ({BLACK_PASSES} "
                               "renders)")  # fmt: skip
            if not changed:
                break
            missed = "; ".join(c["why"] for c in checks if not c["ok"])
            faint_n = meas["faint_sources_per_frame"]
            cfg, after = _faint_sources(
                cfg0, cam, meas, exposure, pixel_pitch_um, real_stats, attitudes, table, sat, faint_n, faint
            )
            step = {"changed": changed, "checks_before": checks, "kept": True}
            after = check_stats(cfg, attitudes, table, sat, after)
            checks = check_renders(real_stats, after)
            step["checks_after"] = checks  # kept in the record either way: what the correction did
            if miss(checks) > miss(step["checks_before"]):  # worse: the fit before it stands
                cfg, after, checks, exposure, kept_meas, px["mv"] = first
                meas.clear()
                meas.update(kept_meas)
                step["kept"] = False
            if correction is None:
                correction = step
            else:
                correction["second"] = step
            log(
                f"fit-camera: renders of the fitted camera missed the frames ({missed}): "
                + ("corrected once: " if round_ == 0 else "corrected again: ")
                + "; ".join(changed)
                + ("" if step["kept"] else " -- which missed by more, so the fit before it stands")
            )
            if not step["kept"]:
                break
        return cfg, after, checks, correction, exposure

    cfg, after, checks, correction, exposure = finish(exposure, render_zp, attitudes)
    if meas["tone_gamma"] < 1.0 and any(not c["ok"] for c in checks):
        # a tone curve whose renders still miss: the fit without it, kept where its renders miss by less (a response
        # below linear that is not the processor's curve, e.g. cedar's frames, whose zero points follow exposure)
        toned = (cfg, after, checks, correction, exposure, copy.deepcopy(meas), px["mv"], attitudes)
        exposure, kept, render_zp, attitudes, px["mv"] = linear  # (the curve's correction, if any, is not this fit's)
        meas.clear()
        meas.update(copy.deepcopy(kept))
        meas.update(tone_gamma=1.0, tone_knee_adu=0.0)
        cfg, after, checks, correction, exposure = finish(exposure, render_zp, attitudes)
        if miss(checks) < miss(toned[2]):
            meas["tone"] = {**toned[5]["tone"], "gamma": 1.0, "fitted_gamma": toned[5]["tone_gamma"]}
            meas["tone"]["note"] = (
                f"{toned[5]['tone']['note']} -- undone: its renders missed the frames by more than renders without "
                f"it ({miss(toned[2]):.3f} against {miss(checks):.3f}, the summed log ratios beyond tolerance)"
            )
        else:
            without = miss(checks)
            cfg, after, checks, correction, exposure, kept, px["mv"], attitudes = toned
            meas.clear()
            meas.update(kept)
            meas["tone"]["note"] += (
                f" -- kept: its renders still miss the frames, but by less than renders without it ({miss(checks):.3f} "
                f"against {without:.3f}, the summed log ratios beyond tolerance)"
            )
        log(f"fit-camera: {meas['tone']['note']}")
    warnings = [c["why"] for c in checks if not c["ok"]]
    nonlinear = response_warning(meas["star_scatter"])
    if nonlinear:
        warnings.append(nonlinear)
    shallow = half_detected_warning(median_of(real_stats, "half_detected_mag"), median_of(after, "half_detected_mag"))
    if shallow:
        warnings.append(shallow)
    before = None
    if with_start:  # the start camera's renders, for comparison; a start file that gives only the geometry (no
        # sensor, optics or exposure: the defaults) may detect nothing at all, which leaves the column out
        try:
            before = _render_stats(cfg0, attitudes, table, 2**cfg0.sensor.bit_depth - 1)
        except ConfigError as e:
            log(f"fit-camera: the start camera's renders are left out of the report: {e}")
    return {
        "cfg": cfg,
        "exposure": exposure,
        "real_stats": real_stats,
        "before": before,
        "after": after,
        "checks": checks,
        "correction": correction,
        "warnings": warnings,
        # the compared frames' exposures relative to the camera's, as rendered (None: all at the camera's)
        "check_exposure_scales": [a[3] for a in attitudes] if exposure_scales else None,
    }


#: a processor's black level (``sensor.black_level_adu``) is looked for only where the frames' background sits at
#: the ADC's floor (median level at most this, ADU): a black level below the sky takes nothing off a star
BLACK_FLOOR_ADU = 0.5
#: its search: doubling then bisection over whole ADU from 0 to the saturation level, at most BLACK_STEPS levels,
#: stopping where the renders' half-detected magnitude is within BLACK_TOL_MAG of the frames'
BLACK_STEPS = 10
BLACK_TOL_MAG = 0.05
#: renders per black level tried (:func:`_at_black_level`): the zero point and star width refitted twice
BLACK_PASSES = 3


def black_level_gate(real_stats: list[dict]) -> tuple[bool, str]:
    """(whether a black level is looked for on these frames: their background sits at the ADC's floor, why)."""
    from skygen.real.frame_stats import median_of

    level = median_of(real_stats, "background_adu")
    if not (np.isfinite(level) and level <= BLACK_FLOOR_ADU):
        return False, f"the frames' background sits at {level:.2f} ADU, above the floor: no black level crushes it"
    return True, f"the frames' background sits at the floor ({level:.2f} ADU)"


def _at_black_level(cfg0, cam, meas, exposure, pitch, attitudes, table, sat, px, real_width: float) -> tuple:
    """(renders' half-detected magnitude, exposure, PSF) of the fitted camera at ``meas["black_level_adu"]``: a black
    level takes light off every star pixel, the wings first, so the frames' zero point and star width (measured
    after it) are refitted with it (:func:`_refitted`)."""
    from skygen.real.frame_stats import median_of

    rows, exposure, psf = _refitted(cfg0, cam, meas, exposure, pitch, attitudes, table, sat, px, real_width)
    return (median_of(rows, "half_detected_mag") if rows else float("nan")), exposure, psf


def zero_point_response(meas: dict) -> float:
    """How many magnitudes the renders' zero point moves per magnitude of exposure: 1 for a linear sensor; through a
    tone curve (``meas["tone_gamma"]`` < 1) the renders' flux exponent (clipped to 0.2-2)."""
    if meas.get("tone_gamma", 1.0) >= 1.0:
        return 1.0
    return _clipped_response(meas.get("star_scatter", {}).get("flux_exponent_rendered", float("nan")))


def _clipped_response(s: float) -> float:
    """A flux exponent as the zero point's response to the exposure: clipped to 0.2-2, 1 where not measured."""
    return float(np.clip(s, 0.2, 2.0)) if np.isfinite(s) else 1.0


def _refitted(cfg0, cam, meas, exposure, pitch, attitudes, table, sat, px, real_width: float, response=None) -> tuple:
    """(the last renders' rows, exposure, PSF) of the fitted camera as ``meas`` gives it, with the exposure and the
    PSF's width refitted to the frames' zero point and star width: :data:`BLACK_PASSES` renders, the exposure scaled
    to the zero point and the PSF's width to the star width after each but the last. ``response(rows)``: how the
    renders' zero point answers the exposure (the flux exponent, where a tone curve compresses the stars; None: 1).
    Rows are [] where the renderer refuses the camera (it detects no star). ``meas["psf"]`` is restored; the PSF
    fitted is returned."""
    from skygen.real.frame_stats import median_of

    psf0 = meas["psf"]
    psf = dict(psf0)
    key = "moffat_sigma_px" if psf.get("psf") == "moffat" else "gaussian_sigma_px"
    try:
        for i in range(BLACK_PASSES):
            meas["psf"] = psf
            try:
                rows = _render_stats(build_fitted(cfg0, cam, meas, exposure, pitch), attitudes, table, sat)
            except ConfigError:  # the renderer refuses a camera that detects no star: a level far too high
                return [], exposure, psf
            if i == BLACK_PASSES - 1:
                break
            zp, width = median_of(rows, "zero_point_mag"), median_of(rows, "star_sigma_px")
            slope = _clipped_response(response(rows)) if response is not None else 1.0
            if np.isfinite(zp) and np.isfinite(px["zp_real"]):
                exposure *= 10 ** (0.4 * (px["zp_real"] - zp) / slope)
            if psf.get("ok") and np.isfinite(width) and width > 0 and np.isfinite(real_width):
                psf = {**psf, key: float(psf[key] * np.clip(real_width / width, 0.5, 2.0))}
    finally:
        meas["psf"] = psf0
    return rows, exposure, psf


#: a tone curve (``sensor.tone_gamma``) is looked for where the frames' flux exponent is below the linear renders' by
#: more than the response warning's tolerance (:data:`RESPONSE_EXPONENT_TOL`); its search: at most TONE_STEPS
#: exponents, each rendered as the black level's are (:func:`_refitted`), stopping within TONE_TOL of the frames'
TONE_STEPS = 4
TONE_TOL = 0.03
TONE_GAMMA_MIN = 0.2
#: the curve's knee: this many background sigma above the frames' background (the background is read linearly)
TONE_KNEE_SIGMA = 3.0


def tone_gate(scatter: dict, black_level_adu: int) -> dict | None:
    """None where a tone curve is to be fitted (:func:`fit_tone_curve`), else the record of none and why."""
    a, b = scatter.get("flux_exponent_real", float("nan")), scatter.get("flux_exponent_rendered", float("nan"))
    if black_level_adu:
        why = "none: a black level was fitted (the frames' crushed darks, not a curve, lose their faint stars)"
    elif not (np.isfinite(a) and np.isfinite(b)):
        why = "none: the matched stars' response is not measured on both frames and renders"
    elif a >= b - RESPONSE_EXPONENT_TOL:
        why = (f"none: the frames' stars respond to brightness as the linear renders' do (flux exponent {a:.2f} "
               f"against {b:.2f}, tolerance {RESPONSE_EXPONENT_TOL})")  # fmt: skip
    else:
        return None
    return {"gamma": 1.0, "note": f"a processor's tone curve: {why}", "trace": []}


def toned_exposures(attitudes: list, real_s: float, linear_s: float) -> list:
    """``attitudes`` whose fourth entry (a frame's exposure from its zero point, :func:`frame_exposure_scales`) is
    raised to linear_s / real_s: a frame's zero point moves as its exposure to the power real / linear through the
    processor's curve that makes the frames' flux exponent ``real_s`` where linear renders give ``linear_s``."""
    if not attitudes or len(attitudes[0]) < 4:
        return attitudes
    k = tone_exposure_power(real_s, linear_s)
    return [(*a[:3], float(a[3]) ** k) for a in attitudes]


def tone_exposure_power(real_s: float, linear_s: float) -> float:
    """The power that turns a frame's exposure read from its zero point into its exposure through a processor's curve
    (:func:`toned_exposures`): linear_s / real_s, within 1-5; 1 where either is not measured."""
    if not (np.isfinite(real_s) and np.isfinite(linear_s) and real_s > 0):
        return 1.0
    return float(np.clip(linear_s / real_s, 1.0, 5.0))


def tone_knee(real_stats: list[dict], meas: dict) -> float:
    """The tone curve's knee (ADU above the pedestal, at least 1): :data:`TONE_KNEE_SIGMA` background sigma above the
    frames' median background, so that the background and its noise are read as a linear sensor's (as fitted) and
    the stars above it compressed."""
    from skygen.real.frame_stats import median_of

    pedestal = max(int(round(meas["bias_adu"])) - int(meas.get("black_level_adu", 0)), 0)
    level, sigma = median_of(real_stats, "background_adu"), median_of(real_stats, "noise_adu")
    return float(max(level - pedestal + TONE_KNEE_SIGMA * sigma, 1.0))


def fit_tone_curve(measure, real_s: float, linear_s: float, knee: float, steps: int = TONE_STEPS,
                   tol: float = TONE_TOL) -> dict:  # fmt: skip
    """The tone curve's exponent (``sensor.tone_gamma``) whose renders' matched stars respond to brightness as the
    frames' do: flux exponent ``real_s`` (:func:`flux_exponent`), ``linear_s`` on renders without a curve.
    ``measure(g)`` -> (the renders' flux exponent, the exposure and PSF refitted with it). Starts at
    ``real_s / linear_s`` (a power law on the stars multiplies the exponent), then g x real / rendered, at most
    ``steps`` renders, stopping within ``tol``; keeps the best, and no curve where none comes nearer than the linear
    renders. Returns {gamma, knee_adu, exposure_s, psf, trace: [[g, s], ...], note}."""
    out = {"gamma": 1.0, "knee_adu": knee, "exposure_s": None, "psf": None, "trace": [], "real_exponent": real_s,
           "linear_exponent": linear_s}  # fmt: skip
    best = (abs(linear_s - real_s), 1.0, None, None, linear_s)
    g = float(np.clip(real_s / linear_s, TONE_GAMMA_MIN, 1.0))
    for _ in range(steps):
        got, e, p = measure(g)
        out["trace"].append([g, got])
        if not np.isfinite(got):
            break
        if abs(got - real_s) < best[0]:
            best = (abs(got - real_s), g, e, p, got)
        if abs(got - real_s) <= tol:
            break
        nxt = float(np.clip(g * real_s / got, TONE_GAMMA_MIN, 1.0))
        if abs(nxt - g) < 1e-3:
            break
        g = nxt
    gap, g, e, p, got = best
    out.update(gamma=float(g), exposure_s=e, psf=p)
    said = (f"the frames' matched stars respond to brightness as the catalogue flux to the power {real_s:.2f}, "
            f"linear renders {linear_s:.2f}")  # fmt: skip
    if g >= 1.0:
        out["note"] = f"a processor's tone curve: none fitted: {said}, and no curve tried came nearer"
        return out
    out["note"] = (
        f"a processor's tone curve: sensor.tone_gamma {g:.3f} above sensor.tone_knee_adu {knee:.1f} ({said}; renders "
        f"with it {got:.2f}; {len(out['trace'])} exponents tried, the "
        "exposure and PSF width refitted to the zero point and star width at each; the knee is the frames' "
        f"background + {TONE_KNEE_SIGMA:g} sigma, not fitted)"
    )
    return out


#: the frames' centroid scatter is rendered (optics.star_jitter_px) where it exceeds the renders' own by more than
#: this factor (the tolerance of the star width's check, a statistic of the same pixels) and by STAR_JITTER_MIN_PX
STAR_JITTER_RATIO = 1.25
STAR_JITTER_MIN_PX = 0.1


def star_jitter(real_px, own_px) -> dict:
    """{px, note}: the per-axis centroid scatter the frames show (``real_px``, the geometry fit's residual rms / sqrt 2)
    beyond the renders' own (``own_px``), added in quadrature; 0 where it is within :data:`STAR_JITTER_RATIO` of it or
    under :data:`STAR_JITTER_MIN_PX`."""
    if real_px is None or not (np.isfinite(real_px) and np.isfinite(own_px)):
        return {"px": 0.0, "note": "not measured"}
    extra = float(np.sqrt(max(real_px**2 - own_px**2, 0.0)))
    said = (
        f"centroid scatter per axis {real_px:.3f} px on the frames (the geometry fit's residual), {own_px:.3f} on "
        "renders"
    )
    if real_px <= STAR_JITTER_RATIO * own_px or extra < STAR_JITTER_MIN_PX:
        return {"px": 0.0, "note": f"{said}: none added", "real_px": real_px, "rendered_px": own_px}
    return {
        "px": extra,
        "note": f"{said}: optics.star_jitter_px {extra:.3f} (each star drawn that far from its place, per axis)",
        "real_px": real_px,
        "rendered_px": own_px,
    }


def fit_black_level(measure, real_half: float, top: int, steps: int = BLACK_STEPS, tol: float = BLACK_TOL_MAG) -> dict:
    """The black level (whole ADU, 0 to ``top``) whose renders detect catalogue stars down to the magnitude the
    frames do (``real_half``, :func:`half_detected_mag`'s median over frames). ``measure(b)`` -> (the renders'
    half-detected magnitude, the exposure and the PSF it was measured with); the magnitude falls as ``b`` grows
    (NaN: no catalogue star detected at all, too high). b = 0 is measured first and kept where the renders are not
    deeper than the frames by more than :data:`HALF_BIN_MAG` (nothing to fit: finer gaps are within the half-detected
    magnitude's own bins; the frames' background at the floor is what calls for a black level); then levels 1, 2, 4, ...
    until one is too high, then bisection, at most ``steps`` measurements in all, stopping within ``tol``.
    Returns {adu, exposure_s, psf, trace: [[b, mag], ...], note}."""
    out = {"adu": 0, "exposure_s": None, "psf": None, "trace": []}
    if not np.isfinite(real_half):
        out["note"] = "none: the frames' catalogue stars have no half-detected magnitude to fit one to"
        return out
    m0, e0, p0 = measure(0)
    out["trace"].append([0, m0])
    out["exposure_s"], out["psf"] = e0, p0
    if not (np.isfinite(m0) and m0 - real_half > HALF_BIN_MAG):
        out["note"] = (
            f"none: the frames' background sits at the floor, but renders without one detect catalogue stars down "
            f"to {m0:.2f} mag against the frames' {real_half:.2f}"
        )
        return out
    lo, hi, best = 0, int(top), (m0 - real_half, 0, e0, p0)
    doubling = True  # 1, 2, 4, ... until a level is too high (levels span orders of magnitude), then halving
    for _ in range(steps - 1):
        if hi - lo <= 1:
            break
        b = min(2 * lo if lo else 1, hi - 1) if doubling else (lo + hi) // 2
        m, e, p = measure(b)
        out["trace"].append([b, m])
        if not np.isfinite(m) or m < real_half:
            hi, doubling = b, False  # too high: the renders lose stars the frames keep (or every star)
        else:
            lo = b
        if np.isfinite(m) and abs(m - real_half) < abs(best[0]):
            best = (m - real_half, b, e, p)
        if abs(best[0]) <= tol:
            break
    gap, b, e, p = best
    out.update(adu=int(b), exposure_s=e, psf=p)
    out["note"] = (
        f"sensor.black_level_adu {b}: the frames' background sits at the floor and their catalogue stars are half "
        f"detected down to {real_half:.2f} mag, renders without a black level to {m0:.2f}; with it to "
        f"{real_half + gap:.2f} (a camera's processor subtracting a level above the sky, which takes that much off "
        f"every star pixel; {len(out['trace'])} levels tried, the exposure and PSF width refitted to the zero point "
        "and star width at each)"
    )
    return out


#: real frames whose matched stars' flux exponent (:func:`flux_exponent`) differs from the renders' by more than
#: this have a response skygen does not render: a warning
RESPONSE_EXPONENT_TOL = 0.15


def response_warning(scatter: dict) -> str | None:
    """The warning where the frames' response to star brightness is not the renders' (:data:`RESPONSE_EXPONENT_TOL`),
    else None."""
    a, b = scatter.get("flux_exponent_real", float("nan")), scatter.get("flux_exponent_rendered", float("nan"))
    if not (np.isfinite(a) and np.isfinite(b)) or abs(a - b) <= RESPONSE_EXPONENT_TOL:
        return None
    return (
        f"response not linear: matched stars' detected flux grows as the catalogue flux to the power {a:.2f} on "
        f"the frames, {b:.2f} on renders (tolerance {RESPONSE_EXPONENT_TOL}): a tone curve or black clip of the "
        "camera's image processor (JPEG or other processed frames) that skygen's (a black level; a power-law tone "
        "curve above a knee, fitted where the frames respond with the lower power) did not reproduce, so the "
        "renders' faint stars, detections and photometry will not match; raw frames (PNG, TIFF, FITS read-outs) fit"
    )


def miss(checks: list) -> float:
    """How far a set of checks misses, in all: the sum over statistics of the log ratio beyond its tolerance
    (inf for a statistic not measured)."""
    out = 0.0
    for c in checks:
        r = c["ratio"]
        out += max(abs(np.log(r)) - np.log1p(c["tolerance"]), 0.0) if np.isfinite(r) and r > 0 else np.inf
    return out


#: the most frames whose statistics the renders are checked against (and rendered at)
CHECK_FRAMES = 16
#: corrections after the render check (fit_model_terms' finish), each kept only where it misses by less
CORRECTION_ROUNDS = 2


def spread_evenly(n_total: int, n: int) -> np.ndarray:
    """Indices of at most ``n`` of ``n_total`` items spread evenly from the first to the last (the frames a check
    compares; the benchmarks that re-render a fit pick the same)."""
    return np.unique(np.linspace(0, n_total - 1, min(n_total, n)).round().astype(int))


#: light fixed on the sensor: its renders' detected flux within this of the frames' (relative), in at most this many
#: renders of the check frames beyond the first (skygen.real.fit_fixed)
FIXED_FLUX_TOL = 0.1
FIXED_STEPS = 3


def _faint_sources(cfg0, cam, meas, exposure, pitch, real_stats, attitudes, table, sat, start: float, faint=None):
    """(config, renders) with the sources the catalogue lacks as ``corruptions.false_stars``.

    With ``faint`` = (zero point, fluxes of the real detections no catalogue star explains) their brightness
    is fitted (:func:`fit_false_star_shape`, on the detection limit of renders without false stars) and
    their number is the one that gives the renders as many uncatalogued sources well above the limit per
    frame as the frames have, beyond those the renders make themselves (hot pixels, blends): the bright
    ones are those a few-star solver is given. Otherwise (too few of them, no zero point) the number is
    ``start`` plus the median of the detections real frames have beyond the renders, in up to three steps
    each scaled by the detections the last one gained per false star added; with the frames' uncatalogued
    detections known but too few to fit a shape, the neutral shape's bright end is capped to the frames' non-catalogue
    sources among their ten brightest detections, as a fitted shape's is (:func:`cap_bright_tail`)."""
    if faint is not None:
        zp, flux = faint
        meas["faint_sources_per_frame"] = 0.0
        cfg = build_fitted(cfg0, cam, meas, exposure, pitch)
        bare = _render_stats(cfg, attitudes, table, sat)
        own = np.concatenate([r["_unexplained_flux"] for r in bare])
        shape = fit_false_star_shape(
            _mags(zp, flux),
            bare[0]["_detection_limit_mag"],
            len(real_stats),
            np.concatenate([r["_star_mag"] for r in bare]),
            np.concatenate([r["_star_found"] for r in bare]),
            rendered_mags=_mags(zp, own),
        )
        meas["false_star_shape"] = shape
        if shape["n"] >= MIN_FALSE_STARS_FITTED:
            meas["faint_sources_per_frame"] = shape["per_frame"]
            if shape["per_frame"] == 0:
                return cfg, bare
            cfg = build_fitted(cfg0, cam, meas, exposure, pitch)
            rendered = _render_stats(cfg, attitudes, table, sat)
            capped = _capped(shape, bare, real_stats, rendered)
            if capped is shape:
                return cfg, rendered
            meas["false_star_shape"] = capped
            meas["faint_sources_per_frame"] = capped["per_frame"]
            cfg = build_fitted(cfg0, cam, meas, exposure, pitch)
            return cfg, _render_stats(cfg, attitudes, table, sat)
    meas["faint_sources_per_frame"] = start
    if faint is not None and start == 0:  # the renders without false stars are these: not rendered again
        rendered = bare
    else:
        cfg = build_fitted(cfg0, cam, meas, exposure, pitch)
        rendered = _render_stats(cfg, attitudes, table, sat)
    count, gain = start, 1.0
    for _ in range(3):
        deficit = float(np.median([a["detections"] - b["detections"] for a, b in zip(real_stats, rendered)]))
        more = float(np.clip(count + deficit / gain, 0.0, MAX_FALSE_STARS))
        if abs(deficit) < 1.0 or abs(more - count) < 0.5:
            break
        meas["faint_sources_per_frame"] = more
        cfg = build_fitted(cfg0, cam, meas, exposure, pitch)
        again = _render_stats(cfg, attitudes, table, sat)
        gained = float(np.median([b["detections"] - a["detections"] for a, b in zip(rendered, again)]))
        gain = float(np.clip(gained / (more - count), 0.2, 1.0)) if more != count else 1.0
        count, rendered = more, again
    if faint is not None and count > 0:
        # their shape not fitted (too few uncatalogued detections where renders detect stars), so uniform over 4 mag
        # above the limit: its bright end checked as a fitted one's is (the 70D's and openstartracker's renders had
        # put 9.7-10 false stars among each frame's ten brightest detections, the frames 0-1.7, and solved none)
        shape = {**meas["false_star_shape"], "per_frame": count}
        capped = _capped(shape, bare, real_stats, rendered)
        if capped is not shape:
            meas["false_star_shape"] = capped
            meas["faint_sources_per_frame"] = capped["per_frame"]
            cfg = build_fitted(cfg0, cam, meas, exposure, pitch)
            rendered = _render_stats(cfg, attitudes, table, sat)
    return cfg, rendered


def _capped(shape: dict, bare: list, real_stats: list, rendered: list) -> dict:
    """:func:`cap_bright_tail` of ``shape`` from the frames' (``real_stats``), the renders without false stars'
    (``bare``) and the renders with them (``rendered``) non-catalogue sources among the ten brightest detections."""
    return cap_bright_tail(
        shape,
        bare[0]["_detection_limit_mag"],
        np.array([r["_tenth_mag"] for r in bare]),
        int(sum(r["nonstar_brightest10"] for r in real_stats)),
        own=float(sum(r["nonstar_brightest10"] for r in bare)),
        rendered=float(sum(r["nonstar_brightest10"] for r in rendered)),
    )


#: the renders' bright false stars contradict the frames when the frames show this unlikely few non-catalogue
#: sources among their brightest ten (Poisson, lower tail) for what the renders would put there
BRIGHT_TAIL_P = 0.05


def cap_bright_tail(
    shape: dict, limit_mag: float, tenth_mags: np.ndarray, real_count: int, own: float, rendered: float
) -> dict:
    """The false stars' bright end, checked against what a few-star solver is given: the non-catalogue sources
    among each frame's ten brightest detections.

    The magnitude fit (:func:`fit_false_star_shape`) takes its span from the single brightest uncatalogued
    detection and its slope mostly from the faint bins, so it can put more false stars among a frame's ten
    brightest detections than the frames show there (the DMK 41BU02: 0.78 per frame in renders, 0.22 real).
    Counts summed over the frames compared: ``real_count`` (the frames'), ``rendered`` (renders at their
    attitudes with ``shape``), ``own`` (the same renders without false stars: hot pixels, blends). Where the
    frames' count is improbably low for the renders' (Poisson lower tail below :data:`BRIGHT_TAIL_P`), the span
    is shortened, the density below the cap kept (fewer false stars, none of the faint ones lost), until the
    false stars' part, ``rendered - own`` scaled by the model's share of false stars brighter than each frame's
    tenth-brightest catalogue star (``tenth_mags``, true magnitudes: saturation ranks false and real bright
    stars alike, so renders measure a constant share of it), equals the frames' excess over ``own`` (or no
    false star is brighter than any frame's tenth). Otherwise ``shape`` itself is returned. Renders showing
    *fewer* than the frames are left alone: the span already reaches the brightest uncatalogued detection."""
    from scipy.stats import poisson

    slope, span, n = float(shape["slope"]), float(shape["span_mag"]), float(shape["per_frame"])
    tenth = np.asarray(tenth_mags, dtype=np.float64)
    tenth = np.minimum(tenth[np.isfinite(tenth)], limit_mag)
    if not len(tenth) or not span > 0 or rendered <= own or rendered <= real_count:
        return shape
    if poisson.cdf(real_count, rendered) >= BRIGHT_TAIL_P:
        return shape

    def above(lo: float, hi: np.ndarray) -> np.ndarray:  # the unnormalised model mass between magnitudes lo and hi
        hi = np.maximum(hi, lo)
        if slope <= 0:
            return hi - lo
        k = slope * np.log(10.0)
        return (np.exp(k * (hi - limit_mag)) - np.exp(k * (lo - limit_mag))) / k

    def share(s: float) -> float:  # false stars brighter than the frames' tenth, relative to the fitted shape's
        return float(np.sum(above(limit_mag - s, tenth)))

    full = share(span)
    if full <= 0:  # no false star brighter than any tenth: what renders show there is not the false stars'
        return shape
    target = max(float(real_count) - own, 0.0) / (rendered - own) * full
    lo, hi = max(limit_mag - float(np.max(tenth)), 0.0), span  # share(lo) = 0
    for _ in range(60 if target > 0 else 0):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if share(mid) < target else (lo, mid)
    new_span = max(hi if target > 0 else lo, 0.05)
    new_n = (
        n
        * float(above(limit_mag - new_span, np.array(limit_mag)))
        / float(above(limit_mag - span, np.array(limit_mag)))
    )
    note = (
        f"; bright end capped at Hp {limit_mag - new_span:.2f} (span {span:.2f} -> {new_span:.2f} mag, "
        f"{n:.1f} -> {new_n:.1f} per frame): its renders put {rendered:g} non-catalogue sources among the ten "
        f"brightest detections of {len(tenth)} frames ({own:g} without false stars) where the frames show "
        f"{real_count} (Poisson p {poisson.cdf(real_count, rendered):.2g})"
    )
    return {**shape, "span_mag": new_span, "per_frame": new_n, "note": shape.get("note", "") + note}


def _mags(zp: float, flux: np.ndarray) -> np.ndarray:
    flux = np.asarray(flux, dtype=np.float64)
    return zp - 2.5 * np.log10(flux[flux > 0])


#: the most false stars per frame a fit gives (corruptions.false_stars's own bound): most sit near the
#: detection limit, where few of them are detected
MAX_FALSE_STARS = 1000.0
#: magnitude bins (mag) of the false-star fit
FIT_BIN_MAG = 0.2
#: bins where renders detect fewer catalogue stars than this share are left out of the false-star fit
MIN_DETECTED_SHARE = 0.1
#: fewer uncatalogued detections than this in the bins fitted: their brightness is not fitted
MIN_FALSE_STARS_FITTED = 10


def detected_share(star_mags: np.ndarray, found: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Per magnitude bin (``edges``), the share of the catalogue stars on the sensor that renders detect
    (``star_mags`` and their ``found`` flags pooled over frames). Bins of fewer than 5 stars take the nearest
    bin's share that has 5 (none at all: 1 brighter than every star, 0 fainter)."""
    m, f = np.asarray(star_mags, dtype=np.float64), np.asarray(found, bool)
    idx = np.digitize(m, edges) - 1
    nb = len(edges) - 1
    share = np.full(nb, np.nan)
    for b in range(nb):
        sel = idx == b
        if sel.sum() >= 5:
            share[b] = f[sel].mean()
    good = np.flatnonzero(np.isfinite(share))
    if not len(good):
        return np.where(edges[1:] <= (m.min() if len(m) else np.inf), 1.0, 0.0)
    for b in np.flatnonzero(~np.isfinite(share)):
        share[b] = share[good[np.argmin(np.abs(good - b))]]
    return share


def fit_false_star_shape(
    mags: np.ndarray,
    limit_mag: float,
    n_frames: int,
    star_mags: np.ndarray,
    star_found: np.ndarray,
    rendered_mags=None,
) -> dict:
    """The false stars' brightness and number from the magnitudes of real detections no catalogue star
    explains, over ``n_frames`` frames: a forward model of what renders detect.

    False-star magnitudes are drawn as :func:`skygen.instrument.corruptions.false_star_magnitudes` draws
    them: a density rising as 10 ** (slope * (m - limit)) up to the renderer's ``limit_mag``, within ``span``
    magnitudes above it. A false star of magnitude m is detected as often as a catalogue star of that
    magnitude in renders without false stars (:func:`detected_share` of ``star_mags`` / ``star_found``).
    In :data:`FIT_BIN_MAG` bins, the real count of uncatalogued detections is Poisson about the renders' own
    (``rendered_mags``: hot pixels, blends) plus ``per_frame`` x frames x (the model's mass in the bin) x (the
    detected share), over the bins where that share is at least :data:`MIN_DETECTED_SHARE`; slope and number
    by maximum likelihood, the span reaching the brightest of them (plus 0.05 mag). Fewer than
    :data:`MIN_FALSE_STARS_FITTED` detections in those bins: the neutral shape (uniform over 4 mag) and no
    number, said in ``note``. Returns {slope, span_mag, per_frame, n, note}.
    """
    from scipy.optimize import minimize

    mags = np.asarray(mags, dtype=np.float64)
    mags = mags[np.isfinite(mags) & (mags <= limit_mag)]
    neutral = {"slope": 0.0, "span_mag": 4.0, "per_frame": float("nan")}
    if not len(mags):
        return {**neutral, "n": 0, "note": "no uncatalogued detection above the detection limit: not fitted"}
    bright = float(mags.min())
    span = float(min(limit_mag - bright + 0.05, 15.0))
    edges = limit_mag - span + FIT_BIN_MAG * np.arange(int(np.ceil(span / FIT_BIN_MAG)) + 1)
    edges[-1] = limit_mag
    share = detected_share(star_mags, star_found, edges)
    used = share >= MIN_DETECTED_SHARE
    n_real = np.histogram(mags, edges)[0].astype(np.float64)
    own = np.zeros_like(n_real)
    if rendered_mags is not None and len(rendered_mags):
        own = np.histogram(np.asarray(rendered_mags, dtype=np.float64), edges)[0].astype(np.float64)
    n_used = int(n_real[used].sum())
    if n_used < MIN_FALSE_STARS_FITTED:
        note = f"{n_used} uncatalogued detections where renders detect stars: too few to fit"
        return {**neutral, "n": n_used, "note": note}
    d_lo, d_hi = limit_mag - edges[1:], limit_mag - edges[:-1]  # each bin's magnitudes above the limit

    def mass(slope: float) -> np.ndarray:  # the model's probability in each bin
        k = slope * np.log(10.0)
        if k < 1e-9:
            return (d_hi - d_lo) / span
        return (np.exp(-k * d_lo) - np.exp(-k * d_hi)) / -np.expm1(-k * span)

    def nll(p: np.ndarray) -> float:
        slope, count = p
        mu = own[used] + count * n_frames * mass(slope)[used] * share[used] + 1e-9
        return float(np.sum(mu - n_real[used] * np.log(mu)))

    best = None
    for s0 in (0.0, 0.3, 0.6, 1.0):
        c0 = max(n_used - own[used].sum(), 1.0) / n_frames / max(float((mass(s0) * share)[used].sum()), 1e-6)
        r = minimize(nll, [s0, c0], method="L-BFGS-B", bounds=[(0.0, 2.0), (0.0, MAX_FALSE_STARS)])
        best = r if best is None or r.fun < best.fun else best
    slope, per_frame = (float(v) for v in best.x)
    note = (
        f"{n_used} uncatalogued detections between Hp {edges[0]:.2f} and {edges[1:][used][-1]:.2f} "
        f"in {n_frames} frames ({int(own[used].sum())} in renders without false stars); renders detect "
        f"{100 * share[used].min():.0f}-{100 * share[used].max():.0f} % of stars there: slope {slope:.2f} dex/mag "
        f"up to the renderer's detection limit Hp {limit_mag:.2f}, {per_frame:.1f} false stars per frame"
    )
    return {"slope": slope, "span_mag": span, "per_frame": per_frame, "n": n_used, "note": note}


#: a Moffat profile of this beta or more has no more wing than a Gaussian within the star width's 9 x 9 px
WING_BETA = 4.0


def other_profile(psf: dict, ratio: float) -> str | None:
    """The PSF profile to render instead where the renders' star width is ``ratio`` x the frames' (off): both
    profiles were fitted to the same stars (:func:`skygen.real.fit_pixels.psf_fit`), and the choice between them by
    squared residual weighs the cores, where a star's second moment also weighs its wings. Renders too narrow with
    a Gaussian take the fitted Moffat where it has wings (beta under :data:`WING_BETA`; the held-out Amalthea
    camera's stars: beta 1.54, residual ratio 0.97, a Gaussian chosen, star width 0.87 x); renders too wide with a
    Moffat take the Gaussian. None: scale the width instead."""
    kind = psf.get("psf")
    if ratio < 1 and kind == "gaussian" and psf.get("moffat_beta", np.inf) < WING_BETA:
        return "moffat"
    if ratio > 1 and kind == "moffat" and np.isfinite(psf.get("gaussian_sigma_px", np.nan)):
        return "gaussian"
    return None


def profile_words(psf: dict) -> str:
    if psf.get("psf") == "moffat":
        return f"σ(FWHM) {psf['moffat_sigma_px']:.3f} px, β {psf['moffat_beta']:.2f}"
    return f"σ {psf['gaussian_sigma_px']:.3f} px"


def correct_once(checks: list, meas: dict, px: dict, exposure: float, start_sensor, top: int) -> tuple[list, float]:
    """One correction of the terms fitted directly, for each statistic off in ``checks``; updates ``meas``.
    Returns (what changed, one sentence each; the exposure, scaled with the gain so that a star's ADU stay).

    * background level or noise: the sensor fitted directly (:func:`skygen.real.fit_sensor.fit_sensor`), its
      bias kept (the mean-variance line's gain is what missed, when it was that), to a box level shifted by
      (real - rendered) and a box noise of the present sensor's (its model's, at the frames' median box
      level) times real / rendered: renders relate to the model as the frames relate to their boxes;
    * star width: the other fitted profile where it has the wings (or lacks those) the frames' width asks for
      (:func:`other_profile`), else the PSF's width scaled by real / rendered;
    * detections: left to the faint sources (:func:`_faint_sources` runs after this)."""
    from skygen.real.fit_sensor import electrons_at, fit_sensor, model_background

    off = {c["stat"]: c for c in checks if not c["ok"] and np.isfinite(c["ratio"])}
    changed = []
    if "background_adu" in off or "noise_adu" in off:
        bg = next(c for c in checks if c["stat"] == "background_adu")
        sg = next(c for c in checks if c["stat"] == "noise_adu")
        boxes = px["boxes"]
        shift = bg["real"] - bg["rendered"] if np.isfinite(bg["ratio"]) else 0.0
        scale = 1 / sg["ratio"] if np.isfinite(sg["ratio"]) else 1.0
        now = (meas["gain_e_per_adu"], meas["read_noise_e"], int(meas["bias_adu"]), meas["fpn_adu"], top)
        level = float(np.median(boxes["level"]))
        sigma_now = model_background(electrons_at(level, *now), *now)[1]
        targets = (max(level + shift, 0.05), sigma_now * scale)
        start = dataclasses.replace(start_sensor, read_noise_e=float(now[1]), fpn_adu=float(now[3]))
        sensor, rec = fit_sensor(boxes, start, now[2], top, "as fitted", targets=targets, bias_name="as fitted")
        old_gain = meas["gain_e_per_adu"]
        meas.update(sensor.terms(meas["centre_adu"] + shift, top))
        exposure *= sensor.gain_e_per_adu / old_gain
        px["mv"] = {**px["mv"], "correction": rec}
        changed.append(
            f"gain {old_gain:.3g} -> {sensor.gain_e_per_adu:.3g} e-/ADU and background {meas['background_e']:.3g} e- "
            f"fitted to a level of {targets[0]:.2f} ADU and σ {targets[1]:.2f} ADU"
        )
    if "star_sigma_px" in off and meas["psf"].get("ok"):
        psf = dict(meas["psf"])
        ratio = off["star_sigma_px"]["ratio"]
        other = other_profile(psf, ratio)
        if other:
            psf["psf"] = other
            meas["psf"] = psf
            changed.append(f"PSF profile {other} (as fitted to the stars: {profile_words(psf)}) for the "
                           f"{'narrower' if ratio > 1 else 'wider'} stars of the frames")  # fmt: skip
        else:
            # widths add in quadrature (the pixel, the jitter, the noise's share): the PSF takes the whole difference
            # (ost's frames: 0.96 px rendered from a PSF of 0.64 px against 1.95 real; scaled by the ratio it reached
            # only 1.31 px)
            key = "moffat_sigma_px" if psf.get("psf") == "moffat" else "gaussian_sigma_px"
            w = off["star_sigma_px"]
            s2 = psf[key] ** 2 + w["real"] ** 2 - w["rendered"] ** 2
            psf[key] = float(np.sqrt(s2)) if s2 > (0.5 * psf[key]) ** 2 else psf[key] / ratio
            meas["psf"] = psf
            changed.append(f"PSF σ {meas['psf'][key]:.3f} px (the frames' star width less the renders' in quadrature)")
    det = off.get("detections")
    if det and not changed and (det["rendered"] < det["real"] or meas.get("faint_sources_per_frame", 0) > 0):
        changed.append("faint sources fitted again to the detections")
    return changed, exposure


def _exposure_from_stars(cfg0, stars, gain) -> float:
    """First estimate of exposure x throughput: detected electrons / the model's electrons per second."""
    from skygen.instrument.photometry import Photometry

    if stars["n"] == 0:
        return cfg0.sensor.exposure_s
    ph = Photometry.from_config(cfg0.optics, cfg0.photometry, cfg0.sensor)
    e_s = ph.electrons_per_s(stars["mag"], stars["bv"])
    return float(np.clip(np.median(stars["flux_adu"] * gain / e_s), 1e-4, 3600))


def _photometric_residuals(flux_adu, mag, bv, frame, r2, v: float, brightest_mag: float, default_bv: float = 0.65):
    """Matched stars' instrumental magnitudes (-2.5 log10 flux) less their catalogue Hp and a vignetting ``v``
    (1 - v r2, as the renderer's), after each frame's zero point and one linear colour term in B-V (a colour
    mismatch between the sensor and the model is not scatter) and one linear term in magnitude; stars no fainter
    than ``brightest_mag`` (the faint ones' shot noise would dominate). None when fewer than 10."""
    fit = _photometric_fit(flux_adu, mag, bv, frame, r2, v, brightest_mag, default_bv)
    return None if fit is None else fit[0]


def flux_exponent(flux_adu, mag, bv, frame, r2, v: float, brightest_mag: float) -> float:
    """s of detected flux ∝ (catalogue flux)^s over the matched stars of :func:`_photometric_residuals` (1 + its
    term in magnitude): ~1 for a linear sensor and skygen's detector (slightly above: a brighter star spreads over
    more pixels above the threshold), far from 1 where the camera's response is not linear (a tone curve or black
    clip of a camera's image processor). NaN with fewer than 10 stars."""
    fit = _photometric_fit(flux_adu, mag, bv, frame, r2, v, brightest_mag)
    return float("nan") if fit is None else 1.0 + fit[1]


def _photometric_fit(flux_adu, mag, bv, frame, r2, v: float, brightest_mag: float, default_bv: float = 0.65):
    """(residuals, the magnitude term's coefficient) of :func:`_photometric_residuals`; None when too few."""
    flux, mag = np.asarray(flux_adu, dtype=np.float64), np.asarray(mag, dtype=np.float64)
    bv, frame, r2 = np.asarray(bv, dtype=np.float64), np.asarray(frame), np.asarray(r2, dtype=np.float64)
    ok = (flux > 0) & np.isfinite(mag) & (mag <= brightest_mag) & (1 - v * r2 > 0.01)
    if ok.sum() < 10:
        return None
    res = -2.5 * np.log10(flux[ok]) - mag[ok] + 2.5 * np.log10(1 - v * r2[ok])
    f, c = frame[ok], np.where(np.isfinite(bv[ok]), bv[ok], default_bv)
    # one zero point per frame, one colour term and one linear term in magnitude (the detector's flux in its
    # above-threshold area grows faster than the star: a monotone non-linearity reorders nothing, so it is not
    # scatter), fitted together; twice, the second time without the stars beyond 3 robust sigma of the first
    frames = np.unique(f)
    a = np.column_stack([f[:, None] == frames[None, :], c, mag[ok] - np.median(mag[ok])]).astype(np.float64)
    keep = np.ones(len(res), bool)
    for _ in range(2):
        coef = np.linalg.lstsq(a[keep], res[keep], rcond=None)[0]
        out = res - a @ coef
        keep = np.abs(out) <= 3 * 1.4826 * np.median(np.abs(out[keep])) + 1e-9
    return out, float(coef[-1])


def photometric_scatter(flux_adu, mag, bv, frame, r2, v: float, brightest_mag: float) -> tuple[float, int]:
    """(robust rms in mag = 1.4826 x the median absolute deviation, stars used) of
    :func:`_photometric_residuals`; NaN with fewer than 10 stars."""
    res = _photometric_residuals(flux_adu, mag, bv, frame, r2, v, brightest_mag)
    if res is None:
        return float("nan"), 0
    return float(1.4826 * np.median(np.abs(res - np.median(res)))), len(res)


#: the least spread of matched stars' r^2 (0 at the centre, 1 at the corner) for fitting the stars' vignetting
VIGNETTING_MIN_R2_SPREAD = 0.25


def star_vignetting(stars: dict) -> dict:
    """``optics.vignetting`` from the stars: the v of 1 - v r^2 (r = 1 at the corner) that minimises the robust
    scatter of the matched unsaturated stars' photometric residuals (:func:`_photometric_residuals`; a 0.005
    grid over [0, 0.9]), over the brighter half of them. The background's fall to the corners is not the
    optics' alone (sensor shading, a sky that is not flat): on the DMK 41BU02 the background said 0.9, its
    stars 0.1 or less, and renders that dimmed corner stars ten times scattered 0.38 mag against the frames'
    0.12 (results/real-frames/star-photometry.md). None where the stars are too few or too central."""
    if stars.get("n", 0) < 30 or "r2" not in stars or np.ptp(stars["r2"]) < VIGNETTING_MIN_R2_SPREAD:
        return {"v": None, "note": "stars too few or too central to measure the vignetting: the background's used"}
    cut = float(np.median(stars["mag"]))
    grid = np.round(np.arange(0.0, 0.9001, 0.005), 3)
    cost = []
    for v in grid:
        res = _photometric_residuals(stars["flux_adu"], stars["mag"], stars["bv"], stars["frame"], stars["r2"], v, cut)
        cost.append(np.inf if res is None else float(np.median(np.abs(res - np.median(res)))))
    best = float(grid[int(np.argmin(cost))])
    note = (
        f"stars' vignetting {best:.3f} (robust scatter {1.4826 * min(cost):.3f} mag; {1.4826 * cost[0]:.3f} without "
        f"vignetting, {1.4826 * cost[-1]:.3f} at 0.9) from {len(stars['mag'])} matched stars"
    )
    return {"v": best, "note": note}


def _star_scatter(real_stars: dict, renders: list, v: float) -> dict:
    """``photometry.star_scatter_mag``: the real frames' photometric scatter beyond the renders' own (shot noise,
    PSF sampling), in quadrature, over the same brightness range (the brighter half of the real matched stars)."""
    if real_stars.get("n", 0) < 10 or "frame" not in real_stars:
        return {"fitted_mag": 0.0, "note": "too few matched unsaturated stars: not fitted"}
    cut = float(np.median(real_stars["mag"]))
    s = real_stars
    real, n_real = photometric_scatter(s["flux_adu"], s["mag"], s["bv"], s["frame"], s["r2"], v, cut)
    parts = [r["_phot"] for r in renders]
    frame = np.concatenate([np.full(len(p["mag"]), k) for k, p in enumerate(parts)])
    flux, mag, bv, r2 = (np.concatenate([p[key] for p in parts]) for key in ("flux_adu", "mag", "bv", "r2"))
    sim, n_sim = photometric_scatter(flux, mag, bv, frame, r2, v, cut)
    # the response: detected flux against catalogue flux, on both (the detector's own slope is in both)
    s_real = flux_exponent(s["flux_adu"], s["mag"], s["bv"], s["frame"], s["r2"], v, cut)
    s_sim = flux_exponent(flux, mag, bv, frame, r2, v, cut)
    response = {"flux_exponent_real": s_real, "flux_exponent_rendered": s_sim}
    if not (np.isfinite(real) and np.isfinite(sim)):
        return {"fitted_mag": 0.0, "real_mag": real, "rendered_mag": sim, "note": "not measured on both: not fitted",
                **response}  # fmt: skip
    fitted = float(np.sqrt(max(real**2 - sim**2, 0.0)))
    note = (
        f"photometric scatter of matched stars to Hp {cut:.2f} about the zero point and a colour term: real "
        f"{real:.3f} mag ({n_real} stars), renders {sim:.3f} mag ({n_sim}) -> photometry.star_scatter_mag {fitted:.3f}"
        f"; their flux grows as the catalogue flux to the power {s_real:.2f} on the frames, {s_sim:.2f} on renders"
    )
    return {"fitted_mag": fitted, "real_mag": real, "rendered_mag": sim, "cut_mag": cut, "note": note, **response}


def _explaining_depth(cfg0, cam, meas: dict, exposure: float, pixel_pitch_um, table) -> float:
    """How faint a catalogue star may be and still explain a real detection. Hipparcos-2: every star (it is
    sparse: ~1 % of detections sit within 3 px of one by chance). A deep catalogue (``catalog.source: gaia``):
    the depth its renders will draw (the detection limit + ``catalog.mag_margin``), so that a star the renders
    leave out, or one of the many faint stars a detection lands near by chance (~12 % of a 27 deg camera's to
    G = 10), does not explain away a detection the false stars must reproduce."""
    if cfg0.catalog.source == "hipparcos":
        return 99.0
    from skygen.render.frame import Renderer

    return Renderer(build_fitted(cfg0, cam, meas, exposure, pixel_pitch_um), catalog=table).mag_limit


def build_fitted(cfg0, cam: Camera, meas: dict, exposure: float, pixel_pitch_um=None):
    """The fitted config: the start config with the measured values in the model's own terms."""
    from skygen.config import build_config, config_dict
    from skygen.instrument.photometry import Photometry, dark_current_e_s

    d = config_dict(cfg0)
    s = cfg0.sensor
    gain = meas["gain_e_per_adu"]
    pitch = pixel_pitch_um or cfg0.camera.pixel_pitch_um
    d["camera"].update(
        {
            "pixel_pitch_um": pitch,
            "focal_length_mm": cam.f_px * pitch / 1000.0,
            "fov_deg": None,
            "principal_x_px": float(cam.cx_px),
            "principal_y_px": float(cam.cy_px),
            "k1": float(cam.k1),
            "k2": float(cam.k2),
            "pixel_aspect": float(cam.aspect),
            "centroid_sigma_px": meas.get("centroid_sigma_px"),
            "match_tol_px": cam.match_tol_px,
            "shared_sigma_px": cam.shared_sigma_px,
            "bright_shift_px": float(cam.bright_shift_px),
            "bright_shift_from": float(cam.bright_shift_from),
            "bright_shift_x_px": float(cam.bright_shift_x_px),
            "bright_shift_y_px": float(cam.bright_shift_y_px),
        }
    )
    psf = meas["psf"]
    if psf["ok"]:
        d["optics"].update(
            {
                "psf": psf["psf"],
                "psf_sigma_px": float(
                    np.clip(psf["moffat_sigma_px"] if psf["psf"] == "moffat" else psf["gaussian_sigma_px"], 0.2, 20)
                ),
            }
        )
        if psf["psf"] == "moffat":
            d["optics"]["moffat_beta"] = float(np.clip(psf["moffat_beta"], 1.1, 20))
    bits = meas["bits"]
    d["sensor"].update(
        {
            "exposure_s": float(exposure),
            "gain_e_per_adu": float(gain),
            "read_noise_e": float(meas["read_noise_e"]),
            "bias_adu": int(round(meas["bias_adu"])),
            "black_level_adu": int(meas.get("black_level_adu", 0)),
            "fpn_adu": float(meas.get("fpn_adu", s.fpn_adu)),
            "bit_depth": int(bits),
            "full_well_e": float(max(s.full_well_e, gain * (2**bits - 1))),
            "tone_gamma": float(meas.get("tone_gamma", 1.0)),
            "tone_knee_adu": float(meas.get("tone_knee_adu", 0.0)),
            "processor_blur_px": float(meas.get("processor_blur_px", 0.0)),
        }
    )
    if meas.get("blooming", {}).get("on") is not None:  # as the frames' saturated stars show (fit_pixels.blooming)
        d["sensor"]["blooming"] = bool(meas["blooming"]["on"])
    if d["sensor"]["tone_gamma"] < 1.0:  # a tone curve: the well holds what reaches the top through it
        from skygen.config import tone_raw_top

        d["sensor"]["full_well_e"] = float(max(s.full_well_e, gain * tone_raw_top(build_config(d).sensor)))
    fitted_sensor = build_config(d).sensor
    grad_e = meas["gradient_adu"] * gain
    drop_e = meas["corner_drop_adu"] * gain
    # background at the centre (dark + sky + half the stray-light ramp), in electrons: the sensor model's
    # inverse of the measured level (skygen.real.fit_sensor.electrons_at)
    centre_e = meas.get("background_e", (meas["centre_adu"] - meas["bias_adu"]) * gain)
    dark_e = dark_current_e_s(fitted_sensor) * exposure
    darkest_e = max(centre_e - grad_e / 2 - max(drop_e, 0.0), 0.0)
    if dark_e > darkest_e:  # the start camera's dark charge alone would outshine the darkest corner: lowered
        d["sensor"]["dark_current_e_s"] = float(s.dark_current_e_s * darkest_e / dark_e)
        fitted_sensor = build_config(d).sensor
        dark_e = darkest_e
    sky_e = centre_e - dark_e - grad_e / 2
    # the corner loses vignetting x sky; the stars, where they measure it, their own (star_vignetting)
    v_sky = float(np.clip(drop_e / sky_e, 0.0, 0.9)) if sky_e > 0 else 0.0
    v_star = meas.get("star_vignetting", {}).get("v")
    d["optics"]["vignetting"] = v_sky if v_star is None else float(v_star)
    d["optics"]["sky_vignetting"] = None if v_star is None or abs(v_star - v_sky) < 0.01 else v_sky
    ph = Photometry.from_config(cfg0.optics, cfg0.photometry, fitted_sensor)
    scale = np.degrees(1.0 / cam.f_px) * 3600
    ref = ph.sky_electrons_per_px_s(20.0, scale) * cam.aspect * exposure
    d["photometry"]["sky_mag_arcsec2"] = float(np.clip(20.0 - 2.5 * np.log10(max(sky_e, 1e-9) / ref), 10, 30))
    hot = meas["hot"]
    d["corruptions"].update(
        {"stray_light": float(min(grad_e / exposure, 1e7)), "hotpixels": float(min(hot["fraction"], 0.05))}
    )
    if hot["n_static"]:
        d["sensor"]["hot_pixel_dark_e_s"] = float(min(hot["excess_adu"] * gain / exposure, 1e9))
    d["corruptions"]["false_stars"] = float(min(meas.get("faint_sources_per_frame", 0.0), MAX_FALSE_STARS))
    # light fixed on the sensor (skygen.real.fit_fixed) in e-/s at this exposure: its light as the fit scaled it
    # to be detected as the frames detect it (fit_model_terms), else its detected flux
    d["sensor"]["fixed_sources"] = [
        [q["x_px"], q["y_px"], float(min(q.get("light_adu", q["flux_adu"]) * gain / exposure, 1e12)), q["sigma_px"]]
        for q in meas.get("fixed_sources", [])
    ]
    d["photometry"]["star_scatter_mag"] = float(min(meas.get("star_scatter_mag", 0.0), 2.0))
    d["optics"]["star_jitter_px"] = float(min(meas.get("star_jitter_px", 0.0), 20.0))
    if "sharp_per_frame" in meas:  # particle hits: as many sharp sources per frame as the frames show
        area_cm2 = cfg0.camera.width_px * cfg0.camera.height_px * (pitch * 1e-4) ** 2
        d["corruptions"]["cosmic_rays"] = float(min(meas["sharp_per_frame"] / (area_cm2 * exposure), 1e5))
    shape = meas.get("false_star_shape")
    if shape is not None:
        d["corruptions"]["false_star_slope"] = shape["slope"]
        d["corruptions"]["false_star_span_mag"] = shape["span_mag"]
    st = meas["settings"]
    d["detection"].update(
        {
            "threshold_sigma": st["threshold_sigma"],
            "min_area_px": st["min_area_px"],
            "background_box_px": st["background_box_px"],
        }
    )
    w, h = cam.width_px, cam.height_px
    if w % d["output"]["image_size_px"] or h % (w // d["output"]["image_size_px"]):
        d["output"]["image_size_px"] = image_size(w, h)
    d["attitude"] = config_dict(build_config({}))["attitude"]
    return build_config(d)


def _measure_real(img, settings, sat, fs, g, k, sky) -> dict:
    from skygen.real.fit_pixels import zero_point
    from skygen.real.frame_stats import frame_stats, nonstar_brightest

    st, det = frame_stats(img, settings["threshold_sigma"], settings["min_area_px"], settings["background_box_px"], sat)
    # a camera with a bright-star shift: its bright stars are looked for where the camera puts them
    x, y = g.camera.unshift(det["x_px"], det["y_px"], det["flux_adu"], st["noise_adu"])
    explained = explained_by(g.camera, g.rotations[k], sky, x, y)
    st["nonstar_brightest10"] = nonstar_brightest(det["flux_adu"], ~explained)
    st["catalogue_detections"] = int(explained.sum())  # against the renders': depth, not the sources it lacks
    # the detections no catalogue star explains (light fixed on the sensor is found among them, the rest are the
    # false stars'), and which of them have a flux a false star could be drawn with
    un = ~explained
    st["_unexplained"] = {k: np.asarray(det[k], np.float64)[un] for k in ("x_px", "y_px", "flux_adu", "peak_adu")}
    usable = point_source_flags(det, st["background_adu"], sat)
    st["_unexplained"]["usable"] = usable[un]
    fl, pk = np.asarray(det["flux_adu"], np.float64), np.asarray(det["peak_adu"], np.float64)
    stars = explained & usable & (fl > 0)
    st["_unexplained"]["star_share"] = float(np.median(pk[stars] / fl[stars])) if stars.sum() >= 3 else float("nan")
    st["sharp_sources"] = sharp_sources(det, explained, st["background_adu"], sat)
    # how faint the frame still detects catalogue stars: those on the sensor, found within 2 px of a detection
    smag, sfound = catalogue_found(g.camera, g.rotations[k], sky, det["x_px"], det["y_px"])
    st["half_detected_mag"] = half_detected_mag(smag, sfound)
    m = g.keep[k]
    d = fs.det_index[m]
    zp, n = zero_point(
        fs.det["flux_adu"][d].astype(float),
        fs.star_mag[m],
        fs.det["peak_adu"][d].astype(float),
        np.full(len(d), st["background_adu"]),
        sat,
    )
    return {**st, "zero_point_mag": zp, "zero_point_stars": n}


def point_source_flags(det: dict, background_adu: float, sat: float) -> np.ndarray:
    """Flags: the detections that are unsaturated (peak below 80 % of ``sat``). A saturated blob (a planet, the
    Moon, a glint, a bright star's bloom) has no magnitude a false star could be drawn with, and one of them
    alone would stretch the fitted brightness range by magnitudes."""
    peak = np.asarray(det["peak_adu"], dtype=np.float64)
    return peak + background_adu < 0.8 * sat


def point_source_flux(det: dict, flags: np.ndarray, background_adu: float, sat: float) -> np.ndarray:
    """The fluxes (ADU) of the ``flags``-ed detections that are unsaturated (:func:`point_source_flags`)."""
    flux = np.asarray(det["flux_adu"], dtype=np.float64)
    return flux[np.asarray(flags, bool) & point_source_flags(det, background_adu, sat)]


def sharp_sources(det: dict, explained: np.ndarray, background_adu: float, sat: float) -> int:
    """Detections no catalogue star explains whose light is far more concentrated than a star's: the
    peak's share of the flux above both twice the median and the 99th percentile of the catalogue stars'
    (unsaturated ones only). Particle hits (and pixel defects that come and go) look like this."""
    flux, peak = np.asarray(det["flux_adu"], dtype=np.float64), np.asarray(det["peak_adu"], dtype=np.float64)
    ok = (flux > 0) & (peak + background_adu < 0.8 * sat)
    share = np.where(ok, peak / np.where(flux > 0, flux, 1.0), np.nan)
    stars = share[ok & explained]
    if len(stars) < 5:
        return 0
    limit = max(2.0 * float(np.median(stars)), float(np.quantile(stars, 0.99)))
    return int(np.sum(ok & ~explained & (share > limit)))


#: bins (mag) of :func:`half_detected_mag`, and the least stars a bin needs to count
HALF_BIN_MAG = 0.25
HALF_MIN_STARS = 5
#: frames that stop detecting catalogue stars this much brighter (or fainter) than the renders: a warning
HALF_DETECTED_TOL_MAG = 0.5


def half_detected_mag(mags, found) -> float:
    """The catalogue magnitude at which half the catalogue stars on the sensor are detected: from the brightest
    bin of :data:`HALF_BIN_MAG` (with at least :data:`HALF_MIN_STARS` stars) the first whose detected share falls
    below one half, interpolated linearly with the bin before it between bin centres. NaN where no bin falls
    below a half (the catalogue is shallower than the frames) or none is above it."""
    m, f = np.asarray(mags, dtype=np.float64), np.asarray(found, bool)
    if len(m) < HALF_MIN_STARS:
        return float("nan")
    edges = np.arange(np.floor(m.min() / HALF_BIN_MAG) * HALF_BIN_MAG, m.max() + HALF_BIN_MAG, HALF_BIN_MAG)
    idx = np.digitize(m, edges) - 1
    prev = None  # (centre, share) of the last bin with enough stars
    for b in range(len(edges) - 1):
        sel = idx == b
        if sel.sum() < HALF_MIN_STARS:
            continue
        centre, share = edges[b] + HALF_BIN_MAG / 2, float(f[sel].mean())
        if share < 0.5:
            if prev is None:
                return float("nan")
            (c0, s0) = prev
            return float(c0 + (s0 - 0.5) / (s0 - share) * (centre - c0))
        prev = (centre, share)
    return float("nan")


def catalogue_found(cam, R: np.ndarray, sky, x, y, radius_px: float = 2.0, margin_px: float = 3.0):
    """(magnitudes, found) of the catalogue stars of ``sky`` that camera ``cam`` at attitude ``R`` puts at least
    ``margin_px`` inside the sensor; found: a detection (``x``, ``y``) lies within ``radius_px``."""
    from scipy.spatial import cKDTree

    idx, sx, sy = projected(cam, R, sky, -margin_px)
    mags = np.asarray(sky.table.mag, dtype=np.float64)[idx]
    if not len(idx) or not len(x):
        return mags, np.zeros(len(mags), bool)
    d, _ = cKDTree(np.column_stack([np.asarray(x, np.float64), np.asarray(y, np.float64)])).query(
        np.column_stack([sx, sy])
    )
    return mags, d <= radius_px


def projected(cam, R: np.ndarray, sky, margin_px: float):
    """(rows of ``sky``, x, y) of its stars that camera ``cam`` at attitude ``R`` (camera -> sky) puts on the sensor
    grown by ``margin_px`` (negative: shrunk)."""
    idx = sky.cone(R[:, 2], cam.corner_radius_rad() + 0.01)
    sx, sy, front = cam.project(sky.vectors[idx] @ R)
    ok = front & cam.inside(sx, sy, margin_px=margin_px)
    return idx[ok], sx[ok], sy[ok]


def half_detected_warning(real: float, rendered: float) -> str | None:
    """The warning where the frames stop detecting catalogue stars more than :data:`HALF_DETECTED_TOL_MAG` away
    from where the renders do (:func:`half_detected_mag`, medians over frames), else None."""
    if not (np.isfinite(real) and np.isfinite(rendered)) or abs(real - rendered) <= HALF_DETECTED_TOL_MAG:
        return None
    why = (
        "the camera's response drops faint stars that its zero point and noise say it should see (a black clip, "
        "tone curve or denoiser of a camera's image processor: JPEG or other processed frames?); raw read-outs "
        "(PNG, TIFF, FITS) fit"
        if real < rendered
        else "the frames see fainter stars than the fitted camera renders"
    )
    return (
        f"catalogue stars half detected down to {real:.2f} mag on the frames, {rendered:.2f} on renders "
        f"(tolerance {HALF_DETECTED_TOL_MAG} mag): {why}"
    )


def explained_by(cam, R: np.ndarray, sky, x: np.ndarray, y: np.ndarray, radius_px: float = 2.0) -> np.ndarray:
    """Flags: a star of ``sky`` (a :class:`skygen.sky.catalog.SkyIndex`) projects within ``radius_px`` of the
    detection at (``x``, ``y``) through camera ``cam`` at attitude ``R`` (camera -> sky)."""
    from scipy.spatial import cKDTree

    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    idx, sx, sy = projected(cam, R, sky, radius_px)
    if not len(idx) or not len(x):
        return np.zeros(len(x), bool)
    d, _ = cKDTree(np.column_stack([sx, sy])).query(np.column_stack([x, y]))
    return d <= radius_px


def renderer_at(cfg, attitudes, table=None):
    """A NumPy renderer of ``cfg`` whose frame i is at ``attitudes[i]`` (ra, dec, roll, deg; a fourth entry, the
    frame's exposure scale, is :func:`_render_stats`'s), full-resolution read-outs kept: the fitted camera seen where
    the real frames were."""
    from skygen.config import build_config, config_dict
    from skygen.render.frame import Renderer

    d = config_dict(cfg)
    ra, dec, roll = (tuple(float(a[i]) for a in attitudes) for i in range(3))
    d["attitude"] = {**d["attitude"], "mode": "list", "ra_deg": ra, "dec_deg": dec, "roll_deg": roll}
    d["n_frames"] = len(attitudes)
    d["output"] = {**d["output"], "full_res": True}
    d["render"] = {**d["render"], "backend": "numpy", "device": "cpu"}
    return Renderer(build_config(d), catalog=table)


def at_exposure(cfg, scale: float):
    """``cfg`` with ``sensor.exposure_s`` times ``scale`` (``cfg`` itself at 1): a frame taken at another exposure or
    gain than the camera's pooled one (its stars, sky, dark current and particle hits all scale with it)."""
    if scale == 1.0:
        return cfg
    return dataclasses.replace(cfg, sensor=dataclasses.replace(cfg.sensor, exposure_s=cfg.sensor.exposure_s * scale))


#: frames of several exposures are rendered each at its own, rounded to this step (mag): one renderer per step
EXPOSURE_STEP_MAG = 0.05


def frame_exposure_scales(zps, pooled: float, spread_mag: float) -> list[float] | None:
    """Each frame's exposure relative to the camera's pooled one, from its own zero point ``zps[k]`` and the pooled
    ``pooled`` (mag), rounded to :data:`EXPOSURE_STEP_MAG`; 1 where a frame has no zero point of its own. None where
    the finite zero points span at most ``spread_mag`` (frames of one exposure: every frame renders the pooled one).
    A set of 20 ms and 100 ms frames rendered at one exposure compares unlike frames: the short ones' renders
    detect what the long ones do."""
    z = np.asarray(zps, dtype=np.float64)
    ok = np.isfinite(z)
    if ok.sum() < 2 or not np.isfinite(pooled) or np.ptp(z[ok]) <= spread_mag:
        return None
    steps = np.where(ok, np.round((z - pooled) / EXPOSURE_STEP_MAG), 0.0)
    return [float(10 ** (0.4 * EXPOSURE_STEP_MAG * k)) for k in steps]


def _render_stats(cfg, attitudes, table, sat, skip: int = 0) -> list[dict]:
    """Frames rendered at ``attitudes`` (ra, dec, roll[, exposure scale]) with ``cfg``, measured like the real ones;
    the first ``skip`` of them not rendered (frame i's noise depends on i and the config alone: :func:`check_stats`
    adds renders). An attitude's fourth entry renders that frame at ``cfg``'s exposure times it
    (:func:`frame_exposure_scales`: frames of several exposures compared each with its own)."""
    from skygen.real.fit_fixed import detected_near
    from skygen.real.fit_fixed import near_any as near_fixed
    from skygen.real.fit_pixels import zero_point
    from skygen.real.frame_stats import frame_stats, nonstar_brightest

    scales = [float(a[3]) if len(a) > 3 else 1.0 for a in attitudes]
    renderers = {s: renderer_at(at_exposure(cfg, s), attitudes, table) for s in sorted(set(scales[skip:]))}
    rows = []
    for i in range(skip, len(attitudes)):
        r = renderers[scales[i]]
        c = r.cfg
        det_cfg = c.detection
        f = r.render(i)
        img = f.image_full.astype(np.float32)
        st, det = frame_stats(img, det_cfg.threshold_sigma, det_cfg.min_area_px, det_cfg.background_box_px, sat)
        from skygen.instrument.detect import match

        mx, my = r.camera.unshift(det["x_px"], det["y_px"], det["flux_adu"], st["noise_adu"])  # as the real frames'
        sidx = match(mx, my, f.stars["x_px"], f.stars["y_px"], f.stars["electrons"], 2.0)
        ok = sidx >= 0
        star = np.zeros(len(sidx), bool)
        star[ok] = f.stars["hip_id"][sidx[ok]] >= 0  # a false star is no catalogue star
        extra = {"nonstar_brightest10": nonstar_brightest(det["flux_adu"], ~star)}
        extra["catalogue_detections"] = int(star.sum())
        extra["false_star_detections"] = int((ok & ~star).sum())  # the fitted corruptions.false_stars detected
        extra["sharp_sources"] = sharp_sources(det, star, st["background_adu"], sat)
        extra["_detection_limit_mag"] = r.detection_limit_mag
        # the false stars' own brightness: the sources fixed on the sensor (rendered too) are none of them
        fixed = near_fixed(det["x_px"], det["y_px"], [{"x_px": q[0], "y_px": q[1]} for q in c.sensor.fixed_sources])
        extra["_unexplained_flux"] = point_source_flux(det, ~star & ~fixed, st["background_adu"], sat)
        extra["_fixed_flux"] = detected_near(det["x_px"], det["y_px"], det["flux_adu"], c.sensor.fixed_sources)
        w, h = c.camera.width_px, c.camera.height_px  # the catalogue stars on the sensor, found or not
        sx, sy = np.asarray(f.stars["x_px"]), np.asarray(f.stars["y_px"])
        cat = np.flatnonzero((f.stars["hip_id"] >= 0) & (sx >= 3) & (sx <= w - 4) & (sy >= 3) & (sy <= h - 4))
        extra["_star_mag"] = np.asarray(f.stars["mag"], dtype=np.float64)[cat]
        extra["_star_found"] = np.isin(cat, sidx[ok])
        extra["half_detected_mag"] = half_detected_mag(extra["_star_mag"], extra["_star_found"])
        extra["centroid_sigma_px"] = centroid_scatter(  # the detector's own, against the true places
            det["x_px"][star] - f.stars["x_px"][sidx[star]], det["y_px"][star] - f.stars["y_px"][sidx[star]]
        )
        # the zero point from catalogue stars, as on the frames: a false star's magnitude is drawn, not catalogued,
        # and through a tone curve a star's zero point depends on its magnitude (the false stars are the faint ones)
        zp, n = zero_point(
            det["flux_adu"][star].astype(float),
            f.stars["mag"][sidx[star]].astype(float),
            det["peak_adu"][star].astype(float),
            np.full(int(star.sum()), st["background_adu"]),
            sat,
        )
        unsat = star & (det["peak_adu"] + st["background_adu"] < 0.8 * sat)  # photometric scatter: _star_scatter
        extra["_phot"] = {
            "r2": r.camera.corner_r2(det["x_px"], det["y_px"])[unsat],
            "flux_adu": np.asarray(det["flux_adu"], dtype=np.float64)[unsat],
            "mag": np.asarray(f.stars["mag"], dtype=np.float64)[sidx[unsat]],
            "bv": np.asarray(f.stars["bv"], dtype=np.float64)[sidx[unsat]],
        }
        mags = np.sort(extra["_star_mag"])  # the tenth-brightest catalogue star on the sensor: cap_bright_tail
        extra["_tenth_mag"] = float(mags[9]) if len(mags) >= 10 else float("nan")
        rows.append({**st, **extra, "zero_point_mag": zp, "zero_point_stars": n, "_image": img if i == 0 else None})
    return rows


#: the renders fit-camera's check compares with the frames: each compared frame's attitude rendered this many times
#: in all, each with its own noise, false stars and jitter (at least once and at most CHECK_REPEATS_MAX times each).
#: One render per frame of the eleven creusot-16mm frames gave detection ratios from 1.14 to 1.37 over eight seeds
#: (benchmarks/render_check.py): medians over a few renders are what a verdict at 25 % can rest on
CHECK_RENDERS = 32
CHECK_REPEATS_MAX = 4


def check_stats(cfg, attitudes, table, sat, first: list[dict]) -> list[dict]:
    """The renders a verdict rests on (:func:`skygen.real.frame_stats.check_renders`): ``first`` (one render of
    each of ``attitudes`` with ``cfg``, as :func:`_render_stats` gave them) and the further renders of each
    attitude up to :data:`CHECK_RENDERS` in all; each row's ``render_pass`` says which pass over the attitudes it is."""
    n = len(attitudes)
    reps = int(np.clip(np.ceil(CHECK_RENDERS / max(n, 1)), 1, CHECK_REPEATS_MAX))
    more = _render_stats(cfg, list(attitudes) * reps, table, sat, skip=n) if reps > 1 else []
    rows = [dict(r) for r in first] + more
    for i, r in enumerate(rows):
        r["render_pass"] = i // max(n, 1)
    return rows


def centroid_scatter(dx: np.ndarray, dy: np.ndarray) -> float:
    """Per-axis rms of centroid offsets (px), those beyond 3.5 robust sigma left out as the geometry fit leaves
    them out of its residual (:func:`skygen.real.fit_geometry.fit_geometry`); NaN with fewer than 3."""
    r = np.hypot(np.asarray(dx, np.float64), np.asarray(dy, np.float64))
    if r.size < 3:
        return float("nan")
    from skygen.real.fit_geometry import residual_cut

    keep = r < residual_cut(r)
    return float(np.sqrt(np.mean(r[keep] ** 2) / 2))


def image_size(w: int, h: int, want: int = 256) -> int:
    """The stored width: the largest divisor of ``w`` <= ``want`` whose factor also divides ``h`` (else ``w``)."""
    for size in range(min(want, w), 7, -1):
        if w % size == 0 and h % (w // size) == 0:
            return size
    return w
