"""Counter-based random numbers: a draw is a pure function of (key, sample, draw id).

The streams of :mod:`skygen.stream.samples` synthesise thousands of samples per second. Creating
a ``numpy.random.Generator`` per sample costs ~15 us, more than a whole detection set is
allowed to cost, and a generator's sequence depends on the *order* of draws. Here every
random number is instead a hash of three integers:

* ``key`` — the stream (dataset seed and stream kind, :func:`stream_key`);
* ``sample`` — the sample index ``i``;
* ``draw`` — what the number is for (a fixed id per quantity; per-star quantities use the
  catalog row of the star, so a star's draws do not depend on which other stars are in
  the field).

So a sample is identical whether it is made alone, in a batch of any size, in any
DataLoader worker or DDP rank, or after a restart. The hash is SplitMix64 (Steele,
Lea & Flood 2014), whose output passes BigCrush; uniforms take its top 53 bits.
"""

from __future__ import annotations

import zlib

import numpy as np
from scipy.special import ndtri

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S11 = np.uint64(30), np.uint64(27), np.uint64(31), np.uint64(11)
_TWO_M53 = 1.0 / (1 << 53)


def splitmix64(x) -> np.ndarray:
    """The SplitMix64 finaliser of ``x + golden`` (uint64 arithmetic, wrapping)."""
    with np.errstate(over="ignore"):
        z = np.asarray(x, np.uint64) + _GOLDEN
        z = (z ^ (z >> _S30)) * _M1
        z = (z ^ (z >> _S27)) * _M2
        return z ^ (z >> _S31)


def stream_key(seed: int, name: str) -> np.uint64:
    """The key of a named stream of a dataset seed (``name`` separates kinds of samples)."""
    return np.uint64(splitmix64(splitmix64(np.uint64(seed)) ^ np.uint64(zlib.crc32(name.encode()))))


def bits(key: np.uint64, sample, draw) -> np.ndarray:
    """64 random bits per element of the broadcast ``sample`` and ``draw`` arrays."""
    s = np.asarray(sample, np.int64).astype(np.uint64)
    d = np.asarray(draw, np.int64).astype(np.uint64)
    return splitmix64(splitmix64(key ^ splitmix64(s)) ^ d)


def uniform(key: np.uint64, sample, draw) -> np.ndarray:
    """Uniform floats in [0, 1) (53-bit resolution)."""
    return (bits(key, sample, draw) >> _S11).astype(np.float64) * _TWO_M53


def normal(key: np.uint64, sample, draw) -> np.ndarray:
    """Standard normal floats (inverse CDF of a uniform in (0, 1))."""
    u = uniform(key, sample, draw)
    return ndtri(np.clip(u, 1e-300, None) + 0.5 * _TWO_M53)


def poisson(lam, u: np.ndarray, max_count: int = 200) -> np.ndarray:
    """Poisson counts from uniforms by the inverse CDF, elementwise in ``lam`` (small means)."""
    lam = np.broadcast_to(np.asarray(lam, np.float64), np.shape(u))
    out = np.zeros(np.shape(u), np.int64)
    p = np.exp(-lam)
    cdf = p.copy()
    for k in range(1, max_count + 1):
        more = u >= cdf
        if not more.any():
            break
        out += more
        p = p * lam / k
        cdf = cdf + p
    return out
