"""``skygen fit-camera``: a camera file fitted to a real sensor from its own frames.

    skygen fit-camera FRAME... --out camera.yaml [--camera START.yaml | --fov-range LO HI] [--pixel-pitch UM]
                      [--pixel-aspect A] [--epoch YEAR] [--report DIR]

1. Read the frames (:mod:`skygen.real.frames`; colour frames become one plane, luminance by default,
   saying so); all must have one size. Values are divided by the scale they carry
   (:func:`skygen.real.fit_pixels.value_scale`: 12-bit data stored x16 in 16-bit TIFF). Blank (constant)
   and saturated frames, multi-plane and unreadable files are dropped with the reason.
2. Detect stars (skygen's detector, 5 sigma, >= 3 px, a background per 64 px box) and solve each
   frame lost-in-space with tetra3rs (:mod:`skygen.real.platesolve`): from the start camera, or, with
   ``--fov-range`` (default without a camera file: 5-30 deg), searching the horizontal field in that
   range (the first search of a range builds and caches a database: ~35 s for 5-30 deg; a range whose
   database would pass 350 MB is refused first, naming a narrower one). Unsolved frames are dropped
   with the solver's reason.
3. Geometry (:mod:`skygen.real.fit_geometry`): detections matched to skygen's catalogue (Hipparcos-2 at the
   epoch); focal length, pixel aspect, principal point, k1 (k2) and every frame's attitude fitted
   together by least squares, matched from the centre outwards first (:func:`skygen.real.fit_geometry.grow_matches`:
   a wide lens's outer stars lie beyond the match radius until its distortion is fitted); terms the data cannot
   constrain are fixed, and the report says why. Frames
   the fitted camera does not explain (their own solved field over 3 % from the others', fewer than 4
   matched stars, or residuals over 3 x the fit's rms) are dropped with the reason and the fit made
   again without them; when they are half the solved frames or more, the fit is refused (frames of
   more than one camera?). Their pixels are left out of steps 4-6 too.
3b. Bright stars' shift (:mod:`skygen.real.fit_shift`): where the frames show bright stars farther from the centre
   than faint ones at the same place (an asymmetric star image: coma, lateral colour), by a significant amount, the
   camera gets ``camera.bright_shift_px`` (and ``_x_px`` / ``_y_px`` for a part the same everywhere) and the geometry
   is fitted again with every detection moved back by it.
   Then how far each frame's brightest 8 detections lie from their stars (unclipped) sets the few-star solvers'
   match window, ``camera.match_tol_px`` (1.5 x their 95th percentile, within 1-2 px), and the error they
   share in each frame, ``camera.shared_sigma_px`` (the attitude covariance adds it across the boresight).
4. Pixels (:mod:`skygen.real.fit_pixels`): background level and gradient, PSF (Gaussian or Moffat), hot
   pixels, whether saturated stars bloom along the columns (``sensor.blooming``, from the shape of their saturated
   cores: :func:`skygen.real.fit_pixels.blooming`), the background noise's neighbour correlation and the
   ``sensor.processor_blur_px`` it implies (:func:`skygen.real.fit_pixels.processor_blur`; rendered, the sensor
   and PSF fitted as the read-out was before it, where ``--processor-blur auto`` finds its renders miss the frames by
   less than renders without it, steps 4-6 done both ways: :func:`_with_or_without_blur`),
   the photometric zero point. The sensor
   (:mod:`skygen.real.fit_sensor`): gain, bias and read
   noise from the background's mean-variance line where the frames constrain them; a line whose gain rests
   on too short a lever arm, whose bias would sit above the darkest background, or whose background is
   clipped at the ADC's floor is refused, and gain and background electrons are fitted directly to the
   background's level and noise instead (one line on the terminal and in the report says so).
5. Detector settings: the threshold and background box that find the most catalogue stars net of
   other detections on these frames. Real frames show stars fainter than the catalogue's
   completeness; the detections they have beyond renders of the fitted camera (median per frame)
   become ``corruptions.false_stars`` (point sources at random places up to the detection limit; their bright
   end capped where renders put more of them among the ten brightest detections than the frames have:
   :func:`skygen.real.fit_render.cap_bright_tail`).
6. The model's own terms (:mod:`skygen.real.fit_render`): electrons from the gain; the zero point becomes
   ``sensor.exposure_s`` (exposure x throughput: the start camera's aperture, transmission and QE are kept,
   so the fitted exposure absorbs the atmosphere and any other loss); the background becomes
   ``photometry.sky_mag_arcsec2`` (after the start camera's dark current, lowered when it alone would
   outshine the darkest corner), its fall towards the corners ``optics.vignetting``, the gradient
   ``corruptions.stray_light`` (a ramp of the same size, random direction). Where the matched stars span the
   field, their own photometric residuals give the stars' vignetting (:func:`skygen.real.fit_render.star_vignetting`)
   and the background's fall is kept apart as ``optics.sky_vignetting``; the stars' photometric scatter beyond
   the renders' own becomes ``photometry.star_scatter_mag`` (a fixed offset per star); uncatalogued detections
   that recur at one place from several pointings become ``sensor.fixed_sources`` (:mod:`skygen.real.fit_fixed`:
   a glow on the sensor, rendered in every frame, and no false star). Where the frames' background sits at the
   ADC's floor, a processor's black level (``sensor.black_level_adu``) is fitted to the depth down to which they
   detect catalogue stars (:func:`skygen.real.fit_render.fit_black_level`); where instead their matched stars respond
   to brightness with a lower power than linear renders' (a JPEG's tone curve), the exponent of a processor's tone
   curve (``sensor.tone_gamma``, linear up to a knee 3 background sigma above the background) is fitted to that
   response (:func:`skygen.real.fit_render.fit_tone_curve`); the centroid scatter the geometry
   fit leaves beyond the renders' own becomes ``optics.star_jitter_px`` (:func:`skygen.real.fit_render.star_jitter`).
   Frames are then rendered at the
   fitted attitudes and the exposure corrected once so that the zero point measured on the renders equals
   the real one (the detector's flux is not a star's whole flux; the zero point is the median over matched
   stars less the pairs far brighter than their star, :func:`skygen.real.fit_pixels.zero_point_rows`). The
   renders' background, its noise, the
   star width and the detections per frame are checked against the frames
   (:data:`skygen.real.frame_stats.TOLERANCES`: 10, 15, 10, 25 %); a statistic that is off is corrected
   where a term fits it directly (at most twice, each kept only where its renders miss by less), and what is still
   off is a WARNING on the terminal, at the top of
   the report and in the camera file's header. Two more comparisons say why detections can be off: the
   magnitude down to which half the catalogue stars on the sensor are detected
   (:func:`skygen.real.fit_render.half_detected_mag`; frames more than 0.5 mag shallower than their renders:
   a response that drops faint stars, a black clip or tone curve of a camera's processor) and the matched
   stars' flux exponent (:func:`skygen.real.fit_render.flux_exponent`: a tone curve on the bright stars);
   either past its tolerance is a warning too.
7. Write the camera YAML (checked by loading it with :func:`skygen.config.load_config`) and a report
   (``REPORT.md``, ``fit.json``, ``fit.png``): residuals per frame and radial, real against rendered
   statistics for the start camera (when given) and the fitted one.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from skygen.errors import ConfigError, SkygenError
from skygen.instrument.camera import Camera

BOX_PX = 64  # background box of detection and pixel statistics
DETECT = {"threshold_sigma": 5.0, "min_area_px": 3}
THRESHOLDS = (3.0, 4.0, 5.0, 6.0, 8.0)
DEFAULT_FOV_RANGE = (5.0, 30.0)  # searched when neither a camera file nor a range is given
PITCH_DEFAULT_UM = 5.5  # skygen's default camera's pixel pitch
BOXES = (0, BOX_PX)
#: a frame the fitted camera does not explain is dropped (:func:`disagreements`): its own solved field more
#: than this far (relative) from the other frames', fewer matched stars than a lost-in-space solution
#: needs, or residuals this many times the fit's rms
FIELD_TOLERANCE = 0.03
MIN_MATCHED = 4
RMS_FACTOR = 3.0
#: ... or under this share of the catalogue stars its own lost-in-space solution matches (its own field, at the fit's
#: match radius), where that solution matches at least OWN_MATCHED_FROM: a frame of the same field to a few per cent
#: but another focal length (the cedar-solve frames: one of six at a 1 % shorter field matched 4 stars under the
#: fitted camera, the others 6-25, results/real-frames/held-out-cedar)
OWN_MATCH_SHARE = 1 / 3
OWN_MATCHED_FROM = 3 * MIN_MATCHED
#: the joint fit's final match radius (px, :func:`_fit_two_radii`), at which a frame's own solution is matched too
FIT_RADIUS_PX = 2.5
#: the report's neighbour correlation of geometry residuals (:func:`neighbour_correlation`): pairs within this many px
NEIGHBOUR_PX = 200.0


class FitError(SkygenError):
    """The frames cannot give a camera (none solved, too few usable)."""


# ----------------------------------------------------------------------------------- input
def read_frames(
    paths: list[str], log, channel: str = "luminance"
) -> tuple[list[str], list[np.ndarray], list[tuple[str, str]]]:
    """(names, images, dropped): unreadable, multi-plane or empty files are dropped with their one-line reason
    (colour frames become one plane by ``channel``, saying so); frames of different sizes are refused."""
    from skygen.real.frames import FrameError, frame_files, read_frame

    files: list[Path] = []
    for p in paths:
        path = Path(p)
        files += frame_files(path) if path.is_dir() else [path]
    names, imgs, dropped = [], [], []
    for f in files:
        try:
            imgs.append(read_frame(f, channel, log=lambda m: log(f"fit-camera: {m}")))
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
        parts = "; ".join(
            f"{w} x {h} px: {', '.join(v[:3])}{' ...' if len(v) > 3 else ''}" for (h, w), v in shapes.items()
        )
        raise ConfigError(
            f"frames of different sizes in one calibration ({parts}); give frames of one camera and read-out mode"
        )
    return names, imgs, dropped


def usable(img: np.ndarray, saturation: float) -> str:
    """'' or why a frame cannot be used (blank, saturated)."""
    at_top = float(np.mean(img >= saturation))
    if at_top > 0.25:
        return f"saturated frame ({100 * at_top:.0f} % of pixels at the top of the range, {saturation:g})"
    if float(img.max()) == float(img.min()):
        return f"blank frame (every pixel {float(img.min()):g})"
    return ""


def start_config(camera, fov_range, pixel_pitch_um, pixel_aspect, shape, fov_deg=None):
    """The start config: the camera file, or a camera of the frames' size with the given field (``fov_deg``) or the
    range's middle one. A camera file without storage settings (``output.image_size_px``) gets a stored size its
    sensor divides into, as :func:`skygen.real.fit_render.image_size` picks: fit-camera stores nothing, and the
    default 256 would refuse a 2256 px wide sensor."""
    from skygen import configlib
    from skygen.config import build_config, load_config
    from skygen.real.fit_render import image_size

    h, w = shape
    if camera is not None:
        if fov_range is not None:
            raise ConfigError("give --camera START.yaml or --fov-range LO HI, not both")
        data = configlib.read_yaml(camera)
        data = data if isinstance(data, dict) else {}  # load_config says what is wrong with a file that is not
        cam = data["camera"] if isinstance(data.get("camera"), dict) else {}
        out = data["output"] if isinstance(data.get("output"), dict) else {}
        cw, ch = cam.get("width_px", w), cam.get("height_px", h)
        size = []
        if "image_size_px" not in out and isinstance(cw, int) and isinstance(ch, int) and cw > 0 and ch > 0:
            size = [f"output.image_size_px={image_size(cw, ch)}"]
        cfg = load_config(camera, size)
        if pixel_aspect is not None:
            cfg = dataclasses.replace(cfg, camera=dataclasses.replace(cfg.camera, pixel_aspect=pixel_aspect))
        if (cfg.camera.width_px, cfg.camera.height_px) != (w, h):
            raise ConfigError(
                f"{camera}: camera is {cfg.camera.width_px} x {cfg.camera.height_px} px but the frames "
                f"are {w} x {h} px (width x height); give the camera of these frames"
            )
        return cfg
    if fov_deg is not None:
        lo = hi = fov_deg
    else:
        lo, hi = fov_range
        if not 0 < lo < hi < 120:
            raise ConfigError(f"--fov-range {lo:g} {hi:g}: give 0 < LO < HI < 120 degrees (horizontal field)")
    if not 0 < pixel_pitch_um <= 100:
        raise ConfigError(f"--pixel-pitch {pixel_pitch_um:g}: pixel width in micrometres, > 0 and <= 100")
    data = {
        "camera": {
            "width_px": w,
            "height_px": h,
            "pixel_pitch_um": pixel_pitch_um,
            "fov_deg": 0.5 * (lo + hi),
            "pixel_aspect": pixel_aspect or 1.0,
        },
        "output": {"image_size_px": image_size(w, h)},
    }
    return build_config(data)


#: the geometry fit and the detector choice match detections to at most this many of the catalogue's
#: brightest stars (Hipparcos-2 holds 117,955: all of them, to Hp 10): a deeper catalogue to Hp 10 (Gaia, 490 k)
#: puts a chance star within 3 px of ~12 % of a 27 deg camera's detections, which pulled the geometry to
#: 0.8 px rms and made the detector choice reward noise (results/real-frames/gaia.md)
MATCH_STARS = 120_000
#: ... unless the pixels are small enough that more stars keep chance matches as rare: at most this share of
#: detections with a chance star within 3 px (MATCH_STARS gives ~3 % on that 27 deg camera, 76"/px). A 1.1 deg
#: telescope field (2"/px) matches every star to G = 10 this way; capped at 120 k it matched a median of 2 per frame
MATCH_CHANCE = 0.03


def match_limit(table, pixel_scale_arcsec: float | None = None) -> float:
    """The magnitude to which ``table``'s stars are matched in the geometry fit and the detector choice: Hp 10,
    or brighter where that would pass :data:`MATCH_STARS` stars, or where given ``pixel_scale_arcsec``, as many
    as put a chance star within 3 px of :data:`MATCH_CHANCE` of the detections, if that is more."""
    mags = np.sort(table.mag[np.isfinite(table.mag)])
    most = MATCH_STARS
    if pixel_scale_arcsec is not None and pixel_scale_arcsec > 0:
        r_rad = np.radians(3.0 * pixel_scale_arcsec / 3600.0)
        most = max(most, int(MATCH_CHANCE * 4.0 / r_rad**2))  # N / (4 pi) * pi r^2 = chance
    return float(min(10.0, mags[min(most, len(mags)) - 1]))


# ----------------------------------------------------------------------------------- the fit
def fit_camera(
    paths: list[str],
    out: str | Path,
    *,
    camera=None,
    fov_range=None,
    fov_deg=None,
    pixel_pitch_um=None,
    pixel_aspect=None,
    epoch_yr=None,
    report_dir=None,
    command: str = "",
    log=print,
    channel: str = "luminance",
    catalog: str | None = None,
    black_level: int | None = None,
    processor_blur: str = "auto",
) -> dict:
    """Fit a camera to ``paths`` (see the module doc); writes ``out`` and the report; returns the fit record.

    ``channel``: how colour frames become one plane (:data:`skygen.real.frames.CHANNELS`). ``black_level``: the
    processor's black level given (ADU; 0: none) instead of fitted. ``processor_blur``: whether the camera renders the
    processor's blur the frames' noise correlation implies (``sensor.processor_blur_px``): ``on``, ``off`` (reported
    only) or ``auto`` (:func:`_with_or_without_blur`: both fitted where a blur is measured, the one whose renders miss
    the frames by less kept). ``fov_deg``: the horizontal field where it is
    known, instead of ``camera`` or ``fov_range``."""
    if processor_blur not in BLUR_MODES:
        raise ConfigError(f"--processor-blur {processor_blur!r}: one of {', '.join(BLUR_MODES)}")
    if black_level is not None and not 0 <= black_level <= 60000:
        raise ConfigError(f"--black-level {black_level}: a level in ADU from 0 (none) to 60000")
    from skygen.real.fit_render import fit_model_terms, frame_exposure_scales
    from skygen.runtime import check_output_file, check_output_folder
    from skygen.sky.catalog import SkyIndex, open_catalog

    t0 = time.perf_counter()
    check_output_file(out, "--out", "camera.yaml")  # before the minute of solving and fitting, not after it
    if report_dir is not None:
        check_output_folder(report_dir, "--report")
    fov_range, pixel_pitch_um, notes = resolve_inputs(camera, fov_range, pixel_pitch_um, pixel_aspect, log, fov_deg)
    fr = load_frames(paths, log, channel)
    cfg0 = start_config(camera, fov_range, pixel_pitch_um, pixel_aspect, fr.imgs[0].shape, fov_deg)
    if catalog is not None:  # the catalogue the renders will use: the false stars fitted are what it lacks
        cfg0 = dataclasses.replace(cfg0, catalog=dataclasses.replace(cfg0.catalog, source=catalog))
    if epoch_yr is None:  # when the frames were taken, where they say (EXIF, FITS): the catalogue's proper motions
        epoch_yr, said = frames_epoch(fr.names)
        if said:
            log(f"fit-camera: {said}")
            notes = [*notes, said]
    epoch = float(epoch_yr if epoch_yr is not None else cfg0.epoch_yr)
    cfg0 = dataclasses.replace(cfg0, epoch_yr=epoch)  # the camera file records the epoch it was fitted at
    table = open_catalog(cfg0.catalog.source, cfg0.catalog.path)
    scale = 3600.0 * np.degrees(1.0 / Camera.from_config(cfg0.camera).f_px)  # arcsec per pixel, at the start
    sky = SkyIndex(table, epoch, match_limit(table, scale))
    solved, cfg0, cam0 = solve_frames(fr, cfg0, fov_range, log, search_aspect=pixel_aspect is None)
    t_solve = time.perf_counter() - t0
    g, solved = fit_joint_geometry(solved, cam0, fov_range, sky, fr, log)
    g, shift = fit_shift_step(g, solved, cam0, fov_range, sky, fr, log)
    t_geom = time.perf_counter() - t0

    def pixels_and_terms(blur: bool, say) -> tuple:
        px = measure_pixels(fr, solved, g, cfg0, sky, say, camera_file=camera is not None, processor_blur=blur)
        model = fit_model_terms(
            cfg0,
            g,
            px,
            solved,
            fr,
            table,
            epoch,
            pixel_pitch_um,
            with_start=camera is not None,
            log=say,
            black_level=black_level,
            exposure_scales=frame_exposure_scales(px["meas"]["frame_zero_points"], px["zp_real"], FRAME_ZP_SPREAD_MAG),
        )
        return px, model

    if processor_blur != "auto":
        px, model = pixels_and_terms(processor_blur == "on", log)
    else:
        px, model = _with_or_without_blur(pixels_and_terms, log)
    timing = {"solve_s": t_solve, "geometry_s": t_geom, "total_s": time.perf_counter() - t0}
    record = _record(
        fr.names,
        fr.dropped,
        solved,
        g,
        cam0,
        g.camera,
        px["mv"],
        px["meas"],
        px["zp_real"],
        model["exposure"],
        model["real_stats"],
        model["before"],
        model["after"],
        model["cfg"],
        fr.scale,
        fr.sat,
        fov_range,
        camera,
        command,
        timing,
        epoch,
    )
    exposures = exposure_note(px["meas"]["frame_zero_points"], px["zp_real"], [fs.name for fs in solved])
    for note in (
        exposures,
        field_note(g.camera.fov_deg[0], fov_range, record["geometry"]["n_matched"]),
        catalogue_note(model["cfg"], model["real_stats"]),
    ):
        if note:
            log(f"fit-camera: {note}")
            notes = [*notes, note]
    record["notes"] = notes
    record["bright_shift"] = shift
    record["start"]["dark_current_e_s"] = cfg0.sensor.dark_current_e_s
    record["checks"] = model["checks"]
    record["correction"] = model["correction"]
    record["warnings"] = model["warnings"]
    record["check_exposure_scales"] = model["check_exposure_scales"]
    if model["warnings"]:
        log(
            "fit-camera: WARNING: renders of this camera contradict the frames it was fitted on: "
            + "; ".join(model["warnings"])
            + (f" (see {report_dir}/REPORT.md)" if report_dir is not None else "")
        )
    from skygen.real.fit_report import write_camera_yaml, write_report

    write_camera_yaml(out, model["cfg"], record, command)
    if report_dir is not None:
        write_report(report_dir, record, [fr.image_of(fs.name) for fs in solved][:1], g)
    return record


@dataclasses.dataclass
class Frames:
    """The usable frames of a fit: names, images (divided by their value ``scale``), their background
    statistics (:func:`skygen.real.fit_pixels.background`, filled by :func:`solve_frames`), the frames
    dropped so far with the reason, and the data's bit depth and saturation level (scaled ADU)."""

    names: list
    imgs: list
    dropped: list
    scale: int
    bits: int
    sat: float
    bgs: list = dataclasses.field(default_factory=list)
    other_camera: set = dataclasses.field(default_factory=set)  # names dropped as not the fitted camera's

    def image_of(self, name: str) -> np.ndarray:
        return self.imgs[self.names.index(name)]

    def background_of(self, name: str) -> dict:
        return self.bgs[self.names.index(name)]

    def drop(self, name: str, why: str, log) -> None:
        self.dropped.append((name, why))
        log(f"fit-camera: dropped {name}: {why}")


