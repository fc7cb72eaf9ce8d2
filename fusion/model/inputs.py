"""The model's input contract: one frame -> ``image``, ``coords``, ``mask`` tensors.

Training (shards and streams), evaluation, robustness sweeps, latency timing and
prediction all build their inputs with :class:`Preprocessor`, so a model sees the same
numbers wherever its frame came from.

Conventions (skygen's, see :mod:`skygen.conventions`): the image is the *stored* frame,
``[y, x]``, ``S x (H / f)`` pixels, area-averaged by the integer factor ``f = W / S`` from the
``W x H`` sensor; detection positions are in *full-resolution* sensor pixels with (0, 0) the
centre of the top-left pixel. A full-resolution position x lands on stored coordinate
``u = (x + 0.5) / f - 0.5``.

Image branch input
    The stored frame (ADU) mapped to [0, 1] by a fixed log stretch,
    ``x = log1p(max(adu - bias, 0) / s) / log1p((2**bits - 1 - bias) / s)`` with the
    dataset's ``sensor.bias_adu`` and ``sensor.bit_depth`` and ``s = data.norm_scale_adu``
    (8 ADU: the faint stars a tracker relies on stay visible next to saturated ones). One
    channel, shape (1, H/f, S); the model replicates it to 3 channels when it loads
    ImageNet weights.

Coordinate input (the explicit ordering/padding convention the paper asks for)
    Detections sorted by ``flux_adu`` descending (stable: ties keep skygen's order), the
    first ``max_stars`` kept, one row per star with features
    ``[x, y, log10(1 + flux_adu) - log_flux_offset]`` where ``x = (x_px + 0.5) / (W / 2) - 1``
    and ``y = (y_px + 0.5 - H / 2) / (W / 2)``: the sensor's outer pixel *edges* map to -1
    and +1 in x (the convention of ``torch.nn.functional.grid_sample(align_corners=False)``),
    the sensor centre to 0, and y uses the same scale (a non-square sensor spans
    ``[-H/W, H/W]`` in y), so distances and angles are preserved. Rows beyond the detected
    stars are zeros with ``mask = False``. The heatmap branch renders the same rows
    (:mod:`fusion.model.heatmap`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

COORD_FEATURES = ("x", "y", "log_flux")


@dataclass(frozen=True)
class FrameGeometry:
    """The sensor and stored-image geometry of a dataset (from its resolved render config).

    Sensors may be non-square: W x H full-resolution pixels stored as S x (H / f), f = W / S.
    ``sensor_h``/``image_h`` of 0 mean square (= ``sensor_px``/``image_px``).
    """

    sensor_px: int  # W, sensor columns
    image_px: int  # S, stored columns
    factor: int  # f = W / S
    bias_adu: float
    max_adu: float  # 2**bit_depth - 1
    psf_sigma_px: float  # full-resolution pixels
    sensor_h: int = 0  # H, sensor rows (0: = W)
    image_h: int = 0  # stored rows = H / f (0: = S)

    def __post_init__(self) -> None:
        if not self.sensor_h:
            object.__setattr__(self, "sensor_h", self.sensor_px)
        if not self.image_h:
            object.__setattr__(self, "image_h", self.sensor_h // self.factor)

    @classmethod
    def from_render_config(cls, config: dict) -> "FrameGeometry":
        w, h = int(config["camera"]["width_px"]), int(config["camera"]["height_px"])
        s = int(config["output"]["image_size_px"])
        return cls(
            w,
            s,
            w // s,
            # the dark level of the read-outs: the bias less a processor's black level (none in older datasets)
            float(max(int(config["sensor"]["bias_adu"]) - int(config["sensor"].get("black_level_adu", 0)), 0)),
            float(2 ** int(config["sensor"]["bit_depth"]) - 1),
            float(config["optics"]["psf_sigma_px"]),
            h,
            h // (w // s),
        )

    def normalised(self, x_px: np.ndarray, y_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Full-resolution pixels -> the models' coordinates: the sensor centre at 0, one scale for
        both axes (half the sensor width = 1), so x spans [-1, 1] and y [-H/W, H/W]; angles and
        distances are preserved (the canonical rotation needs that)."""
        half = self.sensor_px / 2.0
        return (
            (np.asarray(x_px, np.float64) + 0.5 - half) / half,
            (np.asarray(y_px, np.float64) + 0.5 - self.sensor_h / 2.0) / half,
        )

    def to_stored(self, xy_full: np.ndarray) -> np.ndarray:
        return (np.asarray(xy_full, np.float64) + 0.5) / self.factor - 0.5

    def to_full(self, uv_stored: np.ndarray) -> np.ndarray:
        return (np.asarray(uv_stored, np.float64) + 0.5) * self.factor - 0.5


