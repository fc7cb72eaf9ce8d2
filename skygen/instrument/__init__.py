"""The instrument: what happens to starlight between the sky and the detections.

In the order light meets them: :mod:`~skygen.instrument.camera` (pinhole projection,
distortion, pixel aspect), :mod:`~skygen.instrument.photometry` (magnitudes to electrons),
:mod:`~skygen.instrument.psf` (stamps and streaks), :mod:`~skygen.instrument.sensor` (noise,
dark current, hot and dead pixels, blooming, ADC), :mod:`~skygen.instrument.corruptions` (the one
registry of corruptions, shared with fusion's robustness sweeps) and
:mod:`~skygen.instrument.detect` (the real centroid detector run on every frame).
"""