def frames_epoch(names: list[str]) -> tuple[float | None, str]:
    """(the median Julian year the frames were taken, a line saying so) from their own dates
    (:func:`skygen.real.frames.frame_epoch`: EXIF, FITS); (None, '') where none has one."""
    from skygen.real.frames import frame_epoch

    found = [e for e in (frame_epoch(n) for n in names) if e is not None]
    if not found:
        return None, ""
    years = np.array([e[0] for e in found])
    epoch = float(np.median(years))
    span = float(years.max() - years.min())
    fields = sorted({e[1] for e in found})
    return epoch, (
        f"epoch {epoch:.2f} (Julian year) from {len(found)} of {len(names)} frames' {' / '.join(fields)}"
        + (f", which span {span:.1f} years" if span > 1 else "")
        + ": the catalogue's proper motions are taken to it (--epoch YEAR gives another)"
    )


def field_note(fov_deg: float, fov_range, matched: int) -> str:
    """'' or a line saying the fitted field lies outside ``--fov-range`` (the solver's search reaches a little beyond
    it): the stars decide the field, but a user who gave the range from a lens's label should know it is not that."""
    if fov_range is None or fov_range[0] <= fov_deg <= fov_range[1]:
        return ""
    return (
        f"the field found, {fov_deg:.2f} deg, lies outside --fov-range {fov_range[0]:g} {fov_range[1]:g}: "
        f"{matched} matched stars fix it, so the lens or the frames' scaling is not what the range assumed"
    )


