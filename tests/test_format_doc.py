"""docs/FORMAT.md and the writer agree, and its h5py-only example runs."""

import re
from pathlib import Path

import h5py
import numpy as np

from skygen import corruptions as corr

DOC = Path(__file__).parents[1] / "docs" / "FORMAT.md"


def documented() -> dict:
    rows = {}
    for m in re.finditer(r"^\| `([a-z_/<>]+)` \| ([^|]+?) \| \(([^)]*)\)", DOC.read_text(), re.M):
        rows[m.group(1)] = m.group(2).strip()
    return rows


def written(shard: Path) -> dict:
    out = {}
    with h5py.File(shard) as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj.dtype) if isinstance(obj, h5py.Dataset) else None)
    return out


def test_every_dataset_is_documented_and_vice_versa(small_dataset):
    doc = documented()
    expanded = {}
    for path, dtype in doc.items():
        if "<name>" in path:
            expanded.update({path.replace("<name>", n): dtype for n in corr.REGISTRY})
        elif path != "images_full":       # only with --full-res
            expanded[path] = dtype
    got = written(small_dataset / "shard-00000.h5")
    assert set(got) == set(expanded)
    for path, dtype in got.items():
        want = expanded[path]
        if want.startswith("str"):
            assert h5py.check_string_dtype(dtype) is not None, path
        else:
            assert np.dtype(want) == dtype, path


def test_example_reads_a_shard(small_dataset, capsys):
    code = re.search(r"```python\n(.*?)```", DOC.read_text(), re.S).group(1)
    code = code.replace("data/sky-n2000-s0/shard-00000.h5", str(small_dataset / "shard-00000.h5"))
    assert len(code.strip().splitlines()) <= 16
    exec(compile(code, "FORMAT.md example", "exec"), {})
    assert "detections" in capsys.readouterr().out