@dataclass(frozen=True)
class Sample:
    """One frame in ADU: the stored image (float32, S x S) and its detections (brightest first)."""

    image: np.ndarray
    x_px: np.ndarray
    y_px: np.ndarray
    flux_adu: np.ndarray
    area_px: np.ndarray
    background_adu: float  # stored-image background level
    noise_adu: float  # stored-image background noise (full-res sigma / f)

    @property
    def n(self) -> int:
        return len(self.x_px)

    def take(self, keep: np.ndarray) -> "Sample":
        return replace(
            self, x_px=self.x_px[keep], y_px=self.y_px[keep], flux_adu=self.flux_adu[keep], area_px=self.area_px[keep]
        )

    def sorted(self) -> "Sample":
        """Brightest first (flux descending; ties keep their order)."""
        return self.take(np.argsort(-self.flux_adu, kind="stable"))


def normalise_image(adu: np.ndarray, geo: FrameGeometry, scale_adu: float) -> np.ndarray:
    """The documented log stretch of stored ADU to [0, 1] (values above the ADC range exceed 1)."""
    top = math.log1p((geo.max_adu - geo.bias_adu) / scale_adu)
    x = np.log1p(np.maximum(np.asarray(adu, np.float32) - geo.bias_adu, 0.0) / scale_adu) / top
    return x.astype(np.float32)


def stretch_torch(adu, bias: float, scale: float, top: float):
    """:func:`normalise_image` in torch on ``adu``'s device: a (B, H, W) tensor of stored ADU (any
    dtype, uint16 included) -> (B, 1, H, W) float32."""
    import torch

    x = adu.to(torch.float32)
    return (torch.log1p(torch.clamp(x - bias, min=0) / scale) / top)[:, None]


def encode_detections(
    sample: Sample, geo: FrameGeometry, max_stars: int, log_flux_offset: float
) -> tuple[np.ndarray, np.ndarray]:
    """(max_stars, 3) coordinate rows and (max_stars,) mask; ``sample`` must be sorted brightest first."""
    n = min(sample.n, max_stars)
    coords = np.zeros((max_stars, len(COORD_FEATURES)), np.float32)
    mask = np.zeros(max_stars, bool)
    coords[:n, 0], coords[:n, 1] = geo.normalised(sample.x_px[:n], sample.y_px[:n])
    coords[:n, 2] = np.log10(1.0 + np.maximum(sample.flux_adu[:n], 0.0)) - log_flux_offset
    mask[:n] = True
    return coords, mask