#: catalogue_note speaks where the detections the catalogue does not explain outnumber those it does this many times
UNEXPLAINED_RATIO = 2.0


def catalogue_note(cfg, real_stats: list) -> str:
    """'' or a line suggesting ``--catalog gaia`` where the frames' uncatalogued detections outnumber their catalogue
    stars (:data:`UNEXPLAINED_RATIO`) with Hipparcos: the renders then place those as false stars at random, where a
    deeper catalogue's would move with the attitude as real ones do."""
    from skygen.real.frame_stats import median_of

    if cfg.catalog.source != "hipparcos" or not real_stats:
        return ""
    total, cat = median_of(real_stats, "detections"), median_of(real_stats, "catalogue_detections")
    if not (np.isfinite(total) and np.isfinite(cat)) or total - cat <= UNEXPLAINED_RATIO * max(cat, 1.0):
        return ""
    return (
        f"Hipparcos explains {cat:.0f} of the frames' {total:.0f} detections per frame; the other {total - cat:.0f} "
        "are rendered as false stars at random places. If they are fainter stars (a narrow or deep camera), "
        "--catalog gaia renders them from Gaia DR3 (to G = 10), where they move with the attitude"
    )


def resolve_inputs(camera, fov_range, pixel_pitch_um, pixel_aspect, log, fov_deg=None) -> tuple:
    """(field range, pixel pitch, notes): the defaults filled in and said, the options checked before any work
    (a field range whose solver database would be too large is refused here, not after reading the frames)."""
    from skygen.real.platesolve import check_database_size

    if pixel_aspect is not None and not 0.1 <= pixel_aspect <= 10:
        raise ConfigError(f"--pixel-aspect {pixel_aspect:g}: pixel height / width between 0.1 and 10")
    if fov_deg is not None:
        if camera is not None or fov_range is not None:
            raise ConfigError("give one of --camera START.yaml, --fov DEG and --fov-range LO HI")
        if not 0.1 <= fov_deg < 120:
            raise ConfigError(f"--fov {fov_deg:g}: the horizontal field of view in degrees, 0.1 to 120")
    notes = []
    if camera is None and fov_range is None and fov_deg is None:
        fov_range = DEFAULT_FOV_RANGE
        notes.append(
            f"no --camera or --fov-range: the horizontal field was searched in {fov_range[0]:g}-{fov_range[1]:g} deg"
        )
    if camera is None and pixel_pitch_um is None:  # --fov or --fov-range
        pixel_pitch_um = PITCH_DEFAULT_UM
        notes.append(
            f"no --pixel-pitch: {pixel_pitch_um:g} um assumed (only camera.focal_length_mm depends on it; "
            "the field, and so every render, does not)"
        )
    if fov_range is not None and 0 < fov_range[0] < fov_range[1] < 120:  # other ranges: start_config says why
        check_database_size(fov_range[0], fov_range[1])
    for n in notes:
        log(f"fit-camera: {n}")
    return fov_range, pixel_pitch_um, notes


