"""The registry of defects and disturbances, shared by the generator and robustness sweeps.

Each corruption has a name, the stage where it acts, a severity in physical units
(config key ``corruptions.<name>``; 0 means off and reproduces the clean frame exactly)
and a default list of severities for sweeps. ``fusion robustness --corruption NAME``
re-renders frames with :func:`with_level` or, for detection-level corruptions, calls
:func:`apply_detection_corruptions` on stored detections: the same code the generator runs.

Stages:
* ``sensor``   — acts on the charge or the read-out (re-render needed);
* ``scene``    — adds or moves light before the sensor (re-render needed);
* ``detections`` — acts on the detector's output list.

Every random draw of a corruption comes from its own generator derived from
(dataset seed, frame stream key, corruption name), so switching one on never changes the
random numbers of another.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

from skygen.errors import ConfigError

# Cosmic-ray deposit model: a minimum-ionising particle frees ~80 electron-hole pairs
# per micrometre of silicon (most probable value); the sensitive depth of a CMOS pixel
# is ~10 um. Track charge fluctuates (Landau tail) - modelled as log-normal, 0.3 dex.
COSMIC_E_PER_UM = 80.0
COSMIC_DEPTH_UM = 10.0
COSMIC_MAX_TRACK_PX = 200.0


@dataclass(frozen=True)
class Corruption:
    name: str
    stage: str
    unit: str
    sweep: tuple[float, ...]
    description: str
    combine: str = "add"  # how an extra severity stacks on a dataset's own: add, quadrature, probability

    def stack(self, base: float, extra: float) -> float:
        """Severity of ``extra`` applied on top of ``base`` (``extra`` = 0 gives ``base`` exactly)."""
        if extra == 0:
            return base
        if self.combine == "quadrature":
            return float((base**2 + extra**2) ** 0.5)
        if self.combine == "probability":
            return float(1 - (1 - base) * (1 - extra))
        return float(base + extra)


REGISTRY: dict[str, Corruption] = {
    c.name: c
    for c in (
        Corruption(
            "hotpixels",
            "sensor",
            "fraction of pixels",
            (0.0, 1e-4, 5e-4, 2e-3, 5e-3),
            "static hot pixels from the seeded sensor map (log-normal dark current); larger "
            "fractions are supersets of smaller ones",
        ),
        Corruption(
            "cosmic_rays",
            "sensor",
            "hits/cm^2/s",
            (0.0, 50.0, 200.0, 1000.0, 5000.0),
            "particle tracks: isotropic incidence through a 10 um sensitive layer, 80 e-/um",
        ),
        Corruption(
            "motion_blur",
            "scene",
            "deg/s",
            (0.0, 0.2, 0.5, 1.0, 2.0),
            "camera rotation at this rate about a random axis during the exposure (flux conserved)",
        ),
        Corruption(
            "stray_light",
            "scene",
            "e-/px/s",
            (0.0, 1e3, 5e3, 2e4, 1e5),
            "linear stray-light ramp across the frame, this bright at the brightest edge",
        ),
        Corruption(
            "read_noise",
            "sensor",
            "e- rms",
            (0.0, 5.0, 10.0, 20.0, 40.0),
            "extra Gaussian read noise added in quadrature to the sensor's",
            "quadrature",
        ),
        Corruption(
            "false_stars",
            "scene",
            "sources/frame",
            (0.0, 1.0, 2.0, 4.0, 8.0),
            "Poisson number of uncatalogued point sources (stars fainter than the catalogue, debris, "
            "glints) at random positions, magnitudes in the corruptions.false_star_span_mag above the "
            "detection limit, uniform or, with corruptions.false_star_slope, rising towards the limit "
            "as star counts do (see false_star_magnitudes)",
        ),
        Corruption(
            "dropout",
            "detections",
            "probability",
            (0.0, 0.1, 0.2, 0.3, 0.5),
            "each detection is lost independently with this probability",
            "probability",
        ),
        Corruption(
            "centroid_noise",
            "detections",
            "px rms",
            (0.0, 0.5, 1.0, 2.0, 4.0),
            "Gaussian error added to each detected centroid, per axis",
            "quadrature",
        ),
        Corruption(
            "magnitude_noise",
            "detections",
            "mag rms",
            (0.0, 0.1, 0.25, 0.5, 1.0),
            "Gaussian magnitude error applied to each detected flux",
            "quadrature",
        ),
    )
}


def get(name: str) -> Corruption:
    try:
        return REGISTRY[name]
    except KeyError:
        raise ConfigError(f"unknown corruption {name!r}; valid names: {', '.join(REGISTRY)}") from None


def with_level(cfg, name: str, level: float):
    """A RenderConfig with corruption ``name`` at ``level`` (validated like a config value)."""
    from skygen.config import build_config, config_dict

    get(name)
    data = config_dict(cfg)
    data["corruptions"][name] = level
    return build_config(data)


def with_extra(cfg, name: str, extra: float):
    """A RenderConfig with ``extra`` severity of ``name`` stacked on the config's own
    (see :meth:`Corruption.stack`); ``extra`` = 0 returns an identical config."""
    c = get(name)
    return with_level(cfg, name, c.stack(float(getattr(cfg.corruptions, name)), float(extra)))


def stage_rng(seed: int, frame: int | tuple[int, ...], stage: str) -> np.random.Generator:
    """The generator of one stage of one frame: depends only on (seed, frame key, stage name).

    ``frame`` is the frame's stream key: ``(split, index within split)`` for schema 2
    (:func:`skygen.identity.frame_key`), the global index for schema 1.x datasets.
    """
    key = list(frame) if isinstance(frame, tuple) else [frame]
    return np.random.default_rng([seed, *key, zlib.crc32(stage.encode())])


def levels_of(cfg) -> dict[str, float]:
    """Severity of every registered corruption in ``cfg`` (the section's shape parameters, such as
    ``false_star_slope``, are not severities and are not included)."""
    return {name: float(getattr(cfg.corruptions, name)) for name in REGISTRY}


def false_star_magnitudes(u: np.ndarray, limit_mag: float, slope: float = 0.0, span_mag: float = 4.0) -> np.ndarray:
    """Magnitudes of false stars from uniform draws ``u`` in [0, 1): inverse-CDF sampling of a density
    proportional to 10 ** (``slope`` * (m - ``limit_mag``)) on [limit - ``span_mag``, limit].

    ``slope`` is in dex per magnitude: 0 gives magnitudes uniform over the span (what frames made before the
    slope existed have, bit for bit); the counts of field stars rise by ~0.3-0.5 dex per magnitude at
    V = 9-12, so most uncatalogued sources sit just above the detection limit and few are bright.
    ``skygen fit-camera`` fits both from the detections the catalogue does not explain.
    """
    u = np.asarray(u, dtype=np.float64)
    if slope <= 0.0:
        return (limit_mag - span_mag + span_mag * u).astype(np.float32)
    k = slope * np.log(10.0)
    lo = np.exp(-k * span_mag)  # the bright end's density relative to the limit's
    return (limit_mag + np.log(lo + u * (1.0 - lo)) / k).astype(np.float32)


# ---------------------------------------------------------------- detection level
def apply_detection_corruptions(
    det: dict, levels: dict[str, float], seed: int, frame_index: int | tuple, stream: str = ""
) -> tuple[dict, dict]:
    """Apply dropout, centroid noise and magnitude noise to a detection table.

    Returns the new table (rows kept in brightness order of the perturbed flux) and a log.
    Severity 0 returns the table unchanged. ``stream`` selects independent random
    streams (a sweep applied on top of stored detections uses its own).
    """
    det = {k: np.array(v, copy=True) for k, v in det.items()}
    log = {}
    n = len(det["x_px"])
    p = levels.get("dropout", 0.0)
    if p > 0 and n:
        keep = stage_rng(seed, frame_index, "dropout" + stream).random(n) >= p
        det = {k: v[keep] for k, v in det.items()}
        log["dropout"] = {"n_dropped": int(n - keep.sum())}
        n = int(keep.sum())
    s = levels.get("centroid_noise", 0.0)
    if s > 0 and n:
        d = stage_rng(seed, frame_index, "centroid_noise" + stream).normal(0.0, s, size=(2, n))
        det["x_px"] = det["x_px"] + d[0]
        det["y_px"] = det["y_px"] + d[1]
        log["centroid_noise"] = {"rms_px": float(np.sqrt((d**2).mean()))}
    m = levels.get("magnitude_noise", 0.0)
    if m > 0 and n:
        dm = stage_rng(seed, frame_index, "magnitude_noise" + stream).normal(0.0, m, size=n)
        factor = (10 ** (-0.4 * dm)).astype(np.float32)
        det["flux_adu"] = det["flux_adu"] * factor
        det["peak_adu"] = det["peak_adu"] * factor
        order = np.argsort(-det["flux_adu"], kind="stable")
        det = {k: v[order] for k, v in det.items()}
        log["magnitude_noise"] = {"rms_mag": float(np.sqrt((dm**2).mean()))}
    return det, log


# ---------------------------------------------------------------- image level
def cosmic_ray_rate(shape: tuple[int, int], pitch_um: float, exposure_s: float, flux_cm2_s: float) -> float:
    """Expected cosmic-ray hits on the sensor over one exposure."""
    h, w = shape
    return flux_cm2_s * (h * pitch_um * 1e-4) * (w * pitch_um * 1e-4) * exposure_s


def cosmic_ray_charge(
    shape: tuple[int, int],
    pitch_um: float,
    exposure_s: float,
    flux_cm2_s: float,
    rng: np.random.Generator,
    n: int | None = None,
) -> tuple[list, list[tuple[int, int, int, int]], int]:
    """Cosmic-ray tracks as charge patches: ([(y0, x0, patch)], boxes, number of hits).
    ``n``: the number of hits when already drawn (Poisson with :func:`cosmic_ray_rate`)."""
    h, w = shape
    if n is None:
        n = int(rng.poisson(cosmic_ray_rate(shape, pitch_um, exposure_s, flux_cm2_s)))
    patches, boxes = [], []
    for _ in range(n):
        x, y = rng.uniform(-0.5, w - 0.5), rng.uniform(-0.5, h - 0.5)
        cos_t = np.sqrt(rng.random())  # isotropic flux through a plane
        cos_t = max(cos_t, 1e-3)
        phi = rng.uniform(0, 2 * np.pi)
        length_px = min(COSMIC_DEPTH_UM * np.sqrt(1 - cos_t**2) / cos_t / pitch_um, COSMIC_MAX_TRACK_PX)
        charge = COSMIC_E_PER_UM * COSMIC_DEPTH_UM / cos_t * 10 ** (0.3 * rng.standard_normal())
        m = max(2, int(np.ceil(length_px / 0.1)))
        tt = (np.arange(m) + 0.5) / m - 0.5
        px = np.floor(x + tt * length_px * np.cos(phi) + 0.5).astype(int)
        py = np.floor(y + tt * length_px * np.sin(phi) + 0.5).astype(int)
        ok = (px >= 0) & (px < w) & (py >= 0) & (py < h)
        if not ok.any():
            continue
        px, py = px[ok], py[ok]
        x0, y0 = px.min(), py.min()
        patch = np.zeros((py.max() - y0 + 1, px.max() - x0 + 1))
        np.add.at(patch, (py - y0, px - x0), charge / m)
        patches.append((int(y0), int(x0), patch))
        boxes.append((int(y0), int(y0) + patch.shape[0], int(x0), int(x0) + patch.shape[1]))
    return patches, boxes, n


def stray_light_angle(rng: np.random.Generator) -> float:
    """Direction (radians, from +x towards +y) of a frame's stray-light ramp."""
    return float(rng.uniform(0, 2 * np.pi))


def stray_light_ramp(shape: tuple[int, int], level_e_px_s: float, exposure_s: float, angle_rad: float) -> np.ndarray:
    """A linear ramp of stray light, e- over the exposure, float32 (H, W): 0 at the dark edge,
    ``level_e_px_s * exposure_s`` at the bright edge, rising along ``angle_rad``."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    ramp = (xx - (w - 1) / 2) * np.cos(angle_rad) + (yy - (h - 1) / 2) * np.sin(angle_rad)
    ramp = (ramp - ramp.min()) / (ramp.max() - ramp.min())
    return (level_e_px_s * exposure_s * ramp).astype(np.float32)
