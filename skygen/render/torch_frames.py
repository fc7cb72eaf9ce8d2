"""The torch backend: batches of frames rasterised on a torch device (CPU or CUDA).

The *scene* of frame i (attitude, light sources with their sub-exposure paths and
electrons, cosmic-ray charge, stray-light direction) comes from
:meth:`skygen.render.frame.Renderer.scene`, the code the NumPy renderer runs, so both backends
render the same stars with the same fluxes. Only the rasterisation and the pixel noise run
here, for a whole batch at once. Per pixel p of frame b, in electrons (e-) over the
exposure t, then ADU::

    lambda_bp = bg_bp + prnu_p * star_bp + t * hot_p               [e-]
    e_bp      = Poisson(lambda_bp) + cosmic_bp; 0 on dead pixels     [e-]
                -> blooming along columns above full well, then min(e, full_well)
    ADU_bp    = clip(floor((e_bp + N(0, sigma_read)) / gain) + offset_p, 0, 2^bits - 1)

``bg`` is dark + sky (times the static vignetting map) plus the frame's stray-light ramp;
``prnu``, ``offset`` (bias + integer FPN), ``hot`` and the dead-pixel mask are the same
static maps as the NumPy renderer's (:func:`skygen.instrument.sensor.sensor_maps`, drawn from
``sensor.sensor_seed``), copied to the device once. The stored image is the mean of each
``factor x factor`` block of the ADU frame (area averaging, as ``cv2.INTER_AREA`` does
for an integer factor), on the device.

What differs from the NumPy renderer, on purpose:

* Noise (Poisson, read noise) is drawn by the torch generator of the device: frames are
  equal *in distribution*, not bit for bit. ``sensor.sampler`` means what it means for
  the NumPy renderer (see :meth:`TorchRenderer.read_out`): ``fast`` draws the uniform
  background from its exact ADU distribution with one uniform per pixel and redraws every
  pixel touched by a star, a cosmic ray or a defect with the exact model; ``exact`` draws
  Poisson and Gaussian noise for every pixel.
* Gaussian stamps are computed on the device, exact pixel integrals (erf differences),
  with one radius for all stars, :func:`skygen.instrument.psf.stamp_radius_px` (NumPy cuts faint
  stars' stamps where < 0.01 e- lies outside); both normalise each stamp to its flux.
  Moffat and Airy stamps are computed on the host by :mod:`skygen.instrument.psf` (the NumPy code)
  and copied to the device: correct, but slower.
* Blooming (rare: only stars brighter than about Hp -1 saturate the default camera) is
  done on the host for the few affected columns, with :func:`skygen.instrument.sensor.bloom`.

For on-the-fly training (no dataset on disk): :func:`render_batch` renders frames by index
in one call. To keep a GPU busy, make the scenes in host processes (``Renderer(cfg).scene(i)``
in DataLoader workers; a :class:`~skygen.render.frame.Scene` pickles) and pass them to
:meth:`TorchRenderer.rasterise` on the device: the host part costs about 0.6-1.4 ms per frame
per core, the device part is batched.

Arrays are ``[batch, y, x]``; the pixel convention is :mod:`skygen.conventions`'
((0, 0) is the centre of the top-left pixel). Randomness is explicit: pass a
``torch.Generator`` on the device, or get one derived from (dataset seed, first frame
index) by :func:`default_generator` (never from the OS).
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import torch

from skygen.errors import ConfigError
from skygen.instrument.psf import peak_fraction, stamp, stamp_radius_px, streak
from skygen.instrument.sensor import background_sampler, bloom
from skygen.render.frame import Frame, Renderer, Scene
from skygen.sky.catalog import radec_to_vec

_SQRT2 = math.sqrt(2.0)
_AMBIGUOUS = -1e9  # marks a 16-bit prefix whose ADU value needs the full 32-bit search


def resolve_device(name: str) -> torch.device:
    """``cpu``, ``cuda`` or ``cuda:N`` as a torch device; ConfigError when it is not usable here."""
    try:
        dev = torch.device(name)
    except (RuntimeError, ValueError):
        raise ConfigError(f"render.device: {name!r} is not a torch device; use cpu, cuda or cuda:N") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(
                f"render.device={name}: CUDA is not available on this machine (torch {torch.__version__}, "
                "built for CUDA "
                f"{torch.version.cuda}); use render.device=cpu"
            )
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ConfigError(f"render.device={name}: only {torch.cuda.device_count()} CUDA device(s) here")
    elif dev.type != "cpu":
        raise ConfigError(f"render.device: {name!r} is not supported; use cpu, cuda or cuda:N")
    return dev


def default_generator(seed: int, first_index: int, device: torch.device) -> torch.Generator:
    """The noise generator of a batch starting at frame ``first_index`` (depends on nothing else)."""
    state = np.random.SeedSequence([seed, first_index, zlib.crc32(b"torch-noise")]).generate_state(1, np.uint64)[0]
    g = torch.Generator(device=device)
    g.manual_seed(int(state) & 0x7FFF_FFFF_FFFF_FFFF)
    return g


@dataclass(frozen=True)
class Batch:
    """Frames of one batch. ``images``: (B, h, w) stored-size ADU (float32 means of the
    full-resolution ADU blocks, or uint16 rounded like the shards); ``full``: (B, H, W)
    float32 full-resolution ADU (integer values) or None; ``scenes``: the B scenes
    (true star positions in full-resolution pixels, electrons, attitude); ``logs``: what
    the rasteriser did per frame (blooming), to merge with each scene's log."""

    images: torch.Tensor
    full: torch.Tensor | None
    scenes: list
    logs: list
    full_shape: tuple[int, int]

    @property
    def unit_vectors(self) -> np.ndarray:
        """(B, 3) boresight unit vectors in ICRS, [cos d cos a, cos d sin a, sin d] (the training labels' input)."""
        ra = np.radians([sc.ra_deg for sc in self.scenes])
        dec = np.radians([sc.dec_deg for sc in self.scenes])
        return radec_to_vec(ra, dec)

    def true_stars(self, b: int) -> dict:
        """Light sources of frame ``b`` whose centre lies on the sensor (as ``Frame.stars``)."""
        s = self.scenes[b].stars
        h, w = self.full_shape
        inside = (s["x_px"] >= -0.5) & (s["y_px"] >= -0.5) & (s["x_px"] < w - 0.5) & (s["y_px"] < h - 0.5)
        return {k: v[inside] for k, v in s.items() if k != "paths"}


