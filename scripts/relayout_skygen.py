"""One-off: move skygen's flat modules into packages by role (issue 34).

Run from the repository root on a clean tree: git-moves the files, turns skygen's relative
imports absolute, rewrites every dotted name (skygen.render -> skygen.render.frame) and every
path (skygen/render.py -> skygen/render/frame.py) in code, tests, docs and configs.
"""

import re
import subprocess
from pathlib import Path

MOVES = {
    "catalog": "sky.catalog",
    "attitude": "sky.attitude",
    "vizier": "sky.vizier",
    "camera": "instrument.camera",
    "photometry": "instrument.photometry",
    "psf": "instrument.psf",
    "sensor": "instrument.sensor",
    "corruptions": "instrument.corruptions",
    "detect": "instrument.detect",
    "render": "render.frame",
    "render_torch": "render.torch_frames",
    "binned": "render.binned",
    "binned_kernels": "render.binned_kernels",
    "scenes": "render.scenes",
    "perturb": "render.perturb",
    "stream": "stream.samples",
    "emulator": "stream.emulator",
    "calibration": "stream.calibration",
    "frames": "real.frames",
    "platesolve": "real.platesolve",
    "fitcam": "real.fit_camera",
    "fitgeom": "real.fit_geometry",
    "fitpixels": "real.fit_pixels",
    "fitreport": "real.fit_report",
    "framestats": "real.frame_stats",
}
ROOT = Path(".")
CODE_DIRS = ["skygen", "fusion", "tests", "benchmarks", "scripts"]
TEXT_GLOBS = [
    "README.md",
    "docs/*.md",
    "configs/**/*.yaml",
    "pyproject.toml",
    "Makefile",
    "results/**/*.md",
    "real-frames/*.md",
    "CONTRIBUTING.md",
]


def absolutise(path: Path, text: str) -> str:
    """skygen's relative imports as absolute ones, resolved against the file's (old) package."""
    package = path.with_suffix("").parts[:-1]

    def fix(m):
        dots, mod = m.group(2), m.group(3)
        base = list(package[: len(package) - len(dots) + 1])
        return f"{m.group(1)}from {'.'.join(base + ([mod] if mod else []))} import"

    return re.sub(r"^(\s*)from (\.+)([\w.]*) import", fix, text, flags=re.M)


def remap(text: str) -> str:
    # ``from skygen import corruptions as corr`` -> ``from skygen.instrument import corruptions as corr``
    def from_pkg(m):
        name = m.group(2)
        if name not in MOVES:
            return m.group(0)
        pkg, mod = MOVES[name].rsplit(".", 1)
        return f"{m.group(1)}from skygen.{pkg} import {mod}{m.group(3) or ''}"

    names = "|".join(sorted(MOVES, key=len, reverse=True))
    text = re.sub(rf"\bskygen\.({names})\b(?!\.py)", lambda m: "skygen." + MOVES[m.group(1)], text)
    # after the dotted names, so that its output is not remapped a second time
    text = re.sub(r"^(\s*)from skygen import (\w+)( as \w+)?$", from_pkg, text, flags=re.M)
    text = re.sub(rf"\bskygen/({names})\.py\b", lambda m: "skygen/" + MOVES[m.group(1)].replace(".", "/") + ".py", text)
    return text.replace("skygen/data/", "skygen/stream/data/")


def main():
    for path in sorted(Path("skygen").rglob("*.py")):
        path.write_text(absolutise(path, path.read_text()))
    files = [p for d in CODE_DIRS for p in Path(d).rglob("*.py")]
    files += [p for g in TEXT_GLOBS for p in ROOT.glob(g)]
    for path in sorted(set(files)):
        old = path.read_text()
        new = remap(old)
        if new != old:
            path.write_text(new)
    for old, new in MOVES.items():
        dst = Path("skygen", *new.split(".")).with_suffix(".py")
        dst.parent.mkdir(exist_ok=True)
        subprocess.run(["git", "mv", f"skygen/{old}.py", str(dst)], check=True)
    subprocess.run(["git", "mv", "skygen/data", "skygen/stream/data"], check=True)


if __name__ == "__main__":
    main()
