"""The layout stays true (docs/ARCHITECTURE.md): which package may import which, and a light command line.

Every import in fusion's source is read from the syntax tree (module level and inside
functions alike, relative ones resolved), so a lazy import cannot sneak past the rule.
"""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PARTS = ("model", "train", "measure", "solve")
# part -> parts it must not import (experiment, which trains the runs it measures, may import train)
FORBIDDEN = {
    "model": {"train", "measure", "solve"},
    "train": {"measure", "solve"},
    "measure": {"train", "solve"},
    "solve": {"train", "measure"},
}
ALLOWED = {("fusion/measure/experiment.py", "train")}


def imported_modules(path: Path) -> set[str]:
    """Absolute names of every module ``path`` imports (``from . import x`` resolved against its package)."""
    package = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1])
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package.split(".")
            if node.level:
                base = base[: len(base) - node.level + 1]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module
            out.add(name)
            out.update(f"{name}.{a.name}" for a in node.names)  # ``from fusion import train``
    return out


def part_of(module: str) -> str | None:
    bits = module.split(".")
    return bits[1] if len(bits) > 1 and bits[0] == "fusion" and bits[1] in PARTS else None


@pytest.mark.parametrize("part", PARTS)
def test_import_direction(part):
    bad = []
    for path in sorted((ROOT / "fusion" / part).rglob("*.py")):
        rel = str(path.relative_to(ROOT))
        for mod in imported_modules(path):
            target = part_of(mod)
            if target in FORBIDDEN[part] and (rel, target) not in ALLOWED:
                bad.append(f"{rel} imports {mod}")
    assert not bad, "\n".join(bad)


# skygen's layers in the order data flows (docs/ARCHITECTURE.md): a module imports only its own
# package and the layers below it. The core (top-level modules: config, errors, runtime, ...) is
# layer 0; the command line sits above everything.
SKYGEN_LAYERS = {"core": 0, "sky": 1, "instrument": 2, "render": 3, "datasets": 4, "stream": 5, "real": 5, "cli": 9}


def skygen_layer(module: str) -> str | None:
    """The layer of a skygen module name (``skygen.render.frame`` -> ``render``), None outside skygen."""
    bits = module.split(".")
    if bits[0] != "skygen":
        return None
    if len(bits) == 1:
        return "core"
    if bits[1] == "__main__":
        return "cli"
    return bits[1] if bits[1] in SKYGEN_LAYERS else "core"


def skygen_violations() -> list[str]:
    bad = []
    for path in sorted((ROOT / "skygen").rglob("*.py")):
        rel = path.relative_to(ROOT)
        own = skygen_layer(".".join(rel.with_suffix("").parts))
        if rel.name == "__init__.py" and len(rel.parts) == 2:
            continue  # skygen/__init__.py: the lazy facade over every layer
        for mod in imported_modules(path):
            target = skygen_layer(mod)
            if target is None or target == own:
                continue
            if SKYGEN_LAYERS[target] >= SKYGEN_LAYERS[own]:
                bad.append(f"{rel} ({own}) imports {mod} ({target})")
    return bad


def test_skygen_layers_follow_the_data_flow():
    bad = skygen_violations()
    assert not bad, "\n".join(bad)


def test_skygen_layer_rule_catches_a_violation():
    """A sensor-level module reaching up into the renderer is found."""
    fake = ROOT / "skygen" / "instrument" / "_probe_violation.py"
    fake.write_text("def f():\n    from skygen.render.frame import Renderer\n    return Renderer\n")
    try:
        assert any("_probe_violation.py (instrument) imports skygen.render.frame" in b for b in skygen_violations())
    finally:
        fake.unlink()


def test_skygen_imports_no_fusion():
    bad = [
        f"{p.relative_to(ROOT)} imports {m}"
        for p in sorted((ROOT / "skygen").rglob("*.py"))
        for m in imported_modules(p)
        if m.split(".")[0] == "fusion"
    ]
    assert not bad, "\n".join(bad)


# fusion's shared modules sit under every part: they import no part (testing, the tests' helper, reads
# checkpoints through fusion.model); the command line and the package facade may import them all.
SHARED_MAY_IMPORT = {"config.py": set(), "errors.py": set(), "plots.py": set(), "testing.py": {"model"}}


@pytest.mark.parametrize("name", sorted(SHARED_MAY_IMPORT))
def test_fusion_shared_modules_import_no_part(name):
    path = ROOT / "fusion" / name
    bad = [
        f"fusion/{name} imports {m}"
        for m in imported_modules(path)
        if part_of(m) and part_of(m) not in SHARED_MAY_IMPORT[name]
    ]
    assert not bad, "\n".join(bad)


def test_every_shared_module_is_covered():
    """A new top-level fusion module gets a rule here (or is the CLI / the facade)."""
    top = {p.name for p in (ROOT / "fusion").glob("*.py")} - {"__init__.py", "__main__.py", "cli.py"}
    assert top == set(SHARED_MAY_IMPORT), top ^ set(SHARED_MAY_IMPORT)


def test_the_rule_catches_a_violation(tmp_path, monkeypatch):
    """The checker itself: a lazy import of fusion.train inside a solve module is found."""
    fake = ROOT / "fusion" / "solve" / "_probe_violation.py"
    fake.write_text("def f():\n    from ..train.run import train\n    return train\n")
    try:
        with pytest.raises(AssertionError, match="_probe_violation.py imports fusion.train.run"):
            test_import_direction("solve")
    finally:
        fake.unlink()


@pytest.mark.parametrize(
    "argv",
    [
        ["--help"],
        ["train", "--help"],
        ["benchmark", "--help"],
        ["predict", "--help"],
        ["timing", "--help"],
        ["export", "--help"],
        ["robustness", "--help"],
        ["experiment", "--help"],
        ["evaluate", "--help"],
    ],
)
def test_help_loads_no_torch(argv):
    code = (
        "import sys\nfrom fusion.cli import main\ntry:\n    main(%r)\nexcept SystemExit:\n    pass\n"
        "print('TORCH' if 'torch' in sys.modules else 'NO-TORCH')" % argv
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.strip().splitlines()[-1] == "NO-TORCH"


@pytest.mark.parametrize("argv", [["--help"], ["render", "--help"], ["fit-camera", "--help"], ["stream", "--help"]])
def test_skygen_help_loads_no_torch(argv):
    code = (
        "import sys\nfrom skygen.cli import main\ntry:\n    main(%r)\nexcept SystemExit:\n    pass\n"
        "print('TORCH' if 'torch' in sys.modules else 'NO-TORCH')" % argv
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.strip().splitlines()[-1] == "NO-TORCH"


def test_skygen_cli_follows_the_command_pattern():
    """Each skygen command is an _add_NAME / _run_NAME pair registered in SUBCOMMANDS (as fusion's)."""
    from skygen import cli

    for name, (texts, add, run) in cli.SUBCOMMANDS.items():
        key = name.replace("-", "_")
        assert add.__name__ == f"_add_{key}" and run.__name__ == f"_run_{key}", name
        assert "help" in texts, name


def test_public_api_is_lazy_and_complete():
    code = (
        "import sys, fusion\nassert 'torch' not in sys.modules\n"
        "names = [n for n in fusion.__all__ if n != '__version__']\n"
        "missing = [n for n in names if getattr(fusion, n, None) is None]\n"
        "print('MISSING', missing)"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.strip().endswith("MISSING []")