class TorchRenderer:
    """Rasterises scenes of one configuration on ``device``. Construct once per process.

    Holds the NumPy :class:`~skygen.render.frame.Renderer` (catalog index, camera, photometry,
    scene code) and the static sensor maps on the device.
    """

    def __init__(self, cfg, device: str | torch.device | None = None, renderer: Renderer | None = None):
        self.cfg = cfg
        self.device = resolve_device(str(device) if device is not None else cfg.render.device)
        self.base = renderer if renderer is not None else Renderer(cfg)
        s, cam = cfg.sensor, cfg.camera
        self.shape = (cam.height_px, cam.width_px)
        self.factor = self.base.factor
        m, dev = self.base.maps, self.device
        self.prnu = torch.tensor(m.prnu.ravel(), dtype=torch.float32, device=dev)  # (copies: maps are read-only)
        self.offset = torch.tensor(m.offset_adu.ravel(), dtype=torch.float32, device=dev)
        self.hot_e = torch.tensor((m.hot_map * np.float32(s.exposure_s)).ravel(), device=dev)
        self.dead = torch.tensor(m.dead_mask.ravel(), device=dev)
        self.has_dead = bool(m.dead_mask.any())
        self.static_touched = self.hot_e > 0
        if self.has_dead:
            self.static_touched |= self.dead
        self.static_index = self.static_touched.nonzero().squeeze(1)
        self.offset_range = (int(m.offset_adu.min()), int(m.offset_adu.max()))
        self.psf_radius = self.base.psf_radius
        self.peak_fraction = peak_fraction(cfg.optics.psf, cfg.optics.psf_sigma_px, cfg.optics.moffat_beta) * (
            1.0 + 6.0 * s.prnu_frac
        )  # conservative: the brightest PRNU pixel
        self._lut: dict = {}
        h, w = self.shape
        if self.base.sky_vignetting > 0:
            yy, xx = np.mgrid[0:h, 0:w]
            bg = (self.base.dark_e + self.base.sky_e * self.base.vignetting(xx, yy, self.base.sky_vignetting)).astype(
                np.float32
            )
            self.background = torch.as_tensor(bg.ravel(), device=dev)
        else:
            self.background = torch.tensor(float(self.base.background_e), dtype=torch.float32, device=dev)
        self.read_sigma_e = float(np.hypot(s.read_noise_e, self.base.levels["read_noise"]))
        self.radius = stamp_radius_px("gaussian", cfg.optics.psf_sigma_px)

    # ------------------------------------------------------------------ scene (host)
    def scenes(self, indices) -> list[Scene]:
        """The scenes of frames ``indices`` (host, NumPy; picklable, so DataLoader workers can make them)."""
        return [self.base.scene(int(i)) for i in indices]

    # ------------------------------------------------------------------ light (device)
    def star_light(self, scenes: list[Scene]) -> torch.Tensor:
        """Expected star photo-electrons per pixel, (B, H*W) float32 on the device, before PRNU."""
        return self._star_light(scenes)[0]

    def _star_light(self, scenes: list[Scene]) -> tuple[torch.Tensor, list]:
        """:meth:`star_light` and the flat batch indices of the pixels its stamps cover."""
        h, w = self.shape
        out = torch.zeros(len(scenes), h * w, dtype=torch.float32, device=self.device)
        o = self.cfg.optics
        if o.psf != "gaussian":
            touched = []
            for b, sc in enumerate(scenes):
                for y0, x0, patch in _host_stamps(sc.stars, o.psf, o.psf_sigma_px, o.moffat_beta):
                    touched.append(
                        self._scatter(
                            out,
                            np.full(1, b),
                            np.array([y0]),
                            np.array([x0]),
                            torch.as_tensor(patch[None], dtype=torch.float32, device=self.device),
                        )
                    )
            return out, touched
        b, x, y, f = _point_sources(scenes)
        if len(b) == 0:
            return out, []
        x0 = np.floor(x + 0.5)
        y0 = np.floor(y + 0.5)
        dev = self.device
        k = torch.arange(-self.radius, self.radius + 1, dtype=torch.float32, device=dev)
        dx = torch.as_tensor((x - x0).astype(np.float32), device=dev)[:, None]
        dy = torch.as_tensor((y - y0).astype(np.float32), device=dev)[:, None]
        scale = 1.0 / (_SQRT2 * o.psf_sigma_px)
        gx = torch.erf((k + 0.5 - dx) * scale) - torch.erf((k - 0.5 - dx) * scale)
        gy = torch.erf((k + 0.5 - dy) * scale) - torch.erf((k - 0.5 - dy) * scale)
        norm = torch.as_tensor(f.astype(np.float32), device=dev) / (gx.sum(1) * gy.sum(1))
        patches = gy[:, :, None] * gx[:, None, :] * norm[:, None, None]
        flat = self._scatter(out, b, y0.astype(np.int64) - self.radius, x0.astype(np.int64) - self.radius, patches)
        return out, [flat]

    def _scatter(
        self, out: torch.Tensor, b: np.ndarray, y0: np.ndarray, x0: np.ndarray, patches: torch.Tensor
    ) -> torch.Tensor:
        """Add (N, n, m) ``patches`` whose top-left pixels are (y0, x0) into frames ``b`` of ``out``,
        clipped; returns the flat batch indices written."""
        h, w = self.shape
        dev = self.device
        n, m = patches.shape[1:]
        rows = torch.as_tensor(y0, device=dev)[:, None] + torch.arange(n, device=dev)  # (N, n)
        cols = torch.as_tensor(x0, device=dev)[:, None] + torch.arange(m, device=dev)  # (N, m)
        ok = ((rows >= 0) & (rows < h))[:, :, None] & ((cols >= 0) & (cols < w))[:, None, :]
        flat = torch.as_tensor(b, device=dev)[:, None, None] * (h * w) + rows[:, :, None] * w + cols[:, None, :]
        flat = flat[ok]
        out.view(-1).index_add_(0, flat, patches[ok])
        return flat

    def saturating_columns(self, scenes: list[Scene]) -> torch.Tensor | None:
        """Flat batch indices of whole columns under sources that may saturate (expected
        peak above half the full well, as the NumPy renderer's rule), or None."""
        if not self.cfg.sensor.blooming:
            return None
        h, w = self.shape
        limit = 0.5 * self.cfg.sensor.full_well_e / self.peak_fraction
        cols = []
        for b, sc in enumerate(scenes):
            st = sc.stars
            for s in np.flatnonzero(np.asarray(st["electrons"]) > limit):
                xs = st["x_px"][s : s + 1] if st["paths"] is None else st["paths"][0][s]
                lo = max(int(np.floor(xs.min() + 0.5)) - self.psf_radius, 0)
                hi = min(int(np.floor(xs.max() + 0.5)) + self.psf_radius + 1, w)
                c = np.arange(lo, hi)
                cols.append((b * h * w + np.arange(h)[:, None] * w + c[None, :]).ravel())
        return torch.as_tensor(np.concatenate(cols), device=self.device) if cols else None

    def cosmic_charge(self, scenes: list[Scene]) -> torch.Tensor | None:
        """Cosmic-ray charge, e- (B, H*W) on the device, or None when no frame has any."""
        return self._cosmic(scenes)[0]

    def _cosmic(self, scenes: list[Scene]) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        idx, val = [], []
        h, w = self.shape
        for b, sc in enumerate(scenes):
            for y0, x0, p in sc.cosmic_rays:
                j, i = np.nonzero(p)
                y, x = j + y0, i + x0
                ok = (y >= 0) & (y < h) & (x >= 0) & (x < w)
                idx.append(b * h * w + y[ok] * w + x[ok])
                val.append(p[j[ok], i[ok]])
        if not idx:
            return None, None
        out = torch.zeros(len(scenes), h * w, dtype=torch.float32, device=self.device)
        flat = torch.as_tensor(np.concatenate(idx), device=self.device)
        out.view(-1).index_add_(0, flat, torch.as_tensor(np.concatenate(val).astype(np.float32), device=self.device))
        return out, flat

    def background_e(self, scenes: list[Scene]) -> torch.Tensor:
        """Expected dark + sky (+ stray light) e- per pixel: (B, H*W), or (H*W,)/scalar when shared."""
        level = self.base.levels["stray_light"]
        if level == 0 or all(sc.stray_light_rad is None for sc in scenes):
            return self.background
        h, w = self.shape
        dev = self.device
        ang = torch.tensor([sc.stray_light_rad for sc in scenes], dtype=torch.float32, device=dev)[:, None, None]
        yy = torch.arange(h, dtype=torch.float32, device=dev)[None, :, None] - (h - 1) / 2
        xx = torch.arange(w, dtype=torch.float32, device=dev)[None, None, :] - (w - 1) / 2
        ramp = (xx * torch.cos(ang) + yy * torch.sin(ang)).reshape(len(scenes), -1)
        lo, hi = ramp.min(1, keepdim=True).values, ramp.max(1, keepdim=True).values
        ramp = (ramp - lo) / (hi - lo) * float(level * self.cfg.sensor.exposure_s)
        return self.background + ramp

    # ------------------------------------------------------------------ sensor (device)
    def read_out(
        self,
        star_e: torch.Tensor,
        charge_e: torch.Tensor | None,
        background_e: torch.Tensor,
        generator: torch.Generator,
        touched: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, list[int]]:
        """Electrons -> ADU for a batch. ``star_e``: (B, H*W) e- before PRNU; ``charge_e``:
        (B, H*W) cosmic-ray e- or None; ``background_e``: expected dark + sky e- per pixel
        (scalar tensor when uniform). Returns the (B, H*W) float32 ADU frames (integer
        values) and the number of bloomed columns per frame.

        ``sensor.sampler=fast`` with a uniform background: every pixel is first drawn from
        the exact distribution of ``floor((Poisson(bg) + N(0, sigma)) / gain)``
        (:meth:`_dense_background`);
        pixels that receive star light, cosmic-ray charge or a defect, and whole columns
        under a star that may saturate, are drawn again with the exact model. Otherwise
        every pixel is drawn with the exact model. ``touched`` (flat batch indices of those
        pixels, duplicates allowed) spares the full-frame search for them when the caller
        knows them (:meth:`rasterise` does).
        """
        s = self.cfg.sensor
        if s.sampler == "exact" or background_e.dim() > 0:
            adu, bloomed = self._exact(star_e, charge_e, background_e, None, generator)
            return adu, bloomed
        out = self._dense_background(float(background_e), star_e.shape, generator)
        if touched is None:
            mask = (star_e > 0) | self.static_touched
            if charge_e is not None:
                mask |= charge_e > 0
            if s.blooming:
                h, w = self.shape
                may_bloom = (star_e.view(-1, h, w) > 0.5 * s.full_well_e).any(dim=1, keepdim=True)  # (B, 1, W)
                mask |= may_bloom.expand(-1, h, -1).reshape(mask.shape)
            idx = mask.view(-1).nonzero().squeeze(1)
        else:
            hw = star_e.shape[1]
            static = (self.static_index[None, :] + hw * torch.arange(len(star_e), device=self.device)[:, None]).view(-1)
            idx = torch.unique(torch.cat([touched, static]))
        adu, bloomed = self._exact(star_e, charge_e, background_e, idx, generator)
        out.view(-1)[idx] = adu
        return out, bloomed

    def _dense_background(self, background_e: float, shape, generator: torch.Generator) -> torch.Tensor:
        """Every pixel from the uniform-background ADU distribution, offsets added (float32 ADU).

        The NumPy :class:`~skygen.instrument.sensor.BackgroundSampler`'s tables: a random 16-bit
        prefix picks the answer from a 65,536-entry table wherever the prefix alone decides
        it; elsewhere 16 more random bits are drawn and the exact 32-bit CDF thresholds
        searched, so probabilities are resolved to 2^-32.
        """
        s = self.cfg.sensor
        key = (round(background_e, 9), round(self.read_sigma_e, 9))
        if key not in self._lut:
            smp = background_sampler(key[0], key[1], float(s.gain_e_per_adu))
            lut = smp.lut16.astype(np.float32) + smp.kmin  # the ADU value (before offsets) of each prefix
            lut[smp.lut16 == 65535] = _AMBIGUOUS  # ambiguous prefix: search the thresholds
            off = self.offset_range
            may_clip = off[0] + smp.kmin < 0 or off[1] + smp.kmin + len(smp.k) - 1 > 2**s.bit_depth - 1
            self._lut = {
                key: (
                    torch.as_tensor(lut, device=self.device),
                    torch.as_tensor(smp.thresholds.astype(np.int64), device=self.device),
                    float(smp.kmin),
                    may_clip,
                )
            }
        lut, thresholds, kmin, may_clip = self._lut[key]
        top = torch.randint(0, 65536, shape, generator=generator, dtype=torch.int32, device=self.device).view(-1)
        k = lut.index_select(0, top)
        amb = (k == _AMBIGUOUS).nonzero().squeeze(1)
        if amb.numel():
            low = torch.randint(0, 65536, (amb.numel(),), generator=generator, dtype=torch.int64, device=self.device)
            u = top[amb].to(torch.int64) * 65536 + low
            k[amb] = torch.searchsorted(thresholds, u, right=True).to(torch.float32) + kmin
        out = k.view(shape).add_(self.offset)
        return out.clamp_(0, 2**s.bit_depth - 1) if may_clip else out

    def _exact(
        self,
        star_e: torch.Tensor,
        charge_e: torch.Tensor | None,
        background_e: torch.Tensor,
        idx: torch.Tensor | None,
        generator: torch.Generator,
    ) -> tuple[torch.Tensor, list[int]]:
        """The per-pixel model on every pixel (``idx`` None: (B, H*W) out) or on the flat
        indices ``idx`` of the batch (1-D out)."""
        s = self.cfg.sensor
        n_frames, hw = star_e.shape
        if idx is None:
            lam = star_e * self.prnu + self.hot_e + background_e
            e = torch.poisson(lam, generator=generator)
            if charge_e is not None:
                e += charge_e
            if self.has_dead:
                e.masked_fill_(self.dead, 0.0)
            pix = None
        else:
            pix = idx % hw
            lam = star_e.view(-1)[idx] * self.prnu[pix] + self.hot_e[pix] + background_e
            e = torch.poisson(lam, generator=generator)
            if charge_e is not None:
                e += charge_e.view(-1)[idx]
            if self.has_dead:
                e.masked_fill_(self.dead[pix], 0.0)
        bloomed = [0] * n_frames
        if s.blooming and bool((e > s.full_well_e).any()):
            if idx is None:
                bloomed = self._bloom(e)
            else:  # spill inside a cube holding only the drawn pixels (whole columns of saturating stars)
                cube = torch.zeros(n_frames * hw, dtype=e.dtype, device=e.device)
                cube[idx] = e
                bloomed = self._bloom(cube.view(n_frames, hw))
                e = cube[idx]
        e.clamp_(max=s.full_well_e)
        if self.read_sigma_e > 0:
            e += self.read_sigma_e * torch.randn(e.shape, generator=generator, device=e.device, dtype=e.dtype)
        adu = torch.floor(e / s.gain_e_per_adu) + (self.offset if pix is None else self.offset[pix])
        return adu.clamp_(0, 2**s.bit_depth - 1), bloomed

    def _bloom(self, e: torch.Tensor) -> list[int]:
        """Spill charge above full well along the columns of the few frames that have any (host)."""
        fw = self.cfg.sensor.full_well_e
        h, w = self.shape
        cube = e.view(len(e), h, w)
        over = (cube > fw).any(dim=1)  # (B, W)
        if not bool(over.any()):
            return [0] * len(e)
        bs, cs = over.nonzero(as_tuple=True)
        cols = cube[bs, :, cs].double().cpu().numpy().T.copy()  # (H, n)
        bloom(cols, fw)
        cube[bs, :, cs] = torch.as_tensor(cols.T, dtype=e.dtype, device=e.device)
        return np.bincount(bs.cpu().numpy(), minlength=len(e)).tolist()

    # ------------------------------------------------------------------ batch
    def rasterise(
        self,
        scenes: list[Scene],
        generator: torch.Generator | None = None,
        *,
        full_res: bool = False,
        dtype: torch.dtype = torch.float32,
    ) -> Batch:
        """Frames of ``scenes`` on the device; see :func:`render_batch` for the arguments."""
        if not scenes:
            raise ConfigError("rasterise: empty batch (pass at least one scene)")
        if generator is None:
            generator = default_generator(self.cfg.seed, scenes[0].index, self.device)
        h, w = self.shape
        star_e, touched = self._star_light(scenes)
        charge_e, cosmic_idx = self._cosmic(scenes)
        sat = self.saturating_columns(scenes)
        touched = [t for t in touched + [cosmic_idx, sat] if t is not None]
        touched = torch.cat(touched) if touched else torch.zeros(0, dtype=torch.int64, device=self.device)
        adu, bloomed = self.read_out(star_e, charge_e, self.background_e(scenes), generator, touched)
        full = adu.view(len(scenes), h, w)
        images = full if self.factor == 1 else torch.nn.functional.avg_pool2d(full[:, None], self.factor)[:, 0]
        if dtype == torch.uint16:
            images = torch.round(images).to(torch.int32).to(torch.uint16)
        elif dtype != torch.float32:
            raise ConfigError(f"rasterise: dtype must be torch.float32 or torch.uint16, got {dtype}")
        logs = [{"blooming": {"columns": n}} if n else {} for n in bloomed]
        return Batch(images, full if full_res else None, list(scenes), logs, self.shape)

    def render_batch(
        self,
        indices,
        generator: torch.Generator | None = None,
        *,
        full_res: bool = False,
        dtype: torch.dtype = torch.float32,
    ) -> Batch:
        """:meth:`scenes` then :meth:`rasterise`."""
        return self.rasterise(self.scenes(indices), generator, full_res=full_res, dtype=dtype)

    def frames(self, batch: Batch) -> list[Frame]:
        """Every frame of a ``full_res`` batch as a :class:`~skygen.render.frame.Frame`: the real
        detector, matching and detection-level corruptions run on the host (NumPy), with
        the stored image rounded to uint16 as in the shards."""
        if batch.full is None:
            raise ConfigError("frames: render the batch with full_res=True (the detector needs full-resolution frames)")
        full = batch.full.to(torch.int32).cpu().numpy().astype(np.uint16)
        img = batch.images
        img = (torch.round(img).to(torch.int32) if img.dtype == torch.float32 else img.to(torch.int32)).cpu().numpy()
        img = img.astype(np.uint16)
        return [self.base.finish(sc, full[b], img[b], log) for b, (sc, log) in enumerate(zip(batch.scenes, batch.logs))]