def encode_batch(
    offsets: np.ndarray,
    det: dict,
    geo: FrameGeometry,
    max_stars: int,
    log_flux_offset: float,
    limits: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flat detection tables (brightest first per sample) -> coords (B, M, 3), mask (B, M), counts (B,).

    The same rows as :func:`encode_detections`, vectorised over samples. ``limits`` (B,) keeps
    at most that many (brightest) detections of each sample; ``counts`` are then the
    detections kept.
    """
    b = len(offsets) - 1
    counts = np.diff(offsets)
    if limits is not None:
        counts = np.minimum(counts, limits)
    fr = np.repeat(np.arange(b), np.diff(offsets))
    rank = np.arange(len(fr)) - offsets[:-1][fr]
    keep = (rank < max_stars) & (rank < counts[fr])
    fr, rank = fr[keep], rank[keep]
    coords = np.zeros((b, max_stars, len(COORD_FEATURES)), np.float32)
    mask = np.zeros((b, max_stars), bool)
    coords[fr, rank, 0], coords[fr, rank, 1] = geo.normalised(
        np.asarray(det["x_px"])[keep], np.asarray(det["y_px"])[keep]
    )
    coords[fr, rank, 2] = (
        np.log10(1.0 + np.maximum(np.asarray(det["flux_adu"], np.float64)[keep], 0.0)) - log_flux_offset
    )
    mask[fr, rank] = True
    return coords, mask, counts


def sample_from_table(
    det: dict, image: np.ndarray | None = None, background_adu: float = 0.0, noise_adu: float = 0.0
) -> Sample:
    """A :class:`Sample` (brightest first) from a detection table (dict of arrays, skygen's columns)."""
    n = len(det["x_px"])
    area = det.get("area_px")
    return Sample(
        image=None if image is None else np.asarray(image, np.float32),
        x_px=np.asarray(det["x_px"], np.float64),
        y_px=np.asarray(det["y_px"], np.float64),
        flux_adu=np.asarray(det["flux_adu"], np.float32),
        area_px=np.zeros(n, np.int32) if area is None else np.asarray(area, np.int32),
        background_adu=float(background_adu),
        noise_adu=float(noise_adu),
    ).sorted()


def downsample(full: np.ndarray, factor: int) -> np.ndarray:
    """A full-resolution frame area-averaged by the integer ``factor`` (OpenCV's INTER_AREA), in the input's
    dtype: a uint16 sensor frame is rounded to uint16 exactly as skygen stores it, a float frame stays float."""
    import cv2

    full = np.asarray(full)
    if factor == 1:
        return full
    h, w = full.shape
    return cv2.resize(full, (w // factor, h // factor), interpolation=cv2.INTER_AREA)


class Preprocessor:
    """Frame -> model inputs with one geometry and one set of data settings (``data.*`` of a config).

    ``item(sample)`` gives the dict a DataLoader collates (``image`` (1, H/f, S), ``coords``,
    ``mask``, ``n_detections``); ``tensors(...)`` a batch of one for a single frame;
    ``batch(...)`` the coordinate rows of many flat tables at once (streams); ``downsample``
    and ``detect`` the steps before, on a full-resolution frame.
    """

    def __init__(self, geo: FrameGeometry, max_stars: int, log_flux_offset: float = 3.0, norm_scale_adu: float = 8.0):
        self.geo, self.max_stars = geo, int(max_stars)
        self.log_flux_offset, self.norm_scale_adu = float(log_flux_offset), float(norm_scale_adu)

    @classmethod
    def from_configs(cls, render_config: dict, data_cfg, max_stars: int | None = None) -> "Preprocessor":
        """From a skygen render config (dict) and a fusion ``DataConfig`` (``max_stars`` may override it)."""
        return cls(
            FrameGeometry.from_render_config(render_config),
            data_cfg.max_stars if max_stars is None else max_stars,
            data_cfg.log_flux_offset,
            data_cfg.norm_scale_adu,
        )

    # ---------------------------------------------------------------- one frame
    def image(self, adu: np.ndarray) -> np.ndarray:
        """The stored frame (ADU) log-stretched to [0, 1], float32 ``[y, x]``."""
        return normalise_image(adu, self.geo, self.norm_scale_adu)

    def coords(self, sample: Sample) -> tuple[np.ndarray, np.ndarray]:
        """(max_stars, 3) rows and (max_stars,) mask of a brightest-first sample."""
        return encode_detections(sample, self.geo, self.max_stars, self.log_flux_offset)

    def item(self, sample: Sample) -> dict:
        """The tensors of one sample, as a DataLoader collates them."""
        import torch

        coords, mask = self.coords(sample)
        return {
            "image": torch.from_numpy(self.image(sample.image)[None]),
            "coords": torch.from_numpy(coords),
            "mask": torch.from_numpy(mask),
            "n_detections": torch.tensor(sample.n),
        }

    def tensors(self, x_px: np.ndarray, y_px: np.ndarray, flux_adu: np.ndarray, stored: np.ndarray | None = None):
        """(image (1, 1, H/f, S), coords (1, M, 3), mask (1, M)) of one frame's detections (brightest
        first) and stored image (``None``: a blank frame at the bias level, for geometry-only models)."""
        import torch

        g = self.geo
        blank = stored is None
        if blank:
            stored = np.full((g.image_h, g.image_px), g.bias_adu, np.float32)
        s = Sample(
            image=np.asarray(stored, np.float32),
            x_px=np.asarray(x_px, np.float64),
            y_px=np.asarray(y_px, np.float64),
            flux_adu=np.asarray(flux_adu, np.float32),
            area_px=np.zeros(len(x_px), np.int32),
            background_adu=0.0,
            noise_adu=0.0,
        )
        coords, mask = self.coords(s)
        if blank:  # the stretch of a blank frame, once (a tenth of a geometry-only prior's forward otherwise)
            if getattr(self, "_blank", None) is None:
                self._blank = self.image(s.image)
            img = self._blank.copy()
        else:
            img = self.image(s.image)
        return (
            torch.from_numpy(img)[None, None],
            torch.from_numpy(coords)[None],
            torch.from_numpy(mask)[None],
        )

    # ---------------------------------------------------------------- many samples (streams)
    def batch(self, offsets: np.ndarray, det: dict, limits: np.ndarray | None = None):
        """coords (B, M, 3), mask (B, M), counts (B,) of flat brightest-first tables (:func:`encode_batch`)."""
        return encode_batch(offsets, det, self.geo, self.max_stars, self.log_flux_offset, limits)

    def stretch(self) -> tuple[float, float, float]:
        """(bias ADU, scale ADU, log1p of the ADC range over the scale): :func:`normalise_image`'s constants."""
        g = self.geo
        return float(g.bias_adu), float(self.norm_scale_adu), math.log1p((g.max_adu - g.bias_adu) / self.norm_scale_adu)

    def images_torch(self, adu):
        """The log stretch of a (B, H/f, S) torch tensor of stored ADU, on its device: (B, 1, H/f, S)."""
        return stretch_torch(adu, *self.stretch())

    # ---------------------------------------------------------------- a full-resolution frame
    def downsample(self, full: np.ndarray) -> np.ndarray:
        """A full-resolution sensor frame area-averaged to the stored size (as skygen stores it)."""
        return downsample(full, self.geo.factor)
