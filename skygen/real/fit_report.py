"""What ``skygen fit-camera`` writes: the camera YAML and the report (``REPORT.md``, ``fit.json``, ``fit.png``).

Every number in them comes from the fit record (:func:`skygen.real.fit_camera.fit_camera`); files are
written atomically (:mod:`skygen.runtime`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

SECTIONS = ("camera", "optics", "photometry", "sensor", "corruptions", "detection", "catalog", "output")


def read_fit(folder, option: str = "--report") -> dict:
    """The record ``skygen fit-camera --report FOLDER`` wrote (``FOLDER/fit.json``), with at least one solved frame;
    a :class:`skygen.errors.ConfigError` naming ``option`` and what to give otherwise (the benchmarks that re-render
    a fit)."""
    import json

    from skygen.errors import ConfigError

    path = Path(folder) / "fit.json"
    if not path.is_file():
        raise ConfigError(f"{option} {folder}: no fit.json (give the folder skygen fit-camera --report wrote)")
    fit = json.loads(path.read_text())
    if not fit.get("solved"):
        raise ConfigError(f"{path}: no solved frame")
    return fit


def renders_of_fit(folder, n: int, option: str = "--report") -> tuple:
    """(fit record, value scale, rows, renderer): :func:`read_fit`'s record, the frames' value scale (12-bit data
    stored x 16: 16), up to ``n`` of its solved frames spread evenly and a renderer of the fitted camera whose frame i
    is at rows[i]'s attitude (the benchmarks that compare a fit's frames with its renders)."""
    from skygen.config import build_config
    from skygen.real.fit_render import renderer_at, spread_evenly

    fit = read_fit(folder, option)
    solved = fit["solved"]
    rows = [solved[k] for k in spread_evenly(len(solved), n)]
    renderer = renderer_at(build_config(fit["config"]), [(r["ra_deg"], r["dec_deg"], r["roll_deg"]) for r in rows])
    return fit, float(fit.get("value_scale") or 1.0), rows, renderer


def write_camera_yaml(path, cfg, record: dict, command: str) -> None:
    """The fitted camera as a camera file (checked by loading it back)."""
    import yaml

    from skygen.config import config_dict, load_config
    from skygen.runtime import atomic_write_text

    d = config_dict(cfg)
    body = {s: {k: v for k, v in d[s].items() if v is not None} for s in SECTIONS}
    body["epoch_yr"] = d["epoch_yr"]
    g = record["geometry"]
    fixed = "; ".join(f"{k} fixed ({v})" for k, v in g["fixed"].items()) or "none fixed"
    head = [
        f"# Fitted by skygen fit-camera from {len(record['solved'])} solved of "
        f"{len(record['frames'])} usable frames ({record['created_utc']}):",
        f"#   {command}" if command else "#   (from Python: skygen.real.fit_camera.fit_camera)",
        f"# geometry: {g['n_matched']} matched stars, {g['rms_px']:.3f} px rms; horizontal field "
        f"{g['fov_deg']:.4f} deg; terms fitted: {', '.join(g['fitted'])}; {fixed}.",
        "# camera.centroid_sigma_px is that residual per axis (rms / sqrt 2): solvers take it as the least "
        "per-star centroid error of an attitude covariance (fusion.solve.base.attitude_covariance);",
        "# sensor.exposure_s is exposure x throughput relative to the start camera's aperture, transmission "
        "and QE; photometry.sky_mag_arcsec2 the measured background, optics.vignetting its fall to the corners, "
        "corruptions.stray_light its gradient;",
        "# corruptions.false_stars, false_star_slope and false_star_span_mag: the sources the catalogue lacks (stars "
        "fainter than it holds, ...), their number and brightness fitted to the detections no catalogue star explains.",
        "# Its report (residuals per frame and radial, real vs rendered statistics): --report DIR, by default "
        "OUT-report/ beside this file.",
    ]
    head += [f"# note: {n}." for n in record.get("notes", [])]
    if any((record.get("bright_shift") or {}).get(k) for k in ("px", "x_px", "y_px")):
        head.append(
            f"# {record['bright_shift']['note']} (fusion predict takes it off every detection before solving; "
            "renders draw it)."
        )
    tol = (record.get("bright_shift") or {}).get("match_tolerance") or {}
    if tol.get("px"):
        head.append(f"# camera.match_tol_px: {tol['note']}.")
    shared = (record.get("bright_shift") or {}).get("shared_error") or {}
    if shared.get("px") is not None:
        head.append(f"# camera.shared_sigma_px: {shared['note']}.")
    said = record.get("sensor", {}).get("said")
    if said:
        head.append(f"# sensor: {said}.")
    warn = record.get("warnings") or []
    if warn:
        head = [
            "# WARNING: renders of this camera contradict the frames it was fitted on: " + "; ".join(warn) + ".",
            "# (see the report's warning block; use it knowing which statistic is off)",
        ] + head
    text = "\n".join(head) + "\n" + yaml.safe_dump(body, sort_keys=False)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, text)
    load_config(path)  # refuses anything skygen render / fusion predict would refuse


def _fmt(v, nd=2):
    return "–" if v is None or (isinstance(v, float) and not np.isfinite(v)) else f"{v:.{nd}f}"


def markdown(r: dict) -> str:
    from skygen.real.fit_render import MIN_FALSE_STARS_FITTED

    g, px = r["geometry"], r["pixels"]
    cc = r["config"]["corruptions"]
    hw = r["hardware"]
    cpu = (
        (
            f"{hw.get('cpu_model', 'CPU')}, {hw.get('machine', '')}, {hw.get('usable_cores')} usable cores, "
            f"load {hw.get('load_average_1m', float('nan')):.1f}"
        )
        if isinstance(hw, dict)
        else str(hw)
    )
    lines = [
        "# skygen fit-camera report",
        "",
        f"`{r['command'] or 'skygen.real.fit_camera.fit_camera(...)'}` ({cpu}, {r['created_utc']}): "
        f"{len(r['frames'])} usable frames, {len(r['solved'])} solved; {r['timing_s']['total_s']:.1f} s in all "
        f"(solving {r['timing_s']['solve_s']:.1f} s, geometry done at {r['timing_s']['geometry_s']:.1f} s). "
        f"Frame values divided by {r['value_scale']} (the scale they carry); saturation {r['saturation_adu']:.0f} ADU.",
        "",
    ]
    lines += warning_block(r)
    if r.get("notes"):
        lines += [f"Note: {n}." for n in r["notes"]] + [""]
    if r["dropped"]:
        lines += ["Dropped frames:", ""] + [f"- `{d['frame']}`: {d['reason']}" for d in r["dropped"]] + [""]
    st = r["start"]
    lines += [
        "## Geometry",
        "",
        "Start: "
        + (
            f"`{st['camera_file']}`"
            if st["camera_file"]
            else f"field of view searched in {st['fov_range_deg']} deg"
            if st["fov_range_deg"]
            else "the field given (--fov)"
        )
        + " "
        f"(f = {st['f_px']:.1f} px, field {st['fov_deg']:.4f} deg, aspect {st['aspect']:.4f}).",
        "",
        "| term | fitted | 1σ |",
        "|---|---|---|",
    ]
    for t, v in (
        ("f", g["f_px"]),
        ("log_aspect", np.log(g["aspect"])),
        ("cx", g["cx_px"]),
        ("cy", g["cy_px"]),
        ("k1", g["k1"]),
        ("k2", g["k2"]),
    ):
        lines.append(f"| {t} | {v:.6g} | {g['sigma'][t]:.3g} |" if t in g["fitted"] else f"| {t} | {v:.6g} (fixed) | |")
    lines += [
        "",
        f"Horizontal field {g['fov_deg']:.4f} deg, vertical {g['fov_v_deg']:.4f} deg, pixel aspect "
        f"{g['aspect']:.5f}; {g['n_matched']} matched stars, residual **{g['rms_px']:.3f} px rms**.",
        "",
    ]
    for k, v in g["fixed"].items():
        lines.append(f"- {k} fixed: {v}")
    shift = r.get("bright_shift")
    if shift:  # skygen.real.fit_shift: bright stars detected farther out than faint ones, and how far they scatter
        rms = shift.get("geometry_rms_px")
        lines.append(
            f"- {shift['note']}"
            + (f"; the geometry fitted again with it taken off ({rms[0]:.3f} -> {rms[1]:.3f} px rms)" if rms else "")
        )
        if shift.get("match_tolerance"):
            lines.append(f"- {shift['match_tolerance']['note']} (camera.match_tol_px: the few-star solvers' window)")
        if shift.get("shared_error"):
            lines.append(
                f"- {shift['shared_error']['note']} (camera.shared_sigma_px: the attitude covariance adds it across "
                "the boresight)"
            )
    lines += [
        "",
        "| frame | solved field (deg) | matched | rms (px) | RA | Dec | roll | zero point (mag) | exposure × |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for f in r["solved"]:
        lines.append(
            f"| {f['frame']} | {f['solved_fov_deg']:.4f} | {f['matched']} | {f['rms_px']:.3f} | "
            f"{f['ra_deg']:.4f} | {f['dec_deg']:.4f} | {f['roll_deg']:.3f} | {_fmt(f.get('zero_point_mag'))} | "
            f"{_fmt(f.get('exposure_scale'))} |"
        )
    lines += [
        "",
        "Radial residuals (rms of the 2-D offset, px): "
        + ", ".join(
            f"{b['r_lo_px']:.0f}–{b['r_hi_px']:.0f} px: {_fmt(b['rms_px'], 3)} ({b['n']})" for b in g["radial"]
        ),
        "",
        "By catalogue magnitude (rms per axis, px): "
        + (
            ", ".join(
                f"{b['mag_lo']:.0f}–{b['mag_lo'] + 1:.0f}: {_fmt(b['rms_px'], 3)} ({b['n']})"
                for b in g.get("by_magnitude", [])
            )
            or "–"
        )
        + (
            f". Residuals of two stars within {g['neighbour_correlation']['within_px']:.0f} px in one frame correlate "
            f"{_fmt(g['neighbour_correlation']['corr'], 2)} ({g['neighbour_correlation']['n']} pairs; 0: a scatter "
            "drawn per star, 1: a field the camera model misses)"
            if "neighbour_correlation" in g
            else ""
        ),
        "",
        "## Pixels",
        "",
    ]
    lines += sensor_lines(r)
    psf = px["psf"]
    lines += [
        f"- background {px['level_adu']:.1f} ADU (median of box levels); fitted per frame as centre + gradient − "
        f"drop × r²: centre {px['centre_adu']:.1f} ADU, gradient {px['gradient_adu']:.1f} ADU edge to edge, drop "
        f"to the corner {px['corner_drop_adu']:.1f} ADU (optics.vignetting "
        f"{r['config']['optics']['vignetting']:.3f}), box levels off that surface by "
        f"{px['background_residual_adu']:.1f} "
        "ADU rms (medians over frames)",
        (
            f"- PSF from {psf['n_stars']} stars: Gaussian σ {psf['gaussian_sigma_px']:.3f} px; Moffat σ(FWHM) "
            f"{psf['moffat_sigma_px']:.3f} px, β {psf['moffat_beta']:.2f}; Moffat/Gaussian squared residual "
            f"{psf['moffat_over_gaussian_sse']:.2f} → **{psf['psf']}**"
        )
        if psf["ok"]
        else f"- PSF: {psf['why']}",
        f"- hot pixels: {px['hot']['n_static']} static ({px['hot']['fraction']:.2e} of pixels, in ≥ "
        f"{px['hot']['frames_needed']} frames), excess {px['hot']['excess_adu']:.0f} ADU",
        f"- zero point (Hp of a star giving 1 ADU of detected flux): {_fmt(r['zero_point_real_mag'], 3)} mag → "
        f"sensor.exposure_s {r['exposure_s']:.4g} s (exposure × throughput, after the corrections on renders)",
        f"- detector: threshold {r['detector']['threshold_sigma']:g} σ, background box "
        f"{r['detector']['background_box_px']} px ({r['detector']['catalogue_per_frame']:.1f} catalogue stars and "
        f"{r['detector']['other_per_frame']:.1f} other detections per frame)",
        (
            f"- sources the catalogue lacks (corruptions.false_stars {cc['false_stars']:.1f} per frame, "
            f"false_star_slope {cc['false_star_slope']:.2f}, false_star_span_mag {cc['false_star_span_mag']:.2f}): "
            f"{px['false_star_shape']['note']}"
            if px.get("false_star_shape", {}).get("n", 0) >= MIN_FALSE_STARS_FITTED
            else "- sources the catalogue lacks: "
            + (f"{px['false_star_shape']['note']}; " if px.get("false_star_shape") else "")
            + f"corruptions.false_stars {r['config']['corruptions']['false_stars']:.1f} per frame, the number that "
            "gives renders the frames' detections per frame, uniform over 4 mag above the detection limit"
        ),
        "- light fixed on the sensor (sensor.fixed_sources, skygen.real.fit_fixed): "
        + (
            "; ".join(
                f"at ({q['x_px']:.1f}, {q['y_px']:.1f}) px, {q['flux_adu']:.0f} ADU detected per frame (renders: "
                f"{q.get('rendered_adu', float('nan')):.0f}), sigma {q['sigma_px']:.1f} px, in {q['frames']} frames "
                f"from {q['pointings']} pointings"
                for q in px.get("fixed_sources", [])
            )
            or "none (no unexplained detection recurs at one place from 3 pointings beyond chance)"
        ),
        f"- a processor's black level: {px.get('black_level', {}).get('note', 'not looked for')}",
        f"- {px.get('tone', {}).get('note', 'a processor' + chr(39) + 's tone curve: not looked for')}",
        f"- blooming: {px.get('blooming', {}).get('note', 'not measured')}",
        f"- a processor's blur: {px.get('processor_blur', {}).get('note', 'not measured')}",
        f"- {px.get('star_jitter', {}).get('note', 'centroid scatter: not measured')}",
        f"- particle hits: {px.get('sharp_per_frame', float('nan')):.2f} sharp uncatalogued sources per frame → "
        f"corruptions.cosmic_rays {r['config']['corruptions']['cosmic_rays']:.3g} hits/cm²/s (per unit of "
        "sensor.exposure_s)",
        f"- optics.vignetting {r['config']['optics']['vignetting']:.3f} for the stars: "
        f"{px.get('star_vignetting', {}).get('note', 'not measured')}"
        + (
            f"; the background's own fall to the corners kept as optics.sky_vignetting "
            f"{r['config']['optics']['sky_vignetting']:.3f}"
            if r["config"]["optics"].get("sky_vignetting") is not None
            else ""
        ),
        f"- {px.get('star_scatter', {}).get('note', 'photometric scatter: not measured')}",
        "",
        "## Real against rendered (medians over frames; renders at the fitted attitudes)",
        "",
        f"{len(r['real_stats'])} frames compared (at most 16, spread evenly over the solved ones)"
        + (
            f", each rendered at its own exposure (× {min(xs):.2f} to × {max(xs):.2f} the camera's, from its own zero "
            "point: frames of several exposures or gains)"
            if (xs := r.get("check_exposure_scales"))
            else ""
        )
        + (
            f", each rendered {passes} times (a ratio's range over the passes in brackets: the renders' own noise)."
            if (passes := len({s.get("render_pass", 0) for s in r.get("fitted_stats") or []})) > 1
            else "."
        ),
        "",
        "| quantity | real | start camera | fitted camera | fitted / real | tolerance |",
        "|---|---|---|---|---|---|",
    ]
    lab = {
        "background_adu": "background (ADU)",
        "noise_adu": "noise σ (ADU)",
        "detections": "detections / frame",
        "catalogue_detections": "of which catalogue stars",
        "star_sigma_px": "star width σ (px)",
        "zero_point_mag": "zero point (mag)",
        "nonstar_brightest10": "non-catalogue among the brightest 10 (mean)",
        "sharp_sources": "sharp uncatalogued sources / frame (mean)",
        "half_detected_mag": "catalogue stars half detected down to (mag)",
    }
    verdict = {c["stat"]: c for c in r.get("checks") or []}
    for k, v in r["compare"].items():
        rel = (
            f"{v['fitted'] - v['real']:+.3f} mag"
            if k in ("zero_point_mag", "half_detected_mag")
            else f"{v['fitted'] - v['real']:+.2f}"
            if k in ("nonstar_brightest10", "sharp_sources")
            else f"{v['fitted'] / v['real']:.3f}"
            if v["real"] and np.isfinite(v["fitted"] / v["real"])
            else "–"
        )
        c = verdict.get(k)
        if c and c.get("passes"):  # the renders' own noise: each pass of renders over the frames alone
            rel += f" ({min(c['passes']):.3f}–{max(c['passes']):.3f})"
        tol = f"±{100 * c['tolerance']:.0f} % {'✓' if c['ok'] else '**✗**'}" if c else ""
        lines.append(f"| {lab[k]} | {_fmt(v['real'])} | {_fmt(v['start'])} | {_fmt(v['fitted'])} | {rel} | {tol} |")
    lines += correction_lines(r.get("correction"))
    lines += [
        "",
        "Statistics are measured the same way on both (skygen.real.frame_stats): background and noise by the "
        "whole-frame sigma-clipped estimator, detections with the fitted detector settings, star width as "
        "the second moment in 9 × 9 px, zero point from matched stars.",
        "",
        "![fit](fit.png)",
        "",
    ]
    return "\n".join(lines)


def correction_lines(corr: dict | None) -> list[str]:
    """The report's account of the correction rounds (:func:`skygen.real.fit_render.fit_model_terms`, at most two):
    what missed, what was changed, whether it was kept, and where it was undone, what its renders gave instead."""
    if not corr:
        return []
    lines = [""]
    for step, (missed, done, undone) in zip(
        (corr, corr.get("second")),
        (
            ("The first renders missed", "Corrected once", "the first fit stands (the table is the first fit's)"),
            ("They still missed", "Corrected again", "the first correction stands (the table is its)"),
        ),
    ):
        if not step:
            break
        kept = step.get("kept", True)
        lines.append(
            f"{missed}: "
            + "; ".join(c["why"] for c in step["checks_before"] if not c["ok"])
            + f". {done}: "
            + "; ".join(step["changed"])
            + (". The table is after it." if kept else f"; its renders missed by more, so {undone}.")
        )
        if step.get("checks_after") and not kept:
            lines.append(
                "The corrected renders gave: "
                + "; ".join(f"{c['label']} {c['ratio']:.3f} x {'✓' if c['ok'] else '✗'}" for c in step["checks_after"])
                + "."
            )
    return lines


def warning_block(r: dict) -> list[str]:
    """The report's top block when the renders contradict the frames (each statistic off, by how much)."""
    warn = r.get("warnings") or []
    if not warn:
        return []
    return (
        ["> **WARNING: renders of this camera contradict the frames it was fitted on.**", ">"]
        + [f"> - {w}" for w in warn]
        + [
            ">",
            "> The camera file was written; these statistics of its renders are off by more than issue 35's tolerances "
            '(background 10 %, σ 15 %, star width 10 %, detections 25 %). See "Real against rendered".',
            "",
        ]
    )


