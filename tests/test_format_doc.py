"""docs/FORMAT.md and the writer agree, and its h5py-only example runs."""

import re
from pathlib import Path

import h5py
import numpy as np

from skygen.instrument import corruptions as corr

DOC = Path(__file__).parents[1] / "docs" / "FORMAT.md"


def documented() -> dict:
    rows = {}
    for m in re.finditer(r"^\| `([a-z_/<>]+)` \| ([^|]+?) \| \(([^)]*)\)", DOC.read_text(), re.M):
        rows[m.group(1)] = (m.group(2).strip(), m.group(3).strip())
    return rows


def written(shard: Path) -> dict:
    out = {}
    with h5py.File(shard) as f:
        f.visititems(
            lambda name, obj: out.__setitem__(name, (obj.dtype, obj.shape)) if isinstance(obj, h5py.Dataset) else None
        )
    return out


def test_every_dataset_is_documented_and_vice_versa(small_dataset):
    doc = documented()
    expanded = {}
    for path, dtype in doc.items():
        if "<name>" in path:
            expanded.update({path.replace("<name>", n): dtype for n in corr.REGISTRY})
        elif path != "images_full":  # only with --full-res
            expanded[path] = dtype
    got = written(small_dataset / "shard-00000.h5")
    assert set(got) == set(expanded)
    n = 20  # frames in the first shard of the fixture
    sizes = {"N": n, "S": 64, "H": 256, "W": 256, "H/f": 64}
    for path, (dtype, shape) in got.items():
        want, want_shape = expanded[path]
        assert shape[0] == n, path  # one row per frame: what `datasets` needs
        assert shape == tuple(
            sizes[d.strip()] if d.strip() in sizes else int(d) for d in want_shape.split(",") if d.strip()
        ), path
        if want.startswith("str"):
            assert h5py.check_string_dtype(dtype) is not None, path
        elif want.startswith("vlen "):
            assert h5py.check_vlen_dtype(dtype) == np.dtype(want.split()[1]), path
        else:
            assert np.dtype(want) == dtype, path


def test_documented_schema_version_is_the_writers():
    from skygen.datasets.shards import SCHEMA_VERSION, SUPPORTED_MAJOR

    text = DOC.read_text()
    assert f"schema {SCHEMA_VERSION.rsplit('.', 1)[0]})" in text.splitlines()[0]
    assert f"`{SCHEMA_VERSION}`" in text and 1 in SUPPORTED_MAJOR


def test_example_reads_a_shard(small_dataset, capsys):
    code = re.search(r"```python\n(.*?)```", DOC.read_text(), re.S).group(1)
    code = code.replace("data/sky-n2000-s0/shard-00000.h5", str(small_dataset / "shard-00000.h5"))
    assert len(code.strip().splitlines()) <= 16
    exec(compile(code, "FORMAT.md example", "exec"), {})
    assert "detections" in capsys.readouterr().out
