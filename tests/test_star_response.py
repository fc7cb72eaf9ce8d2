"""benchmarks/star_response.py: star-by-star peaks and box sums, frames against renders."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.testing import benchmark_script


def _script():
    return benchmark_script("star_response")


def test_peaks_and_box_sums_are_measured_above_the_frame_median():
    """A flat frame of 10 ADU with a 3 x 3 source of 5 ADU above it: peak 5 and sum 45 at the source (the box
    catches all of it), 0 and 0 on the empty sky; positions are rounded to the nearest pixel."""
    img = np.full((40, 40), 10.0)
    img[19:22, 9:12] += 5.0
    peak, total = _script().measure(img, np.array([10.2, 30.0]), np.array([19.8, 30.0]))
    np.testing.assert_allclose(peak, [5.0, 0.0])
    np.testing.assert_allclose(total, [45.0, 0.0])


def test_a_folder_without_a_fit_report_is_refused(tmp_path):
    with pytest.raises(SystemExit):
        _script().main([str(tmp_path), "--report", str(tmp_path)])
