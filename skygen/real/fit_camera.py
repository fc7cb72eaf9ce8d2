"""``skygen fit-camera``: a camera file fitted to a real sensor from its own frames.

    skygen fit-camera FRAME... --out camera.yaml [--camera START.yaml | --fov-range LO HI] [--pixel-pitch UM]
                      [--pixel-aspect A] [--epoch YEAR] [--report DIR]

1. Read the frames (:mod:`skygen.real.frames`); all must have one size. Values are divided by the scale
   they carry (:func:`skygen.real.fit_pixels.value_scale`: 12-bit data stored x16 in 16-bit TIFF).
   Blank (constant) and saturated frames, colour and unreadable files are dropped with the reason.
2. Detect stars (skygen's detector, 5 sigma, >= 3 px, a background per 64 px box) and solve each
   frame lost-in-space with tetra3rs (:mod:`skygen.real.platesolve`): from the start camera, or, with
   ``--fov-range`` (default without a camera file: 5-30 deg), searching the horizontal field in that
   range (the first search of a range builds and caches a database: ~20 s for 5-30 deg). Unsolved frames are dropped with
   the solver's reason.
3. Geometry (:mod:`skygen.real.fit_geometry`): detections matched to skygen's catalogue (Hipparcos-2 at the
   epoch); focal length, pixel aspect, principal point, k1 (k2) and every frame's attitude fitted
   together by least squares; terms the data cannot constrain are fixed, and the report says why.
4. Pixels (:mod:`skygen.real.fit_pixels`): background level and gradient, gain/bias/read noise from the
   mean-variance relation, PSF (Gaussian or Moffat), hot pixels, the photometric zero point.
5. Detector settings: the threshold and background box that find the most catalogue stars net of
   other detections on these frames. Real frames show stars fainter than the catalogue's
   completeness; the detections they have beyond renders of the fitted camera (median per frame)
   become ``corruptions.false_stars`` (point sources at random places up to the detection limit).
6. The model's own terms: electrons from the gain; the zero point becomes ``sensor.exposure_s``
   (exposure x throughput: the start camera's aperture, transmission and QE are kept, so the fitted
   exposure absorbs the atmosphere and any other loss); the background becomes
   ``photometry.sky_mag_arcsec2`` (after the start camera's dark current), its fall towards the
   corners ``optics.vignetting``, the gradient ``corruptions.stray_light`` (a ramp of the same size,
   random direction). Frames are then rendered
   at the fitted attitudes and the exposure corrected once so that the zero point measured on the
   renders equals the real one (the detector's flux is not a star's whole flux).
7. Write the camera YAML (checked by loading it with :func:`skygen.config.load_config`) and a report
   (``REPORT.md``, ``fit.json``, ``fit.png``): residuals per frame and radial, real against rendered
   statistics for the start camera (when given) and the fitted one.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from skygen.instrument.camera import Camera
from skygen.errors import ConfigError, SkygenError

BOX_PX = 64                 # background box of detection and pixel statistics
DETECT = {"threshold_sigma": 5.0, "min_area_px": 3}
THRESHOLDS = (3.0, 4.0, 5.0, 6.0, 8.0)
DEFAULT_FOV_RANGE = (5.0, 30.0)     # searched when neither a camera file nor a range is given
PITCH_DEFAULT_UM = 5.5              # skygen's default camera's pixel pitch
BOXES = (0, BOX_PX)


class FitError(SkygenError):
    """The frames cannot give a camera (none solved, too few usable)."""


# ----------------------------------------------------------------------------------- input
def read_frames(paths: list[str], log) -> tuple[list[str], list[np.ndarray], list[tuple[str, str]]]:
    """(names, images, dropped): unreadable, colour or empty files are dropped with their one-line reason;
    frames of different sizes are refused."""
    from skygen.real.frames import FrameError, frame_files, read_frame
    files: list[Path] = []
    for p in paths:
        path = Path(p)
        files += frame_files(path) if path.is_dir() else [path]
    names, imgs, dropped = [], [], []
    for f in files:
        try:
            imgs.append(read_frame(f))
            names.append(str(f))
        except FrameError as exc:
            dropped.append((str(f), str(exc)))
            log(f"fit-camera: dropped {exc}")
    if not imgs:
        raise FitError("no readable frame" + (f" (first problem: {dropped[0][1]})" if dropped else ""))
    shapes = {}
    for n, im in zip(names, imgs):
        shapes.setdefault(im.shape, []).append(Path(n).name)
    if len(shapes) > 1:
        parts = "; ".join(f"{w} x {h} px: {', '.join(v[:3])}{' ...' if len(v) > 3 else ''}"
                          for (h, w), v in shapes.items())
        raise ConfigError(f"frames of different sizes in one calibration ({parts}); give frames of one camera "
                          "and read-out mode")
    return names, imgs, dropped


def usable(img: np.ndarray, saturation: float) -> str:
    """'' or why a frame cannot be used (blank, saturated)."""
    at_top = float(np.mean(img >= saturation))
    if at_top > 0.25:
        return f"saturated frame ({100 * at_top:.0f} % of pixels at the top of the range, {saturation:g})"
    if float(img.max()) == float(img.min()):
        return f"blank frame (every pixel {float(img.min()):g})"
    return ""


def start_config(camera, fov_range, pixel_pitch_um, pixel_aspect, shape):
    """The start config: the camera file, or a camera of the frames' size with the range's middle field."""
    from skygen.config import build_config, load_config
    h, w = shape
    if camera is not None:
        if fov_range is not None:
            raise ConfigError("give --camera START.yaml or --fov-range LO HI, not both")
        cfg = load_config(camera)
        if pixel_aspect is not None:
            cfg = dataclasses.replace(cfg, camera=dataclasses.replace(cfg.camera, pixel_aspect=pixel_aspect))
        if (cfg.camera.width_px, cfg.camera.height_px) != (w, h):
            raise ConfigError(f"{camera}: camera is {cfg.camera.width_px} x {cfg.camera.height_px} px but the frames "
                              f"are {w} x {h} px (width x height); give the camera of these frames")
        return cfg
    lo, hi = fov_range
    if not 0 < lo < hi < 120:
        raise ConfigError(f"--fov-range {lo:g} {hi:g}: give 0 < LO < HI < 120 degrees (horizontal field)")
    if not 0 < pixel_pitch_um <= 100:
        raise ConfigError(f"--pixel-pitch {pixel_pitch_um:g}: pixel width in micrometres, > 0 and <= 100")
    data = {"camera": {"width_px": w, "height_px": h, "pixel_pitch_um": pixel_pitch_um, "fov_deg": 0.5 * (lo + hi),
                       "pixel_aspect": pixel_aspect or 1.0},
            "output": {"image_size_px": _image_size(w, h)}}
    return build_config(data)


def _image_size(w: int, h: int, want: int = 256) -> int:
    """The stored width: the largest divisor of ``w`` <= ``want`` whose factor also divides ``h`` (else ``w``)."""
    for size in range(min(want, w), 7, -1):
        if w % size == 0 and h % (w // size) == 0:
            return size
    return w


# ----------------------------------------------------------------------------------- the fit
def fit_camera(paths: list[str], out: str | Path, *, camera=None, fov_range=None, pixel_pitch_um=None,
               pixel_aspect=None, epoch_yr=None, report_dir=None, command: str = "", log=print) -> dict:
    """Fit a camera to ``paths`` (see the module doc); writes ``out`` and the report; returns the fit record."""
    from skygen.real import fit_geometry as G
    from skygen.real import fit_pixels as P
    from skygen.sky.catalog import SkyIndex, load_catalog
    from skygen.instrument.detect import detect
    from skygen.real.platesolve import load_database
    t0 = time.perf_counter()
    if pixel_aspect is not None and not 0.1 <= pixel_aspect <= 10:
        raise ConfigError(f"--pixel-aspect {pixel_aspect:g}: pixel height / width between 0.1 and 10")
    notes = []
    if camera is None and fov_range is None:
        fov_range = DEFAULT_FOV_RANGE
        notes.append(f"no --camera or --fov-range: the horizontal field was searched in {fov_range[0]:g}-"
                     f"{fov_range[1]:g} deg")
    if camera is None and pixel_pitch_um is None:
        pixel_pitch_um = PITCH_DEFAULT_UM
        notes.append(f"no --pixel-pitch: {pixel_pitch_um:g} um assumed (only camera.focal_length_mm depends on it; "
                     "the field, and so every render, does not)")
    for n in notes:
        log(f"fit-camera: {n}")
    names, raw, dropped = read_frames(paths, log)
    scale, bits, sat = P.value_scale(raw)
    imgs = [im / scale for im in raw]
    keep = []
    for n, im in zip(names, imgs):
        why = usable(im, sat)
        if why:
            dropped.append((n, why))
            log(f"fit-camera: dropped {n}: {why}")
        else:
            keep.append((n, im))
    if not keep:
        raise FitError("no usable frame: " + "; ".join(f"{Path(n).name}: {w}" for n, w in dropped[:4]))
    names, imgs = [k[0] for k in keep], [k[1] for k in keep]
    cfg0 = start_config(camera, fov_range, pixel_pitch_um, pixel_aspect, imgs[0].shape)
    cam0 = Camera.from_config(cfg0.camera)
    epoch = float(epoch_yr if epoch_yr is not None else cfg0.epoch_yr)
    if fov_range is None:
        db = load_database(cam0.fov_deg[0], log=log)
    else:
        db = load_database(fov_range[0], log=log, fov_max_deg=fov_range[1])
    table = load_catalog(cfg0.catalog.path)
    sky = SkyIndex(table, epoch, 10.0)
    bgs, frames = [], []
    for n, im in zip(names, imgs):
        bgs.append(P.background(im, BOX_PX))
        det, _, _ = detect(im, DETECT["threshold_sigma"], DETECT["min_area_px"], 200, BOX_PX)
        R, fov, why = G.solve_frame(db, det, cam0, fov_range)
        frames.append(G.FrameSolution(n, det, R, fov, why))
        if why:
            dropped.append((n, why))
            log(f"fit-camera: dropped {n}: {why}")
    solved = [fs for fs in frames if fs.solved]
    if not solved:
        raise FitError(f"no frame solved ({len(dropped)} dropped): " + "; ".join(
            f"{Path(n).name}: {why}" for n, why in dropped[:3]) + (" ..." if len(dropped) > 3 else ""))
    t_solve = time.perf_counter() - t0
    start_cam = cam0
    if fov_range is not None:                       # the field the solver found is the fit's start
        fov = float(np.median([fs.fov_deg for fs in solved]))
        start_cam = dataclasses.replace(cam0, f_px=cam0.width_px / 2 / np.tan(np.radians(fov) / 2))
    g = G.fit_geometry(solved, start_cam, sky, 6.0, log=lambda m: None)
    for fs, R in zip(solved, g.rotations):
        fs.R = R
    g = G.fit_geometry(solved, g.camera, sky, 2.5, log=log)
    cam = g.camera
    t_geom = time.perf_counter() - t0
    # ------------------------------------------------------------------ pixels
    mv = P.gain_from_mean_variance(np.concatenate([b["box_level"] for b in bgs]),
                                   np.concatenate([b["box_sigma"] for b in bgs]) ** 2,
                                   cfg0.sensor.read_noise_e, cfg0.sensor.fpn_adu, cfg0.sensor.bias_adu)
    if mv["ok"]:
        gain, bias, read = mv["gain_e_per_adu"], mv["bias_adu"], mv["read_noise_e"]
    else:
        gain, bias, read = cfg0.sensor.gain_e_per_adu, float(cfg0.sensor.bias_adu), cfg0.sensor.read_noise_e
        log(f"fit-camera: gain, bias and read noise kept from the start camera: {mv['why']}")
    by_name = {n: i for i, n in enumerate(names)}
    sidx = [by_name[fs.name] for fs in solved]
    matched = [fs.det_index[m] for fs, m in zip(solved, g.keep)]
    psf = P.psf_fit([imgs[i] for i in sidx], [bgs[i]["level_map"] for i in sidx], [fs.det for fs in solved],
                    matched, cam.aspect, sat)
    hot = P.hot_pixels(imgs, [b["level_map"] for b in bgs], [b["sigma_map"] for b in bgs])
    zp_real, stars = _zero_point_real(solved, g, [bgs[i] for i in sidx], sat)
    settings = choose_detector(solved, [imgs[i] for i in sidx], cam, g.rotations, sky)
    level = float(np.median([b["level_adu"] for b in bgs]))
    gradient = float(np.median([b["gradient_adu"] for b in bgs]))
    meas = {"gain_e_per_adu": gain, "bias_adu": bias, "read_noise_e": read, "level_adu": level,
            "centre_adu": float(np.median([b["centre_adu"] for b in bgs])),
            "corner_drop_adu": float(np.median([b["corner_drop_adu"] for b in bgs])),
            "background_residual_adu": float(np.median([b["residual_std_adu"] for b in bgs])), "gradient_adu": gradient, "bits": bits, "psf": psf, "hot": hot, "settings": settings}
    exposure = _exposure_from_stars(cfg0, stars, gain)
    attitudes = [G.radec_roll(R) for R in g.rotations]
    real_stats = [_measure_real(imgs[i], settings, sat, fs, g, k) for k, (i, fs) in enumerate(zip(sidx, solved))]
    cfg = build_fitted(cfg0, cam, meas, exposure, pixel_pitch_um)
    render_zp = _render_stats(cfg, attitudes, table, sat)
    zp_sim = float(np.nanmedian([r["zero_point_mag"] for r in render_zp]))
    if np.isfinite(zp_sim) and np.isfinite(zp_real):
        exposure *= 10 ** (0.4 * (zp_real - zp_sim))
        cfg = build_fitted(cfg0, cam, meas, exposure, pixel_pitch_um)
    # stars the catalogue lacks (Hipparcos is complete to about V 8; a real frame shows fainter ones): the
    # detections real frames have beyond the renders' become corruptions.false_stars (point sources at
    # random places, magnitudes up to the detection limit)
    render_det = _render_stats(cfg, attitudes, table, sat)
    deficit = float(np.median([a["detections"] - b["detections"] for a, b in zip(real_stats, render_det)]))
    meas["faint_sources_per_frame"] = max(deficit, 0.0)
    if deficit > 0:
        cfg = build_fitted(cfg0, cam, meas, exposure, pixel_pitch_um)
    after = _render_stats(cfg, attitudes, table, sat) if deficit > 0 else render_det
    before = _render_stats(cfg0, attitudes, table, 2 ** cfg0.sensor.bit_depth - 1) if camera is not None else None
    t_total = time.perf_counter() - t0
    record = _record(names, dropped, solved, g, cam0, cam, mv, meas, zp_real, exposure, real_stats, before, after,
                     cfg, scale, sat, fov_range, camera, command, {"solve_s": t_solve, "geometry_s": t_geom,
                                                               "total_s": t_total}, epoch)
    record["notes"] = notes
    from skygen.real.fit_report import write_camera_yaml, write_report
    write_camera_yaml(out, cfg, record, command)
    if report_dir is not None:
        write_report(report_dir, record, [imgs[i] for i in sidx][:1], g)
    return record


def _zero_point_real(solved, g, bgs, sat):
    """Zero point of the real frames and the matched unsaturated stars (flux ADU, Hp, B-V)."""
    from skygen.real.fit_pixels import zero_point
    flux, mag, bv, peak, lev = [], [], [], [], []
    for fs, m, b in zip(solved, g.keep, bgs):
        d = fs.det_index[m]
        flux.append(fs.det["flux_adu"][d])
        peak.append(fs.det["peak_adu"][d])
        xi = np.clip(np.round(fs.det["x_px"][d]).astype(int), 0, b["level_map"].shape[1] - 1)
        yi = np.clip(np.round(fs.det["y_px"][d]).astype(int), 0, b["level_map"].shape[0] - 1)
        lev.append(b["level_map"][yi, xi])
        mag.append(fs.star_mag[m])
        bv.append(fs.star_bv[m])
    flux, mag, bv, peak, lev = (np.concatenate(a).astype(float) for a in (flux, mag, bv, peak, lev))
    zp, n = zero_point(flux, mag, peak, lev, sat)
    ok = (flux > 0) & (peak + lev < 0.8 * sat)
    return zp, {"flux_adu": flux[ok], "mag": mag[ok], "bv": bv[ok], "n": n}


def _exposure_from_stars(cfg0, stars, gain) -> float:
    """First estimate of exposure x throughput: detected electrons / the model's electrons per second."""
    from skygen.instrument.photometry import Photometry
    if stars["n"] == 0:
        return cfg0.sensor.exposure_s
    ph = Photometry.from_config(cfg0.optics, cfg0.photometry, cfg0.sensor)
    e_s = ph.electrons_per_s(stars["mag"], stars["bv"])
    return float(np.clip(np.median(stars["flux_adu"] * gain / e_s), 1e-4, 3600))