def load_frames(paths: list[str], log, channel: str = "luminance") -> Frames:
    """Step 1: read the frames, divide by the scale their values carry, drop blank and saturated ones."""
    from skygen.real import fit_pixels as P

    names, raw, dropped = read_frames(paths, log, channel)
    scale, bits, sat = P.value_scale(raw)
    fr = Frames([], [], dropped, scale, bits, sat)
    for n, im in zip(names, (im / scale for im in raw)):
        why = usable(im, sat)
        if why:
            fr.drop(n, why, log)
        else:
            fr.names.append(n)
            fr.imgs.append(im)
    if not fr.imgs:
        raise FitError("no usable frame: " + "; ".join(f"{Path(n).name}: {w}" for n, w in dropped[:4]))
    return fr


#: pixel aspects (height / width) tried when the start camera's solves fewer than half the frames and
#: no --pixel-aspect was given: an interlaced read-out stored at half height (2) or doubled rows (0.5)
ASPECT_SEARCH = (2.0, 0.5)


def solve_frames(fr: Frames, cfg0, fov_range, log, search_aspect: bool = True) -> tuple[list, object, Camera]:
    """Step 2: background statistics and detections of every frame, then a lost-in-space solution
    (:class:`skygen.real.fit_geometry.FrameSolution`); unsolved frames are dropped with the solver's reason.

    When the start camera's pixel aspect solves fewer than half the frames and ``search_aspect`` (no
    --pixel-aspect given), the aspects of :data:`ASPECT_SEARCH` are tried too and the one that solves the
    most frames is kept, with one line saying so. Returns (solved frames, start config, start camera), the
    config and camera with the aspect that was kept."""
    from skygen.instrument.detect import detect
    from skygen.real import fit_pixels as P

    cam0 = Camera.from_config(cfg0.camera)
    db = _database(cam0, fov_range, log)
    dets = []
    for im in fr.imgs:
        fr.bgs.append(P.background(im, BOX_PX))
        dets.append(
            detect(im, DETECT["threshold_sigma"], DETECT["min_area_px"], 200, BOX_PX, background=_maps(fr.bgs[-1]))[0]
        )
    frames = _solve_all(db, fr.names, dets, cam0, fov_range)
    n_ok = sum(fs.solved for fs in frames)
    if search_aspect and 2 * n_ok < len(frames):
        tried = [f"{cam0.aspect:g}: {n_ok}"]
        for aspect in ASPECT_SEARCH:
            cfg = dataclasses.replace(cfg0, camera=dataclasses.replace(cfg0.camera, pixel_aspect=aspect))
            cam = Camera.from_config(cfg.camera)
            trial = _solve_all(db, fr.names, dets, cam, fov_range)
            n = sum(fs.solved for fs in trial)
            tried.append(f"{aspect:g}: {n}")
            if n > n_ok:
                frames, n_ok, cfg0, cam0 = trial, n, cfg, cam
        log(
            f"pixel aspect searched (frames solved per height/width: {', '.join(tried)} of {len(frames)}): "
            f"using {cam0.aspect:g}; give --pixel-aspect to set it"
        )
    for fs in frames:
        if fs.reason:
            fr.drop(fs.name, fs.reason, log)
    solved = [fs for fs in frames if fs.solved]
    if not solved:
        raise FitError(
            f"no frame solved ({len(fr.dropped)} dropped): "
            + "; ".join(f"{Path(n).name}: {why}" for n, why in fr.dropped[:3])
            + (" ..." if len(fr.dropped) > 3 else "")
        )
    return solved, cfg0, cam0


def _maps(bg: dict) -> tuple:
    """A frame's :func:`skygen.real.fit_pixels.background` (its ``BOX_PX`` maps and their medians) as
    :func:`skygen.instrument.detect.detect`'s ``background``: the detector need not estimate it again."""
    return bg["level_map"], bg["sigma_map"], bg["level_adu"], bg["noise_adu"]


def _database(cam0: Camera, fov_range, log):
    from skygen.real.platesolve import load_database

    if fov_range is None:
        return load_database(cam0.fov_deg[0], log=log)
    return load_database(fov_range[0], log=log, fov_max_deg=fov_range[1])


def _solve_all(db, names: list, dets: list, cam: Camera, fov_range) -> list:
    from skygen.real import fit_geometry as G

    return [G.FrameSolution(n, det, *G.solve_frame(db, det, cam, fov_range)) for n, det in zip(names, dets)]


