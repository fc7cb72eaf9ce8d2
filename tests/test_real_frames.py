"""The real frames shipped in real-frames/ are whole, and their table names every frame."""

from __future__ import annotations

import csv
import hashlib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDER = ROOT / "real-frames" / "tetra3-blackfly"


def test_shipped_real_frames_match_their_checksums_and_table():
    sums = dict(reversed(line.split()) for line in (FOLDER / "SHA256SUMS").read_text().splitlines())
    assert len(sums) == 8
    for name, digest in sums.items():
        assert hashlib.sha256((FOLDER / name).read_bytes()).hexdigest() == digest, name
    with open(FOLDER / "solutions.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert sorted(r["file"] for r in rows) == sorted(sums)
    for r in rows:
        assert 11.4 < float(r["fov_deg"]) < 11.44 and -90 <= float(r["dec_deg"]) <= 90
    assert "Apache License" in (FOLDER / "LICENSE-Apache-2.0.txt").read_text()