def choose_detector(solved, imgs, cam, rotations, sky) -> dict:
    """Threshold and background box that maximise (catalogue stars found) - (other detections)."""
    from scipy.spatial import cKDTree
    from skygen.instrument.detect import detect
    trees = []
    for fs, R in zip(solved, rotations):
        idx = sky.cone(R[:, 2], cam.corner_radius_rad() + 0.01)
        x, y, front = cam.project(sky.vectors[idx] @ R)
        ok = front & cam.inside(x, y)
        trees.append(cKDTree(np.column_stack([x[ok], y[ok]])) if ok.any() else None)
    rows = []
    for box in BOXES:
        for thr in THRESHOLDS:
            found = other = 0
            for im, tree in zip(imgs, trees):
                det, _, _ = detect(im, thr, DETECT["min_area_px"], 100_000, box)
                if tree is None or not len(det["x_px"]):
                    other += len(det["x_px"])
                    continue
                d, _ = tree.query(np.column_stack([det["x_px"], det["y_px"]]))
                found += int(np.sum(d <= 2.0))
                other += int(np.sum(d > 2.0))
            rows.append({"threshold_sigma": thr, "background_box_px": box, "catalogue_per_frame": found / len(imgs),
                         "other_per_frame": other / len(imgs), "score": (found - other) / len(imgs)})
    best = max(rows, key=lambda r: (r["score"], r["threshold_sigma"]))
    return {**best, "min_area_px": DETECT["min_area_px"], "grid": rows}