def fit_joint_geometry(solved: list, cam0: Camera, fov_range, sky, fr: Frames, log) -> tuple:
    """Step 3: the joint geometry fit (:func:`skygen.real.fit_geometry.fit_geometry`, a 6 px then a 2.5 px
    match radius); the frames whose own solution disagrees with the fitted camera (:func:`disagreements`)
    are dropped and the fit made again from the others' own solutions, as if only they had been given.
    Unless the frames that agree are a majority: then it refuses (frames of more than one camera?).
    One frame has no other to disagree with: its fit stands. Returns (fit, the frames kept)."""
    own = {fs.name: fs.R for fs in solved}  # each frame's lost-in-space solution
    said: list[str] = []  # the fit's notes, kept back until it stands
    own_matched = {fs.name: own_match_count(fs, own[fs.name], cam0, sky) for fs in solved}
    g = _fit_two_radii(solved, cam0, fov_range, sky, said.append)
    bad = disagreements(solved, g, own_matched=own_matched) if len(solved) > 1 else {}
    if not bad:
        for m in said:
            log(m)
        return g, solved
    kept = [fs for fs in solved if fs.name not in bad]
    if 2 * len(kept) <= len(solved):
        shallow = catalogue_too_shallow(solved, g, sky)
        if shallow:
            raise FitError(shallow)
        others = [Path(n).name for n in bad]
        first = next(iter(bad.values()))
        raise FitError(
            f"frames of more than one camera? only {len(kept)} of {len(solved)} solved frames agree with "
            f"the fitted camera (field {g.camera.fov_deg[0]:.2f} deg); the other {len(bad)} "
            f"({', '.join(others[:3])}{' ...' if len(others) > 3 else ''}) do not, e.g. {others[0]}: "
            f"{first}; give the frames of one camera and lens"
            + (
                ""
                if kept or fov_range is not None
                else " (if they are, the camera file's field may be far from theirs: try --fov-range)"
            )
        )
    for n, why in bad.items():
        fr.drop(n, why, log)
        fr.other_camera.add(n)
    for fs in kept:
        fs.R = own[fs.name]
    return _fit_two_radii(kept, cam0, fov_range, sky, log), kept


def catalogue_too_shallow(solved: list, g, sky) -> str:
    """Why the fit cannot stand where the frames are of one camera but its catalogue holds too few of their stars
    (the frames solved at one field, a median of fewer than :data:`MIN_MATCHED` of their detections matched under
    the fitted camera): a narrow or deep camera, whose frames tetra3rs solved from a few catalogue stars. The
    message says what the catalogue explains and what to do; "" where that is not the case."""
    fovs = np.array([fs.fov_deg for fs in solved], float)
    matched = np.array([int(m.sum()) for m in g.keep])
    if len(solved) < 2 or not np.all(np.abs(fovs / np.median(fovs) - 1) <= FIELD_TOLERANCE):
        return ""
    if np.median(matched) >= MIN_MATCHED:
        return ""
    n_det = float(np.median([len(fs.det["x_px"]) for fs in solved]))
    gaia = "gaia" in sky.table.source.lower()
    deeper = (
        "skygen has no deeper catalogue than Gaia DR3 to G = 10, so this camera cannot be fitted from these "
        "frames; a wider field (a shorter lens) sees enough catalogue stars"
        if gaia
        else "--catalog gaia (Gaia DR3 to G = 10) holds more of them"
    )
    name = "Gaia DR3 to G = 10" if gaia else "Hipparcos"
    return (
        f"the catalogue ({name}, matched to {sky.table.band} = {sky.mag_limit:g}) holds too few of these frames' "
        "stars: "
        f"{len(solved)} frames solved at one field ({np.median(fovs):.2f} deg) match a median of "
        f"{np.median(matched):g} of their {n_det:.0f} detections to catalogue stars, and fitting the camera "
        f"needs at least {MIN_MATCHED} per frame; the frames see fainter stars than it holds. {deeper}"
    )


def fit_shift_step(g, solved: list, cam0: Camera, fov_range, sky, fr: Frames, log) -> tuple:
    """Step 3b: the brightness-dependent outward shift of the star images (:mod:`skygen.real.fit_shift`). Where one
    is found, the geometry is fitted again with every detection moved back by it (bright stars no longer pull the
    distortion), and the fitted camera carries it; then the few-star solver's match tolerance from the brightest
    detections' offsets (``camera.match_tol_px``). Returns (the geometry fit, the record of both)."""
    from skygen.real import fit_shift as S

    noise = [fr.background_of(fs.name)["noise_adu"] for fs in solved]
    shift = S.fit_bright_shift(S.shift_rows(solved, g.camera, g.rotations, sky, noise))
    log(f"fit-camera: {shift['note']}")
    if shift["px"] or shift["x_px"] or shift["y_px"]:
        start = dataclasses.replace(
            cam0,
            bright_shift_px=shift["px"],
            bright_shift_from=shift["from"],
            bright_shift_x_px=shift["x_px"],
            bright_shift_y_px=shift["y_px"],
        )
        raw = S.unshift_frames(solved, start, noise)
        try:
            g2 = _fit_two_radii(solved, start, fov_range, sky, lambda m: None)
        finally:
            for fs, det in zip(solved, raw):
                fs.det = det
        shift["geometry_rms_px"] = [float(g.rms_px), float(g2.rms_px)]
        log(
            "fit-camera: geometry fitted again with the shift taken off: residual rms "
            f"{g.rms_px:.3f} -> {g2.rms_px:.3f} px"
        )
        g = g2
    # how far the brightest detections lie from their stars sets the few-star solver's match tolerance
    per_frame = S.bright_offsets_per_frame(solved, g.camera, g.rotations, sky, noise)
    tol = S.match_tolerance(np.concatenate(per_frame) if per_frame else np.zeros((0, 2)))
    shift["match_tolerance"] = tol
    log(f"fit-camera: {tol['note']}")
    # what a frame's brightest stars share: a few-star attitude's error that no number of them averages away
    shared = S.shared_error(per_frame, tol["px"] if tol["px"] is not None else S.TOL_RANGE_PX[1])
    shift["shared_error"] = shared
    log(f"fit-camera: {shared['note']}")
    g.camera = dataclasses.replace(g.camera, match_tol_px=tol["px"], shared_sigma_px=shared["px"])
    return g, shift


def _fit_two_radii(solved: list, cam0: Camera, fov_range, sky, log):
    """The joint fit at a 6 px match radius (its attitudes replace the solutions), then at 2.5 px; from the
    start camera, or with a field range from the median field of :func:`majority_field`."""
    from skygen.real import fit_geometry as G

    start_cam = cam0
    if fov_range is not None:  # the field the solver found is the fit's start
        fov = float(np.median([fs.fov_deg for fs in majority_field(solved)]))
        start_cam = dataclasses.replace(cam0, f_px=cam0.width_px / 2 / np.tan(np.radians(fov) / 2))
    start_cam = G.grow_matches(solved, start_cam, sky, 6.0)  # from the centre outwards: a wide lens's distortion
    g = G.fit_geometry(solved, start_cam, sky, 6.0, log=lambda m: None)
    for fs, R in zip(solved, g.rotations):
        fs.R = R
    return G.fit_geometry(solved, g.camera, sky, FIT_RADIUS_PX, log=log)


def majority_field(solved: list, tol: float = FIELD_TOLERANCE) -> list:
    """The solved frames whose lost-in-space field agrees (within ``tol``, relative) with the most others:
    the start of the joint fit is their median field, not one pulled between two lenses' fields."""
    f = np.array([fs.fov_deg for fs in solved])
    support = [np.flatnonzero(np.abs(f / fi - 1) <= tol) for fi in f]
    return [solved[i] for i in max(support, key=len)]


def own_match_count(fs, R: np.ndarray, cam0: Camera, sky, radius_px: float = FIT_RADIUS_PX) -> int:
    """Catalogue stars a frame's own lost-in-space solution (rotation ``R``, its solved field ``fs.fov_deg``, a
    centred pinhole of ``cam0``'s size and aspect) matches at ``radius_px``: what the frame says of itself, to hold the
    fitted camera's matches against (:func:`disagreements`)."""
    from skygen.real import fit_geometry as G

    if not np.isfinite(fs.fov_deg):
        return 0
    cam = Camera(
        cam0.width_px,
        cam0.height_px,
        cam0.width_px / 2 / np.tan(np.radians(fs.fov_deg) / 2),
        (cam0.width_px - 1) / 2,
        (cam0.height_px - 1) / 2,
        aspect=cam0.aspect,
    )
    probe = G.FrameSolution(fs.name, fs.det, R)
    G.match_catalogue(probe, cam, sky, radius_px)
    return len(probe.det_index)