def sensor_lines(r: dict) -> list[str]:
    """The sensor's lines of the Pixels section: the mean-variance line, what was refused and what was used."""
    mv, sen = r["mean_variance"], r.get("sensor", {})
    px = r["pixels"]
    out = []
    if "slope" in mv:
        out.append(
            f"- mean–variance over {mv['boxes']} of {mv['boxes_all']} background boxes (levels spanning "
            f"{mv['level_span_adu']:.3g} ADU, lever arm {mv['lever_adu']:.3g} ADU rms): var = "
            f"{mv['intercept_adu2']:.3f} + {mv['slope']:.4f} × level, slope ±{100 * mv['slope_rse']:.1f} %"
            + (
                f" → gain {mv['gain_e_per_adu']:.3f} e-/ADU, bias {mv['bias_adu']:.1f} ADU, read noise "
                f"{mv['read_noise_e']:.2f} e- ({mv['note']})"
                if "gain_e_per_adu" in mv
                else ""
            )
        )
    if sen.get("said"):
        out.append(f"- **{sen['said']}**")
    out.append(
        f"- sensor used ({px.get('sensor_method', 'mean-variance')}): gain {px['gain_e_per_adu']:.3f} e-/ADU, "
        f"bias {px['bias_adu']} ADU, read noise {px['read_noise_e']:.2f} e-, FPN {px.get('fpn_adu', float('nan')):.2f} "
        f"ADU; background at the centre {px.get('background_e', float('nan')):.4g} e- (the model's level there equals "
        "the measured one)"
    )
    dark = r["config"]["sensor"]["dark_current_e_s"]
    start_dark = r.get("start", {}).get("dark_current_e_s")
    if start_dark is not None and dark < start_dark:
        out.append(
            f"- dark current lowered from {start_dark:.4g} to {dark:.4g} e-/s: the start camera's dark charge "
            "alone would have outshone the darkest background"
        )
    return out


