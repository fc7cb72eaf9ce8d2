"""A detector emulator: what :func:`skygen.instrument.detect.detect` would report, without pixels.

The ``detections`` stream (:mod:`skygen.stream.samples`) needs detection sets at ~0.1 ms each;
rendering and detecting a frame costs ~12 ms. The emulator replaces pixels and detector
by an empirical model *fitted to the real detector* on rendered frames
(:mod:`skygen.stream.calibration`), never tuned by hand. This module is the model; fitting it is
:mod:`skygen.stream.calibration`.

The variable everything is binned on
    ``u = log10(electrons / threshold_e)``, a source's expected electrons over the
    electrons a centred point source needs for its peak pixel to reach the detection
    threshold (``threshold_sigma x background noise / peak fraction of the PSF``). Brighter
    sky, more read noise or a higher threshold move ``threshold_e``, so the same curve
    carries the dependence on background and noise settings to first order.

What is modelled (each from the calibration frames)
    * completeness: probability that an isolated source is detected, per 0.1 in ``u``;
    * centroid error, flux response (``flux_adu / electrons``), peak response and area:
      every detection of an isolated source in the calibration frames is kept as a row
      ``(dx, dy, log10 flux ratio, log10 peak ratio, area)`` in the bin of its ``u``; an
      emulated detection draws one row of its bin, so the joint distribution (tails,
      saturation of bright stars, the flux lost outside the detector's aperture) is the
      real one;
    * blending: the probability that two detectable sources come out as two detections, as
      a function of the *gap* between their above-threshold footprints,
      ``g = d - sigma (sqrt(2 ln(e_a / threshold_e)) + sqrt(2 ln(e_b / threshold_e)))`` (d the
      separation, sigma the PSF width: each term is the radius at which a Gaussian star
      falls to the threshold). The probability is a logistic curve in ``g`` fitted by maximum
      likelihood to the catalog pairs of the calibration frames plus a designed experiment
      of pairs painted into frames and run through the real sensor model and detector
      (:func:`skygen.stream.calibration.painted_pairs`); a merged
      pair becomes one detection at the flux-weighted mean position with the summed
      electrons;
    * spurious detections (cosmic rays, hot-pixel clusters, stars just outside the frame):
      the per-frame count distribution and their (flux, peak, area) rows; positions
      uniform on the sensor.

What is not modelled
    the dependence of the centroid error on sub-pixel phase and on the position on the
    sensor (vignetting is in the electrons, distortion in the projection), partial stars
    at the sensor edge (their detection rate is averaged into the completeness), a
    spurious detection's position correlating with a bright star (blooming trails),
    motion-blur streaks beyond what the calibration frames contain, and any dependence on
    settings that changed after calibration: a calibration is valid only for the camera,
    optics, photometry, sensor, detector and sensor-stage corruption levels it was made
    with, and :func:`check_compatible` refuses any other (naming the keys).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from skygen import hashrng
from skygen.errors import ConfigError, DatasetError

CALIBRATION_FORMAT = "skygen-detector-calibration"
CALIBRATION_VERSION = 1
U_EDGES = np.round(np.arange(-1.0, 5.0001, 0.1), 6)  # log10(electrons / threshold_e)
GAP_EDGES = np.round(np.arange(-6.0, 6.0001, 0.25), 6)  # px, gap between the threshold radii of a pair
BLEND_MAX_PX = 12.0  # pairs further apart than this are always resolved
ISOLATION_PX = 10.0  # sources with a detectable neighbour closer than this are not used for rows
BANK_ROWS_PER_BIN = 200
KEY_SECTIONS = ("camera", "optics", "photometry", "sensor", "detection")
KEY_CORRUPTIONS = ("hotpixels", "cosmic_rays", "motion_blur", "stray_light", "read_noise")
STREAM_CORRUPTIONS = ("false_stars", "dropout", "centroid_noise", "magnitude_noise")
# sources the stream places itself, as it does false stars: a calibration is made without them and does not
# depend on them (skygen.stream.calibration.calibration_config)
STREAM_SOURCES = ("sensor.fixed_sources",)
# draw ids of one source (the stream multiplies the source id by DRAWS_PER_SOURCE)
DRAWS_PER_SOURCE = 8
_D_DETECT, _D_ROW, _D_BLEND = 0, 1, 2


def calibration_key(config: dict) -> dict:
    """The flat config values a calibration depends on (see the module docstring)."""
    key = {}
    for sec in KEY_SECTIONS:
        for k, v in config[sec].items():
            key[f"{sec}.{k}"] = list(v) if isinstance(v, (list, tuple)) else v
    for name in KEY_CORRUPTIONS:
        key[f"corruptions.{name}"] = config["corruptions"][name]
    key["detection.max_detections"] = config["detection"]["max_detections"]
    from skygen.identity import NEUTRAL_DEFAULTS, STORAGE_KEYS

    return {
        k: v
        for k, v in key.items()
        if k not in STORAGE_KEYS
        and k not in STREAM_SOURCES
        and not (k in NEUTRAL_DEFAULTS and v == NEUTRAL_DEFAULTS[k])
    }


def threshold_electrons(renderer) -> float:
    """Electrons a centred point source needs for its peak pixel to reach the threshold."""
    from skygen.instrument.psf import peak_fraction

    o = renderer.cfg.optics
    return float(
        renderer.cfg.detection.threshold_sigma
        * renderer.noise_e()
        / peak_fraction(o.psf, o.psf_sigma_px, o.moffat_beta, renderer.camera.aspect)
    )


@dataclass(frozen=True)
class DetectorModel:
    """A fitted emulator (see the module docstring).

    Build with :func:`skygen.stream.calibration.calibrate_from_renders` or :func:`load`."""

    key: dict
    threshold_e: float
    completeness: np.ndarray  # (n_bins,) per U_EDGES bin
    bank_start: np.ndarray  # (n_bins + 1,) rows of bin b: bank[...][start[b]:start[b+1]]
    bank: dict  # dx, dy, log_flux_ratio, log_peak_ratio, area
    p_resolved: np.ndarray  # (len(GAP_EDGES) - 1,) per footprint-gap bin
    psf_sigma_px: float
    spurious_pmf: np.ndarray  # P(n spurious detections in a frame), n = 0, 1, ...
    spurious: dict  # flux_adu, peak_adu, area_px rows
    gain_e_per_adu: float
    info: dict  # how it was made, summary statistics

    # ------------------------------------------------------------------ lookups
    def __post_init__(self) -> None:
        counts = np.diff(self.bank_start)
        have = np.flatnonzero(counts > 0)
        if len(have) == 0:
            raise DatasetError("detector calibration holds no detections; calibrate on frames with stars")
        nearest = have[np.abs(np.arange(len(counts))[:, None] - have[None, :]).argmin(axis=1)]
        object.__setattr__(self, "_row_bin", nearest)
        object.__setattr__(self, "_spurious_cdf", np.cumsum(self.spurious_pmf))

    def gap(self, e_a: np.ndarray, e_b: np.ndarray, d_px: np.ndarray) -> np.ndarray:
        """Separation minus the two threshold radii, px (see the module docstring)."""
        return gap_px(e_a, e_b, d_px, self.threshold_e, self.psf_sigma_px)

    def p_resolved_of(self, e_a: np.ndarray, e_b: np.ndarray, d_px: np.ndarray) -> np.ndarray:
        b = np.clip(np.searchsorted(GAP_EDGES, self.gap(e_a, e_b, d_px), side="right") - 1, 0, len(self.p_resolved) - 1)
        return np.where(np.asarray(d_px) > BLEND_MAX_PX, 1.0, self.p_resolved[b])

    def blend_radius_px(self, electrons_each: float) -> float:
        """Separation below which two stars of ``electrons_each`` merge more often than not."""
        d = np.linspace(0, BLEND_MAX_PX, 241)
        e = np.full_like(d, electrons_each)
        merged = np.flatnonzero(self.p_resolved_of(e, e, d) < 0.5)
        return float(d[merged[-1]]) if len(merged) else 0.0

    def u_of(self, electrons: np.ndarray) -> np.ndarray:
        return np.log10(np.maximum(np.asarray(electrons, np.float64), 1e-12) / self.threshold_e)

    def bin_of(self, u: np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(U_EDGES, u, side="right") - 1, 0, len(U_EDGES) - 2)

    def p_detect(self, electrons: np.ndarray) -> np.ndarray:
        u = self.u_of(electrons)
        p = self.completeness[self.bin_of(u)]
        return np.where(u < U_EDGES[0], 0.0, p)

    # ------------------------------------------------------------------ emulation
    def emulate(
        self,
        key,
        sample: np.ndarray,
        source_id: np.ndarray,
        frame: np.ndarray,
        x: np.ndarray,
        y: np.ndarray,
        electrons: np.ndarray,
    ) -> dict:
        """Emulated detections of sources (one row each, any number of frames at once).

        ``sample`` is each source's sample index and ``source_id`` a per-sample unique id
        (the stream's draw namespace); ``frame`` groups sources into frames (any integer
        label). Returns the detected rows: ``src`` (row of the input source, -1 for none),
        ``frame``, ``x_px``, ``y_px``, ``flux_adu``, ``peak_adu``, ``area_px``; spurious
        detections are added by :meth:`spurious_detections`.
        """
        draw = np.asarray(source_id, np.int64) * DRAWS_PER_SOURCE
        e = np.asarray(electrons, np.float64).copy()
        xs, ys = np.asarray(x, np.float64).copy(), np.asarray(y, np.float64).copy()
        det = hashrng.uniform(key, sample, draw + _D_DETECT) < self.p_detect(e)
        idx = np.flatnonzero(det)
        alive = np.ones(len(idx), bool)
        rmax = BLEND_MAX_PX
        if len(idx) > 1:
            # pairs in the same frame: frames are placed far apart along x
            span = 4.0 * (np.abs(xs[idx]).max() + np.abs(ys[idx]).max() + 10.0)
            fr = np.asarray(frame, np.int64)[idx]
            pts = np.column_stack([xs[idx] + (fr - fr.min()) * span, ys[idx]])
            pairs = cKDTree(pts).query_pairs(rmax, output_type="ndarray")
            if len(pairs):
                # the brighter source absorbs the fainter; brightest pairs first
                a, b = pairs[:, 0], pairs[:, 1]
                swap = e[idx[b]] > e[idx[a]]
                a, b = np.where(swap, b, a), np.where(swap, a, b)
                d = np.hypot(xs[idx[a]] - xs[idx[b]], ys[idx[a]] - ys[idx[b]])
                u_b = hashrng.uniform(key, np.asarray(sample)[idx[b]], draw[idx[b]] + _D_BLEND)
                merge = u_b >= self.p_resolved_of(e[idx[a]], e[idx[b]], d)
                for j in np.argsort(-e[idx[a]])[merge[np.argsort(-e[idx[a]])]]:
                    ia, ib = a[j], b[j]
                    if not (alive[ia] and alive[ib]):
                        continue
                    sa, sb = idx[ia], idx[ib]
                    tot = e[sa] + e[sb]
                    xs[sa] = (xs[sa] * e[sa] + xs[sb] * e[sb]) / tot
                    ys[sa] = (ys[sa] * e[sa] + ys[sb] * e[sb]) / tot
                    e[sa] = tot
                    alive[ib] = False
        idx = idx[alive]
        b = self._row_bin[self.bin_of(self.u_of(e[idx]))]
        n_rows = self.bank_start[b + 1] - self.bank_start[b]
        ur = hashrng.uniform(key, np.asarray(sample)[idx], draw[idx] + _D_ROW)
        r = self.bank_start[b] + np.minimum((ur * n_rows).astype(np.int64), n_rows - 1)
        bk = self.bank
        return {
            "src": idx,
            "frame": np.asarray(frame)[idx],
            "x_px": xs[idx] + bk["dx"][r],
            "y_px": ys[idx] + bk["dy"][r],
            "flux_adu": (e[idx] * 10 ** bk["log_flux_ratio"][r]).astype(np.float32),
            "peak_adu": (e[idx] * 10 ** bk["log_peak_ratio"][r]).astype(np.float32),
            "area_px": bk["area"][r].astype(np.int32),
        }

    def spurious_detections(self, key, samples: np.ndarray, draw_base: int, width_px: int, height_px: int) -> dict:
        """Spurious detections of frames ``samples`` (one entry per frame): rows with ``frame``
        = position in ``samples``."""
        samples = np.asarray(samples, np.int64)
        u = hashrng.uniform(key, samples, draw_base)
        n = np.searchsorted(self._spurious_cdf, u, side="right").clip(0, len(self.spurious_pmf) - 1)
        frame = np.repeat(np.arange(len(samples)), n)
        k = np.arange(len(frame)) - np.repeat(np.cumsum(n) - n, n)
        s = samples[frame]
        d = draw_base + 1 + 4 * k
        r = np.minimum(
            (hashrng.uniform(key, s, d) * len(self.spurious["flux_adu"])).astype(np.int64),
            len(self.spurious["flux_adu"]) - 1,
        )
        return {
            "frame": frame,
            "x_px": -0.5 + width_px * hashrng.uniform(key, s, d + 1),
            "y_px": -0.5 + height_px * hashrng.uniform(key, s, d + 2),
            "flux_adu": self.spurious["flux_adu"][r].astype(np.float32),
            "peak_adu": self.spurious["peak_adu"][r].astype(np.float32),
            "area_px": self.spurious["area_px"][r].astype(np.int32),
        }

    # ------------------------------------------------------------------ persistence
    def to_json(self) -> dict:
        def r(a, d=5):
            return np.round(np.asarray(a, np.float64), d).tolist()

        body = {
            "format": CALIBRATION_FORMAT,
            "version": CALIBRATION_VERSION,
            "key": self.key,
            "threshold_e": self.threshold_e,
            "gain_e_per_adu": self.gain_e_per_adu,
            "u_edges": r(U_EDGES, 6),
            "gap_edges_px": r(GAP_EDGES, 6),
            "psf_sigma_px": self.psf_sigma_px,
            "completeness": r(self.completeness),
            "p_resolved": r(self.p_resolved),
            "bank_start": self.bank_start.tolist(),
            "bank": {k: (v.astype(int).tolist() if k == "area" else r(v, 4)) for k, v in self.bank.items()},
            "spurious_pmf": r(self.spurious_pmf, 6),
            "spurious": {k: (v.astype(int).tolist() if k == "area_px" else r(v, 2)) for k, v in self.spurious.items()},
            "info": self.info,
        }
        body["sha256"] = _digest(body)
        return body


def _digest(body: dict) -> str:
    content = {k: v for k, v in body.items() if k != "sha256"}
    return hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()


def save(model: DetectorModel, path: str | Path) -> Path:
    """Write the calibration as JSON (atomically)."""
    from skygen.datasets.shards import write_json_atomic

    path = Path(path)
    write_json_atomic(path, model.to_json())
    return path


def load(path: str | Path) -> DetectorModel:
    """Read a calibration file; a foreign, damaged or newer file raises :class:`DatasetError`."""
    path = Path(path)
    try:
        body = json.loads(path.read_text())
    except FileNotFoundError:
        raise DatasetError(
            f"{path}: detector calibration not found; make one with `skygen calibrate DATASET "
            f"--out {path}` or use the shipped default"
        ) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(
            f"{path}: not a readable detector calibration (JSON: {exc}); re-create it with `skygen calibrate`"
        ) from None
    if not isinstance(body, dict) or body.get("format") != CALIBRATION_FORMAT:
        raise DatasetError(
            f"{path}: not a skygen detector calibration "
            f"(format {body.get('format') if isinstance(body, dict) else None!r}); "
            "give a file written by `skygen calibrate`"
        )
    if body.get("version") != CALIBRATION_VERSION:
        raise DatasetError(
            f"{path}: calibration version {body.get('version')!r}; this skygen reads version "
            f"{CALIBRATION_VERSION} (re-create it with `skygen calibrate`)"
        )
    if body.get("sha256") != _digest(body):
        raise DatasetError(
            f"{path}: calibration checksum mismatch (edited or damaged); re-create it with `skygen calibrate`"
        )
    try:
        if body["u_edges"] != np.round(U_EDGES, 6).tolist() or body["gap_edges_px"] != np.round(GAP_EDGES, 6).tolist():
            raise DatasetError(f"{path}: calibration bins differ from this skygen's; re-create it")

        def a(v, t=np.float64):
            return np.asarray(v, t)

        return DetectorModel(
            key=body["key"],
            threshold_e=float(body["threshold_e"]),
            completeness=a(body["completeness"]),
            bank_start=a(body["bank_start"], np.int64),
            bank={k: a(v) for k, v in body["bank"].items()},
            p_resolved=a(body["p_resolved"]),
            spurious_pmf=a(body["spurious_pmf"]),
            spurious={k: a(v) for k, v in body["spurious"].items()},
            gain_e_per_adu=float(body["gain_e_per_adu"]),
            info=body.get("info", {}),
            psf_sigma_px=float(body["psf_sigma_px"]),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise DatasetError(f"{path}: detector calibration is incomplete ({exc!r}); re-create it") from None


def default_calibration_path() -> Path:
    """The calibration shipped for the default camera."""
    return Path(__file__).parent / "data" / "detector-default.json"


def check_compatible(model: DetectorModel, config: dict, source: str = "calibration") -> None:
    """Refuse a calibration made for another camera/optics/sensor/detector (naming the keys)."""
    want = calibration_key(config)
    diff = sorted(k for k in set(want) | set(model.key) if _norm(want.get(k)) != _norm(model.key.get(k)))
    if diff:
        details = ", ".join(f"{k}: calibrated {model.key.get(k)!r}, asked {want.get(k)!r}" for k in diff[:6])
        more = f" and {len(diff) - 6} more" if len(diff) > 6 else ""
        raise ConfigError(
            f"{source} was made for another camera/sensor ({details}{more}); make one for this "
            "config with `skygen calibrate --config YOUR.yaml --out detector.json` (renders its "
            "own frames) and pass it with --calibration"
        )


def _norm(v):
    return list(v) if isinstance(v, tuple) else v


# ---------------------------------------------------------------------------------- fitting
def gap_px(e_a, e_b, d_px, threshold_e: float, sigma_px: float) -> np.ndarray:
    """Separation minus the radii at which two Gaussian stars fall to the threshold, px."""

    def r(e):
        return sigma_px * np.sqrt(2 * np.log(np.maximum(np.asarray(e, np.float64) / threshold_e, 1.0)))

    return np.asarray(d_px, np.float64) - r(e_a) - r(e_b)