def disagreements(solved: list, g, tol: float = FIELD_TOLERANCE, own_matched: dict | None = None) -> dict:
    """{frame name: why} for the solved frames that the fitted camera does not explain: fewer matched
    catalogue stars than a lost-in-space solution needs (:data:`MIN_MATCHED`), a residual rms over
    :data:`RMS_FACTOR` x the fit's (and over 1 px), a solved field more than ``tol`` from the field
    the frames it does explain were solved at (tetra3rs's field, comparable frame to frame; the
    fitted pinhole field differs from it by the distortion), or (with ``own_matched``, {name: stars its own
    solution matches}, :func:`own_match_count`) fewer than :data:`OWN_MATCH_SHARE` of the stars its own solution
    matches. A wide lens's own pinhole solution matches fewer than the fitted camera, with its distortion, does:
    that last test never holds a frame to more than it can show."""
    matched = np.array([int(m.sum()) for m in g.keep])
    rms = np.array([np.sqrt(np.mean(np.sum(r**2, 1))) if len(r) else np.inf for r in g.residuals])
    good = matched >= MIN_MATCHED
    ref = float(np.median([fs.fov_deg for fs, ok in zip(solved, good) if ok])) if good.any() else float("nan")
    rms_cut = max(RMS_FACTOR * g.rms_px, 1.0)
    bad = {}
    for fs, n, r in zip(solved, matched, rms):
        if n < MIN_MATCHED:
            bad[fs.name] = (
                f"only {n} of its {len(fs.det['x_px'])} detections match catalogue stars under the fitted "
                f"camera (field {g.camera.fov_deg[0]:.2f} deg; its own solution: {fs.fov_deg:.2f} deg): "
                "a frame of another camera or lens, or a wrong solution"
            )
        elif abs(fs.fov_deg / ref - 1) > tol:
            bad[fs.name] = (
                f"solved at a {fs.fov_deg:.2f} deg field, the other frames at {ref:.2f} deg "
                f"({100 * abs(fs.fov_deg / ref - 1):.0f} % apart): a frame of another camera or lens"
            )
        elif r > rms_cut:
            bad[fs.name] = (
                f"its {n} matched stars sit {r:.2f} px rms from the fitted camera's projection, over "
                f"{rms_cut:.2f} px ({RMS_FACTOR:g} x the fit's {g.rms_px:.3f} px): a frame of another "
                "camera or lens, or a wrong solution"
            )
        elif own_matched and (mine := own_matched.get(fs.name, 0)) >= OWN_MATCHED_FROM and n < OWN_MATCH_SHARE * mine:
            bad[fs.name] = (
                f"the fitted camera (field {g.camera.fov_deg[0]:.2f} deg) matches {n} of the {mine} catalogue stars "
                f"its own solution ({fs.fov_deg:.2f} deg field) matches: a frame of another camera or lens (a "
                "different focal length or focus)"
            )
    return bad


#: fit-camera --processor-blur: ``auto`` fits the camera with and without the blur where one is measured and keeps the
#: one whose renders miss the frames by less (kept on two of the six processed cameras of
#: results/real-frames/jpeg-blocks)
BLUR_MODES = ("auto", "on", "off")


def check_score(checks: list) -> tuple[float, float]:
    """How far renders miss their frames, to compare two fits: (the summed log ratio beyond tolerance,
    :func:`skygen.real.fit_render.miss`; the summed absolute log ratio, which breaks a tie of fits that both pass)."""
    from skygen.real.fit_render import miss

    spread = sum(abs(np.log(c["ratio"])) if np.isfinite(c["ratio"]) and c["ratio"] > 0 else np.inf for c in checks)
    return miss(checks), float(spread)


def _with_or_without_blur(pixels_and_terms, log) -> tuple:
    """``--processor-blur auto``: the pixels and model terms fitted without the processor's blur and, where the frames'
    noise correlation implies one, with it (:func:`skygen.real.fit_pixels.processor_blur`); the fit whose renders
    miss the frames by less (:func:`check_score`) is kept and its messages printed, with one line on the choice."""
    said: list[str] = []
    px, model = pixels_and_terms(False, said.append)
    blur = px["meas"]["processor_blur"]
    if not blur["px"] > 0:
        for line in said:
            log(line)
        return px, model
    said_blur: list[str] = []
    px_b, model_b = pixels_and_terms(True, said_blur.append)
    without, with_ = check_score(model["checks"]), check_score(model_b["checks"])
    keep = with_ < without
    scores = (f"renders miss the frames by {with_[0]:.3f} with it and {without[0]:.3f} without (summed log ratios "
              f"beyond tolerance; all ratios {with_[1]:.3f} and {without[1]:.3f})")  # fmt: skip
    for line in said_blur if keep else said:
        log(line)
    chosen_px, chosen = (px_b, model_b) if keep else (px, model)
    b = chosen_px["meas"]["processor_blur"]
    b["auto"] = {"kept": bool(keep), "with": list(with_), "without": list(without)}
    b["note"] += f" -- --processor-blur auto: {'kept' if keep else 'not kept'}, its {scores}"
    log(f"fit-camera: a processor's blur of {blur['px']:.2f} px {'kept' if keep else 'tried and not kept'}: {scores}")
    return chosen_px, chosen


def measure_pixels(
    fr: Frames, solved: list, g, cfg0, sky, log, camera_file: bool = False, processor_blur: bool = False
) -> dict:
    """Step 4 and 5: the sensor (:func:`skygen.real.fit_sensor.fit_sensor`: the mean-variance line where the
    frames constrain it, else a direct fit of the background's level and noise, saying so), PSF, hot pixels,
    the real zero point and the detector settings, on the frames of the fitted camera (frames of another
    camera left out). ``camera_file``: the start camera is the user's (its bias may be kept)."""
    from skygen.real import fit_pixels as P
    from skygen.real.fit_sensor import fit_sensor

    own = [n for n in fr.names if n not in fr.other_camera]
    bgs = [fr.background_of(n) for n in own]
    boxes = sensor_boxes(bgs)
    start_name = "the camera file's" if camera_file else "skygen's default camera's"
    pattern = P.fixed_pattern(
        [fr.image_of(n) for n in own],
        [b["level_map"] for b in bgs],
        [b["sigma_map"] for b in bgs],
        cfg0.sensor.prnu_frac,
    )
    # a processor's blur (neighbouring pixels' noise correlated): measured and reported; rendered with --processor-blur,
    # the sensor and PSF then fitted as they were before it
    blur = P.processor_blur([fr.image_of(n) for n in own], float(np.median(boxes["sigma"])))
    blur_px = blur["px"] if processor_blur else 0.0
    fpn = pattern["fpn_adu"]
    if blur_px > 0:
        blur["note"] = blur["note"].split(": a processor's blur")[0] + (
            f": rendered as a processor's blur, sensor.processor_blur_px {blur_px:.2f}; the "
            f"read-out's noise before it {1 / np.sqrt(blur['variance_factor']):.2f} x the frames', its PSF narrower in "
            "quadrature"
        )
        log(f"fit-camera: {blur['note']}")
        boxes = P.unblurred_boxes(boxes, blur_px)
        fpn = None if fpn is None else float(fpn / np.sqrt(blur["variance_factor"]))
    sensor, sensor_rec = fit_sensor(
        boxes,
        cfg0.sensor,
        cfg0.sensor.bias_adu if camera_file else None,
        int(round(fr.sat)),
        start_name,
        fpn_measured=fpn,
    )
    sensor_rec["fixed_pattern"] = pattern
    if sensor.said:
        log(f"fit-camera: {sensor.said}")
    cam = g.camera
    s_imgs = [fr.image_of(fs.name) for fs in solved]
    s_bgs = [fr.background_of(fs.name) for fs in solved]
    matched = [fs.det_index[m] for fs, m in zip(solved, g.keep)]
    psf = P.psf_fit(s_imgs, [b["level_map"] for b in s_bgs], [fs.det for fs in solved], matched, cam.aspect, fr.sat)
    psf = P.unblurred_psf(psf, blur_px)
    hot = P.hot_pixels([fr.image_of(n) for n in own], [b["level_map"] for b in bgs], [b["sigma_map"] for b in bgs])
    zp_real, stars = _zero_point_real(solved, g, s_bgs, fr.sat)
    settings = choose_detector(solved, s_imgs, cam, g.rotations, sky, [_maps(b) for b in s_bgs])
    meas = {
        **sensor.terms(float(np.median([b["centre_adu"] for b in bgs])), int(round(fr.sat))),
        "level_adu": float(np.median([b["level_adu"] for b in bgs])),
        "centre_adu": float(np.median([b["centre_adu"] for b in bgs])),
        "corner_drop_adu": float(np.median([b["corner_drop_adu"] for b in bgs])),
        "background_residual_adu": float(np.median([b["residual_std_adu"] for b in bgs])),
        "gradient_adu": float(np.median([b["gradient_adu"] for b in bgs])),
        "bits": fr.bits,
        "psf": psf,
        "hot": hot,
        "blooming": P.blooming(s_imgs, fr.sat),
        "processor_blur": blur,
        "processor_blur_px": blur_px,
        "settings": settings,
        # per axis: the geometry fit's residual over every matched star (its rms is radial, sqrt(dx^2 + dy^2))
        "centroid_sigma_px": float(g.rms_px / np.sqrt(2.0)),
        # each frame's own zero point: frames taken at other exposures (or gains) than the others
        "frame_zero_points": frame_zero_points(stars, len(solved)),
    }
    return {"mv": sensor_rec, "meas": meas, "zp_real": zp_real, "stars": stars, "boxes": boxes, "sensor": sensor}