def write_report(folder, record: dict, real_example: list, g) -> None:
    from skygen.runtime import atomic_write_text, write_json

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rec = {k: v for k, v in record.items() if not k.startswith("_")}
    write_json(folder / "fit.json", rec)
    _plot(folder / "fit.png", record, real_example, g)
    atomic_write_text(folder / "REPORT.md", markdown(record))


def _plot(path, record, real_example, g) -> None:
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    from skygen.runtime import atomic_path

    fig, ax = plt.subplots(1, 4, figsize=(18, 4))
    import os

    full = [f["frame"] for f in record["solved"]]
    cut = len(os.path.commonprefix(full)) if len(full) > 1 else 0
    names = [n[cut:][:28] for n in full]
    ax[0].bar(range(len(names)), [f["rms_px"] for f in record["solved"]])
    ax[0].set_xticks(range(len(names)), names, rotation=70, fontsize=6)
    ax[0].set_ylabel("residual rms (px)")
    ax[0].set_title("per frame")
    allr, allp = np.concatenate(g.residuals), np.concatenate(g.positions)
    cam = g.camera
    rad = np.hypot(allp[:, 0] - cam.cx_px, (allp[:, 1] - cam.cy_px) * cam.aspect)
    ax[1].scatter(rad, np.hypot(allr[:, 0], allr[:, 1]), s=4)
    ax[1].set_xlabel("distance from principal point (px)")
    ax[1].set_ylabel("|residual| (px)")
    ax[1].set_title(f"radial, {record['geometry']['rms_px']:.3f} px rms")
    for a, img, title in (
        (ax[2], real_example[0] if real_example else None, "real"),
        (ax[3], record.get("_render_example"), "rendered, fitted camera"),
    ):
        if img is None:
            a.axis("off")
            continue
        lo, hi = np.percentile(img, [1, 99.8])
        a.imshow(np.clip((img - lo) / max(hi - lo, 1), 0, 1) ** 0.5, cmap="gray")
        a.set_title(title)
        a.axis("off")
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=80, bbox_inches="tight")
    plt.close(fig)