def build_fitted(cfg0, cam: Camera, meas: dict, exposure: float, pixel_pitch_um=None):
    """The fitted config: the start config with the measured values in the model's own terms."""
    from skygen.config import build_config, config_dict
    from skygen.instrument.photometry import Photometry, dark_current_e_s
    d = config_dict(cfg0)
    s = cfg0.sensor
    gain = meas["gain_e_per_adu"]
    pitch = pixel_pitch_um or cfg0.camera.pixel_pitch_um
    d["camera"].update({"pixel_pitch_um": pitch, "focal_length_mm": cam.f_px * pitch / 1000.0, "fov_deg": None,
                        "principal_x_px": float(cam.cx_px), "principal_y_px": float(cam.cy_px),
                        "k1": float(cam.k1), "k2": float(cam.k2), "pixel_aspect": float(cam.aspect)})
    psf = meas["psf"]
    if psf["ok"]:
        d["optics"].update({"psf": psf["psf"], "psf_sigma_px": float(np.clip(
            psf["moffat_sigma_px"] if psf["psf"] == "moffat" else psf["gaussian_sigma_px"], 0.2, 20))})
        if psf["psf"] == "moffat":
            d["optics"]["moffat_beta"] = float(np.clip(psf["moffat_beta"], 1.1, 20))
    bits = meas["bits"]
    d["sensor"].update({"exposure_s": float(exposure), "gain_e_per_adu": float(gain),
                        "read_noise_e": float(meas["read_noise_e"]), "bias_adu": int(round(meas["bias_adu"])),
                        "bit_depth": int(bits), "full_well_e": float(max(s.full_well_e, gain * (2 ** bits - 1)))})
    fitted_sensor = build_config(d).sensor
    dark_e = dark_current_e_s(fitted_sensor) * exposure
    grad_e = meas["gradient_adu"] * gain
    # level at the centre = bias + dark + sky + half the stray-light ramp; the corner loses vignetting x sky
    sky_e = (meas["centre_adu"] - meas["bias_adu"]) * gain - dark_e - grad_e / 2
    d["optics"]["vignetting"] = float(np.clip(meas["corner_drop_adu"] * gain / sky_e, 0.0, 0.9)) if sky_e > 0 else 0.0
    ph = Photometry.from_config(cfg0.optics, cfg0.photometry, fitted_sensor)
    scale = np.degrees(1.0 / cam.f_px) * 3600
    ref = ph.sky_electrons_per_px_s(20.0, scale) * cam.aspect * exposure
    d["photometry"]["sky_mag_arcsec2"] = float(np.clip(20.0 - 2.5 * np.log10(max(sky_e, 1e-9) / ref), 10, 30))
    hot = meas["hot"]
    d["corruptions"].update({"stray_light": float(min(grad_e / exposure, 1e7)),
                             "hotpixels": float(min(hot["fraction"], 0.05))})
    if hot["n_static"]:
        d["sensor"]["hot_pixel_dark_e_s"] = float(min(hot["excess_adu"] * gain / exposure, 1e9))
    d["corruptions"]["false_stars"] = float(min(meas.get("faint_sources_per_frame", 0.0), 100.0))
    st = meas["settings"]
    d["detection"].update({"threshold_sigma": st["threshold_sigma"], "min_area_px": st["min_area_px"],
                           "background_box_px": st["background_box_px"]})
    w, h = cam.width_px, cam.height_px
    if w % d["output"]["image_size_px"] or h % (w // d["output"]["image_size_px"]):
        d["output"]["image_size_px"] = _image_size(w, h)
    d["attitude"] = config_dict(build_config({}))["attitude"]
    return build_config(d)


def _measure_real(img, settings, sat, fs, g, k) -> dict:
    from skygen.real.frame_stats import frame_stats
    from skygen.real.fit_pixels import zero_point
    st, _ = frame_stats(img, settings["threshold_sigma"], settings["min_area_px"], settings["background_box_px"], sat)
    m = g.keep[k]
    d = fs.det_index[m]
    zp, n = zero_point(fs.det["flux_adu"][d].astype(float), fs.star_mag[m], fs.det["peak_adu"][d].astype(float),
                       np.full(len(d), st["background_adu"]), sat)
    return {**st, "zero_point_mag": zp, "zero_point_stars": n}


def _render_stats(cfg, attitudes, table, sat) -> list[dict]:
    """Frames rendered at ``attitudes`` (ra, dec, roll) with ``cfg``, measured like the real ones."""
    from skygen.config import build_config, config_dict
    from skygen.real.fit_pixels import zero_point
    from skygen.real.frame_stats import frame_stats
    from skygen.render.frame import Renderer
    d = config_dict(cfg)
    ra, dec, roll = (tuple(float(a[i]) for a in attitudes) for i in range(3))
    d["attitude"] = {**d["attitude"], "mode": "list", "ra_deg": ra, "dec_deg": dec, "roll_deg": roll}
    d["n_frames"] = len(attitudes)
    d["output"] = {**d["output"], "full_res": True}
    d["render"] = {**d["render"], "backend": "numpy", "device": "cpu"}
    c = build_config(d)
    r = Renderer(c, catalog=table)
    det_cfg = c.detection
    rows = []
    for i in range(len(attitudes)):
        f = r.render(i)
        img = f.image_full.astype(np.float32)
        st, det = frame_stats(img, det_cfg.threshold_sigma, det_cfg.min_area_px, det_cfg.background_box_px, sat)
        from skygen.instrument.detect import match
        sidx = match(det["x_px"], det["y_px"], f.stars["x_px"], f.stars["y_px"], f.stars["electrons"], 2.0)
        ok = sidx >= 0
        zp, n = zero_point(det["flux_adu"][ok].astype(float), f.stars["mag"][sidx[ok]].astype(float),
                           det["peak_adu"][ok].astype(float), np.full(int(ok.sum()), st["background_adu"]), sat)
        rows.append({**st, "zero_point_mag": zp, "zero_point_stars": n, "_image": img if i == 0 else None})
    return rows


def _record(names, dropped, solved, g, cam0, cam, mv, meas, zp_real, exposure, real_stats, before, after, cfg,
            scale, sat, fov_range, camera, command, timing, epoch) -> dict:
    from skygen.config import config_dict
    from skygen.runtime import hardware
    per_frame = []
    for fs, r, p, R in zip(solved, g.residuals, g.positions, g.rotations):
        from skygen.real.fit_geometry import radec_roll
        ra, dec, roll = radec_roll(R)
        per_frame.append({"frame": Path(fs.name).name, "solved_fov_deg": fs.fov_deg, "matched": int(len(r)),
                          "rms_px": float(np.sqrt(np.mean(np.sum(r ** 2, 1)))) if len(r) else float("nan"),
                          "ra_deg": ra, "dec_deg": dec, "roll_deg": roll})
    allr = np.concatenate(g.residuals)
    allp = np.concatenate(g.positions)
    rad = np.hypot(allp[:, 0] - cam.cx_px, (allp[:, 1] - cam.cy_px) * cam.aspect)
    edges = np.linspace(0, np.hypot(cam.width_px / 2, cam.height_px * cam.aspect / 2), 6)
    radial = []
    for a, b in zip(edges[:-1], edges[1:]):
        sel = (rad >= a) & (rad < b)
        radial.append({"r_lo_px": float(a), "r_hi_px": float(b), "n": int(sel.sum()),
                       "rms_px": float(np.sqrt(np.mean(np.sum(allr[sel] ** 2, 1)))) if sel.any() else float("nan")})
    keys = ("background_adu", "noise_adu", "detections", "star_sigma_px", "zero_point_mag")
    med = lambda rows, k: float(np.nanmedian([r[k] for r in rows])) if rows else float("nan")  # noqa: E731
    compare = {k: {"real": med(real_stats, k), "fitted": med(after, k),
                   "start": med(before, k) if before else float("nan")} for k in keys}
    strip = lambda rows: [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows] if rows else None  # noqa: E731
    return {"command": command, "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "hardware": hardware(), "timing_s": timing, "epoch_yr": epoch, "value_scale": scale, "saturation_adu": sat,
            "start": {"camera_file": str(camera) if camera else None, "fov_range_deg": list(fov_range) if fov_range else None,
                      "f_px": cam0.f_px, "fov_deg": cam0.fov_deg[0], "aspect": cam0.aspect},
            "frames": [Path(n).name for n in names], "solved": per_frame,
            "dropped": [{"frame": Path(n).name, "reason": w} for n, w in dropped],
            "geometry": {"f_px": cam.f_px, "fov_deg": cam.fov_deg[0], "fov_v_deg": cam.fov_deg[1], "aspect": cam.aspect,
                         "cx_px": cam.cx_px, "cy_px": cam.cy_px, "k1": cam.k1, "k2": cam.k2, "fitted": g.fitted,
                         "fixed": g.fixed, "sigma": g.sigma, "rms_px": g.rms_px, "n_matched": int(len(allr)),
                         "radial": radial},
            "mean_variance": mv, "pixels": {k: v for k, v in meas.items() if k != "settings"},
            "detector": meas["settings"], "zero_point_real_mag": zp_real, "exposure_s": exposure,
            "compare": compare, "real_stats": real_stats, "fitted_stats": strip(after), "start_stats": strip(before),
            "config": config_dict(cfg), "_render_example": after[0]["_image"] if after else None}