def _point_sources(scenes: list[Scene]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(frame, x, y, electrons) of every point to stamp: one per source, or one per
    sub-exposure position (each with an equal share) for a motion-blurred frame."""
    bs, xs, ys, fs = [], [], [], []
    for b, sc in enumerate(scenes):
        st = sc.stars
        f = np.asarray(st["electrons"], dtype=np.float64)
        if st["paths"] is None:
            x, y = np.asarray(st["x_px"], np.float64), np.asarray(st["y_px"], np.float64)
        else:
            px, py = st["paths"]
            n = px.shape[1]
            x, y, f = px.ravel(), py.ravel(), np.repeat(f / n, n)
        bs.append(np.full(len(x), b, np.int64))
        xs.append(x)
        ys.append(y)
        fs.append(f)
    if not bs:
        return (np.zeros(0, np.int64),) + (np.zeros(0),) * 3
    return np.concatenate(bs), np.concatenate(xs), np.concatenate(ys), np.concatenate(fs)


def _host_stamps(stars: dict, psf: str, sigma: float, beta: float) -> list:
    """Moffat/Airy stamps (and streaks) from :mod:`skygen.instrument.psf`, as the NumPy renderer makes them."""
    flux = np.asarray(stars["electrons"], dtype=np.float64)
    if stars["paths"] is None:
        return [
            stamp(float(x), float(y), float(f), psf, sigma, beta) for x, y, f in zip(stars["x_px"], stars["y_px"], flux)
        ]
    return [streak(xs, ys, float(f), psf, sigma, beta) for xs, ys, f in zip(stars["paths"][0], stars["paths"][1], flux)]


@lru_cache(maxsize=4)
def _cached(cfg, device: str) -> TorchRenderer:
    return TorchRenderer(cfg, device)


def render_batch(
    cfg,
    indices,
    device: str | None = None,
    generator: torch.Generator | None = None,
    *,
    full_res: bool = False,
    dtype: torch.dtype = torch.float32,
) -> Batch:
    """Render frames ``indices`` of config ``cfg`` on ``device`` in one batch (for on-the-fly training).

    ``device``: ``cpu``, ``cuda`` or ``cuda:N`` (default ``cfg.render.device``); a CUDA
    device that is not available raises :class:`~skygen.errors.ConfigError`.
    ``generator``: a ``torch.Generator`` on that device for the noise; None derives one
    from (``cfg.seed``, ``indices[0]``). The scene of frame i is always that of
    ``Renderer(cfg).render(i)`` (same stars, pixel positions, electrons, cosmic rays).
    Returns a :class:`Batch`: ``images`` (B, h, w) at the stored size in ADU (float32, or
    uint16 when ``dtype=torch.uint16``), ``full`` (B, H, W) ADU when ``full_res``, and the
    scenes (per-frame truth). The TorchRenderer (catalog index, device maps) is cached per
    (cfg, device), so the first call costs about a second and later ones only the frames.
    """
    dev = str(resolve_device(device if device is not None else cfg.render.device))
    return _cached(cfg, dev).render_batch(list(indices), generator, full_res=full_res, dtype=dtype)