#: a frame's zero point needs this many matched unsaturated stars (NaN with fewer)
FRAME_ZP_MIN_STARS = 5
#: the frames' zero points "differ" (frames of other exposures or gains, said in the report and on the terminal)
#: where the brightest and faintest frame's are this far apart (mag)
FRAME_ZP_SPREAD_MAG = 0.5


def frame_zero_points(stars: dict, n_frames: int) -> list[float]:
    """Per solved frame, the median of Hp + 2.5 log10 flux over its matched stars that the pooled zero point
    keeps (:func:`_zero_point_real`'s ``stars``), NaN where fewer than :data:`FRAME_ZP_MIN_STARS`."""
    out = []
    zp = stars["mag"] + 2.5 * np.log10(np.maximum(stars["flux_adu"], 1e-12)) if stars["n"] else np.zeros(0)
    for k in range(n_frames):
        sel = stars["frame"] == k if stars["n"] else np.zeros(0, bool)
        out.append(float(np.median(zp[sel])) if sel.sum() >= FRAME_ZP_MIN_STARS else float("nan"))
    return out


def exposure_note(zps: list[float], pooled: float, names: list[str]) -> str | None:
    """The line saying that the frames' own zero points spread beyond :data:`FRAME_ZP_SPREAD_MAG` (None where
    they do not): the camera renders one exposure, the pooled one; each frame's exposure relative to it is in
    fit.json (``solved[k].exposure_scale``), which the renders-vs-real check
    (:func:`skygen.real.fit_render.frame_exposure_scales`) and ``benchmarks/sim_vs_real.py --fit-report`` render
    with."""
    from skygen.real.fit_render import frame_exposure_scales

    if frame_exposure_scales(zps, pooled, FRAME_ZP_SPREAD_MAG) is None:  # one exposure: nothing to say
        return None
    z = np.asarray(zps, dtype=np.float64)
    ok = np.isfinite(z)
    lo, hi = int(np.nanargmin(z)), int(np.nanargmax(z))
    return (
        f"frames of different exposures or gains: their own zero points span {z[lo]:.2f} ({Path(names[lo]).name}) "
        f"to {z[hi]:.2f} mag ({Path(names[hi]).name}), {np.ptp(z[ok]):.2f} mag, more than the "
        f"{FRAME_ZP_SPREAD_MAG} mag frames of one exposure are taken to span; the camera renders one exposure, the "
        f"pooled zero point's {pooled:.2f} mag (x {10 ** (0.4 * (z[lo] - pooled)):.2f} to "
        f"x {10 ** (0.4 * (z[hi] - pooled)):.2f} "
        "for these frames: fit.json's exposure_scale per frame); the renders-vs-real check renders each frame at "
        "its own, as sim_vs_real.py --fit-report does"
    )


def sensor_boxes(bgs: list) -> dict:
    """The background boxes of all frames (:func:`skygen.real.fit_pixels.background`) as the sensor fit's
    arrays: level, noise variance (odd-row differences), the level's own noise and the clipped sigma."""
    return {
        "level": np.concatenate([b["box_level"] for b in bgs]),
        "variance": np.concatenate([b["box_sigma"] for b in bgs]) ** 2,
        "level_noise": np.concatenate([b["box_level_noise"] for b in bgs]),
        "sigma": np.concatenate([b["box_clip_sigma"] for b in bgs]),
    }


def _zero_point_real(solved, g, bgs, sat):
    """Zero point of the real frames and the matched unsaturated stars (flux ADU, Hp, B-V)."""
    from skygen.real.fit_pixels import zero_point_rows

    flux, mag, bv, peak, lev, frame, r2 = [], [], [], [], [], [], []
    cam = g.camera
    for k, (fs, m, b) in enumerate(zip(solved, g.keep, bgs)):
        d = fs.det_index[m]
        frame.append(np.full(len(d), k))
        r2.append(cam.corner_r2(fs.det["x_px"][d], fs.det["y_px"][d]))
        flux.append(fs.det["flux_adu"][d])
        peak.append(fs.det["peak_adu"][d])
        xi = np.clip(np.round(fs.det["x_px"][d]).astype(int), 0, b["level_map"].shape[1] - 1)
        yi = np.clip(np.round(fs.det["y_px"][d]).astype(int), 0, b["level_map"].shape[0] - 1)
        lev.append(b["level_map"][yi, xi])
        mag.append(fs.star_mag[m])
        bv.append(fs.star_bv[m])
    flux, mag, bv, peak, lev, frame, r2 = (
        np.concatenate(a).astype(float) for a in (flux, mag, bv, peak, lev, frame, r2)
    )
    # the photometric fits (vignetting, scatter, false stars) take the matches the zero point keeps: a detection
    # far brighter than the faint star it was paired with is not that star
    zp, ok = zero_point_rows(flux, mag, peak, lev, sat)
    return zp, {
        "flux_adu": flux[ok],
        "mag": mag[ok],
        "bv": bv[ok],
        "frame": frame[ok].astype(int),
        "r2": r2[ok],
        "n": int(ok.sum()),
    }


def choose_detector(solved, imgs, cam, rotations, sky, box_maps: list | None = None) -> dict:
    """Threshold and background box that maximise (catalogue stars found) - (other detections).

    ``box_maps``: each image's ``BOX_PX`` background (:func:`_maps`), when already estimated; each frame's
    backgrounds are estimated once and shared by every threshold."""
    from scipy.spatial import cKDTree

    from skygen.instrument.detect import background_map, detect, estimate_background

    found = {(box, thr): 0 for box in BOXES for thr in THRESHOLDS}
    other = dict(found)
    for k, (im, R) in enumerate(zip(imgs, rotations)):
        idx = sky.cone(R[:, 2], cam.corner_radius_rad() + 0.01)
        x, y, front = cam.project(sky.vectors[idx] @ R)
        ok = front & cam.inside(x, y)
        tree = cKDTree(np.column_stack([x[ok], y[ok]])) if ok.any() else None
        for box in BOXES:
            if box == 0:
                bg = estimate_background(im)
            elif box == BOX_PX and box_maps is not None:
                bg = box_maps[k]
            else:
                bg = background_map(im, box)
            for thr in THRESHOLDS:
                det, _, _ = detect(im, thr, DETECT["min_area_px"], 100_000, box, background=bg)
                if tree is None or not len(det["x_px"]):
                    other[box, thr] += len(det["x_px"])
                    continue
                d, _ = tree.query(np.column_stack([det["x_px"], det["y_px"]]))
                found[box, thr] += int(np.sum(d <= 2.0))
                other[box, thr] += int(np.sum(d > 2.0))
    rows = [
        {
            "threshold_sigma": thr,
            "background_box_px": box,
            "catalogue_per_frame": found[box, thr] / len(imgs),
            "other_per_frame": other[box, thr] / len(imgs),
            "score": (found[box, thr] - other[box, thr]) / len(imgs),
        }
        for box in BOXES
        for thr in THRESHOLDS
    ]
    best = max(rows, key=lambda r: (r["score"], r["threshold_sigma"]))
    return {**best, "min_area_px": DETECT["min_area_px"], "grid": rows}


def neighbour_correlation(residuals: list, positions: list, within_px: float = NEIGHBOUR_PX) -> dict:
    """{n, corr}: over pairs of matched stars of one frame within ``within_px`` of each other, the mean dot product
    of their residual vectors over the mean squared residual: ~0 for a centroid scatter drawn afresh per star, ~1 for
    a field the camera model misses (distortion beyond its terms)."""
    dots, sq = [], []
    for r, p in zip(residuals, positions):
        if len(r) < 2:
            continue
        sq.append(np.sum(r**2, 1))
        i, j = np.triu_indices(len(r), 1)
        near = np.hypot(*(p[i] - p[j]).T) < within_px
        dots.append(np.sum(r[i[near]] * r[j[near]], 1))
    d = np.concatenate(dots) if dots else np.zeros(0)
    v = float(np.mean(np.concatenate(sq))) if sq else float("nan")
    return {"within_px": within_px, "n": int(d.size), "corr": float(d.mean() / v) if d.size and v > 0 else float("nan")}


def _record(
    names,
    dropped,
    solved,
    g,
    cam0,
    cam,
    mv,
    meas,
    zp_real,
    exposure,
    real_stats,
    before,
    after,
    cfg,
    scale,
    sat,
    fov_range,
    camera,
    command,
    timing,
    epoch,
) -> dict:
    from skygen.config import config_dict
    from skygen.real.fit_render import tone_exposure_power
    from skygen.runtime import hardware

    per_frame = []
    zps = meas.get("frame_zero_points") or [float("nan")] * len(solved)
    tone = meas.get("tone", {})  # through a fitted tone curve a zero point moves as the exposure to a power
    nan = float("nan")
    power = tone_exposure_power(tone.get("real_exponent", nan), tone.get("linear_exponent", nan))
    power = power if tone.get("gamma", 1.0) < 1.0 else 1.0
    for fs, r, p, R, zp in zip(solved, g.residuals, g.positions, g.rotations, zps):
        from skygen.real.fit_geometry import radec_roll

        ra, dec, roll = radec_roll(R)
        per_frame.append(
            {
                "frame": Path(fs.name).name,
                "solved_fov_deg": fs.fov_deg,
                "matched": int(len(r)),
                "rms_px": float(np.sqrt(np.mean(np.sum(r**2, 1)))) if len(r) else float("nan"),
                "ra_deg": ra,
                "dec_deg": dec,
                "roll_deg": roll,
                # the frame's own zero point, and its exposure relative to the camera's (the pooled zero point)
                "zero_point_mag": zp,
                "exposure_scale": float(10 ** (0.4 * (zp - zp_real) * power)) if np.isfinite(zp - zp_real) else nan,
            }
        )
    allr = np.concatenate(g.residuals)
    allp = np.concatenate(g.positions)
    rad = np.hypot(allp[:, 0] - cam.cx_px, (allp[:, 1] - cam.cy_px) * cam.aspect)
    edges = np.linspace(0, np.hypot(cam.width_px / 2, cam.height_px * cam.aspect / 2), 6)
    radial = []
    for a, b in zip(edges[:-1], edges[1:]):
        sel = (rad >= a) & (rad < b)
        radial.append(
            {
                "r_lo_px": float(a),
                "r_hi_px": float(b),
                "n": int(sel.sum()),
                "rms_px": float(np.sqrt(np.mean(np.sum(allr[sel] ** 2, 1)))) if sel.any() else float("nan"),
            }
        )
    # is the residual random per star (a centroid scatter renders can draw: optics.star_jitter_px) or a field the
    # model misses? By catalogue magnitude, and the correlation of two stars' residuals in one frame
    mags = np.concatenate([fs.star_mag[m] for fs, m in zip(solved, g.keep)])
    by_mag = []
    for lo in np.arange(np.floor(mags.min()), np.ceil(mags.max()), 1.0) if len(mags) else []:
        sel = (mags >= lo) & (mags < lo + 1)
        if sel.sum() >= 5:
            by_mag.append({"mag_lo": float(lo), "n": int(sel.sum()), "rms_px": float(np.sqrt(np.mean(allr[sel] ** 2)))})
    keys = (
        "background_adu",
        "noise_adu",
        "detections",
        "catalogue_detections",
        "star_sigma_px",
        "zero_point_mag",
        "nonstar_brightest10",
        "sharp_sources",
        "half_detected_mag",
    )
    from skygen.real.frame_stats import median_of

    def med(rows, k):  # counts of rare sources are mostly 0: their mean tells more
        if k in ("nonstar_brightest10", "sharp_sources"):
            vals = [float(r[k]) for r in rows if k in r]
            return float(np.mean(vals)) if vals else float("nan")
        return median_of(rows, k)

    compare = {
        k: {"real": med(real_stats, k), "fitted": med(after, k), "start": med(before, k) if before else float("nan")}
        for k in keys
    }
    strip = lambda rows: [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows] if rows else None  # noqa: E731
    return {
        "command": command,
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "hardware": hardware(),
        "timing_s": timing,
        "epoch_yr": epoch,
        "value_scale": scale,
        "saturation_adu": sat,
        "start": {
            "camera_file": str(camera) if camera else None,
            "fov_range_deg": list(fov_range) if fov_range else None,
            "f_px": cam0.f_px,
            "fov_deg": cam0.fov_deg[0],
            "aspect": cam0.aspect,
        },
        "frames": [Path(n).name for n in names],
        "solved": per_frame,
        "dropped": [{"frame": Path(n).name, "reason": w} for n, w in dropped],
        "geometry": {
            "f_px": cam.f_px,
            "fov_deg": cam.fov_deg[0],
            "fov_v_deg": cam.fov_deg[1],
            "aspect": cam.aspect,
            "cx_px": cam.cx_px,
            "cy_px": cam.cy_px,
            "k1": cam.k1,
            "k2": cam.k2,
            "fitted": g.fitted,
            "fixed": g.fixed,
            "sigma": g.sigma,
            "rms_px": g.rms_px,
            "n_matched": int(len(allr)),
            "radial": radial,
            "by_magnitude": by_mag,
            "neighbour_correlation": neighbour_correlation(g.residuals, g.positions),
        },
        "sensor": {k: v for k, v in mv.items() if k != "mean_variance"},
        "mean_variance": mv["mean_variance"],
        "pixels": {k: v for k, v in meas.items() if k != "settings"},
        "detector": meas["settings"],
        "zero_point_real_mag": zp_real,
        "exposure_s": exposure,
        "compare": compare,
        "real_stats": real_stats,
        "fitted_stats": strip(after),
        "start_stats": strip(before),
        "config": config_dict(cfg),
        "_render_example": after[0]["_image"] if after else None,
    }
