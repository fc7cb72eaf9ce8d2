"""The README runs as written: its quick start at small size, and every command in its (and the
docs') shell blocks parses and names inputs that a fresh clone has, `make demo` makes, or an
earlier command of the same page writes (issue 21, item 12)."""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
MADE_BY_DEMO = ("data/demo", "runs/demo")  # the Makefile's DEMO and RUN
# flags whose value is written, not read
OUTPUT_FLAGS = {"--out", "--onnx", "--overlay", "--report", "--write-config", "--engine"}
# tokens that stand for the user's own files in examples
PLACEHOLDER = re.compile(
    r"^(FRAME|CK|DIR|D|FILE|PATH|frame|sky|cube|grid|detector|star_fusion|mine|sets|my-|your)\b"
    r"|\.\.\.|^/scratch/|^\$"
)


def shell_commands(page: Path) -> list[tuple[int, str]]:
    """(line number, command) of every skygen/fusion command in the page's ```bash blocks, with
    backslash continuations joined and comments kept apart (returned as part of the text after #)."""
    out, in_block, buf, start = [], False, "", 0
    for n, line in enumerate(page.read_text().splitlines(), 1):
        if line.strip().startswith("```"):
            in_block = line.strip() == "```bash" and not in_block
            continue
        if not in_block:
            continue
        if not buf:
            start = n
        buf += line.rstrip("\\").rstrip() + " " if line.rstrip().endswith("\\") else line
        if line.rstrip().endswith("\\"):
            continue
        code, hash_, comment = buf.partition(" #")
        for part in code.split("&&"):
            if re.match(r"\s*(skygen|fusion)\s", part):
                out.append((start, (part.strip() + "  " + hash_ + comment).strip()))
        buf = ""
    return out


def split_comment(command: str) -> tuple[list[str], str]:
    code, _, comment = command.partition("  #")
    if " #" in code:
        code, _, comment = command.partition(" #")
    return shlex.split(code.replace("[", " ").replace("]", " ").replace("|", " ")), comment


def test_the_pages_have_commands_to_check():
    """The README is a short front door (issue 34): its commands and the guides' are checked together."""
    per_page = {page.name: len(shell_commands(page)) for page in PAGES}
    assert per_page["README.md"] >= 8, per_page
    assert sum(per_page.values()) >= 30, per_page


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_command_parses(page):
    from fusion.cli import build_parser as fusion_parser
    from skygen.cli import build_parser as skygen_parser

    parsers = {"skygen": skygen_parser(), "fusion": fusion_parser()}
    bad = []
    for n, command in shell_commands(page):
        argv, _ = split_comment(command)
        argv = [a[:-3] if a.endswith("...") and a != "..." else a for a in argv if a != "..."]
        try:
            parsers[argv[0]].parse_args(argv[1:])
        except SystemExit:
            bad.append(f"{page.name}:{n}: {command}")
    assert not bad, "commands the CLI rejects:\n" + "\n".join(bad)


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_input_path_exists_or_is_made_first(page):
    """An input is a repository file, something `make demo` makes, the output of an earlier
    command on the page, or the line's comment says what makes it ("after", "from", "needs")."""
    made, bad = list(MADE_BY_DEMO), []
    for n, command in shell_commands(page):
        argv, comment = split_comment(command)
        outputs, inputs, i = [], [], 1
        while i < len(argv):
            a = argv[i]
            if a in OUTPUT_FLAGS and i + 1 < len(argv):
                outputs.append(argv[i + 1])
                i += 2
                continue
            if a.startswith("--set") or a == "--range":
                i += 2
                continue
            if a.startswith("--"):
                key, _, val = a.partition("=")
                if val and key in OUTPUT_FLAGS:
                    outputs.append(val)
                elif val:
                    inputs.append(val)
                i += 1
                continue
            inputs.append(a)
            i += 1
        for arg in inputs:
            if "/" not in arg or PLACEHOLDER.search(arg) or arg.startswith("http"):
                continue
            path = arg.split("=")[-1].rstrip(",")
            if any(ch in path for ch in "*?"):
                ok = any(ROOT.glob(path))
            else:
                ok = (ROOT / path).exists()
            ok = ok and not path.startswith(("data/", "runs/"))  # ignored by git: not in a fresh clone
            ok = ok or any(path == m or path.startswith(m.rstrip("/") + "/") for m in made)
            ok = ok or re.search(r"\b(after|from|needs|made by|written by|produced by)\b", comment)
            if not ok:
                bad.append(f"{page.name}:{n}: {path!r} in `{command[:90]}`")
        made += outputs
        if argv[:2] == ["skygen", "render"] and "--out" not in argv:  # its default folder
            n_frames = argv[argv.index("--n") + 1] if "--n" in argv else "?"
            seed = argv[argv.index("--seed") + 1] if "--seed" in argv else "0"
            made.append(f"data/sky-n{n_frames}-s{seed}")
    assert not bad, "inputs nothing on the page makes (run it first, or say in a comment what makes it):\n" + "\n".join(
        bad
    )


def test_quickstart_demo_recipe_runs_at_small_size(tmp_path):
    """`make demo` as written (the Makefile's recipe), with 200 frames and a one-epoch training."""
    make = shutil.which("make")
    if make is None:
        pytest.skip("make not installed")
    bin_dir = Path(sys.executable).parent
    if not (bin_dir / "skygen").exists():
        pytest.skip("the skygen/fusion entry points are not installed beside this python")
    demo, run = tmp_path / "demo", tmp_path / "run"
    r = subprocess.run(
        [
            make,
            "-C",
            str(ROOT),
            "demo",
            f"BIN={bin_dir}",
            f"STAMP={ROOT / 'Makefile'}",
            f"DEMO={demo}",
            f"RUN={run}",
            "DEMO_N=200",
            "WORKERS=2",
            "DEMO_TRAIN=--set train.epochs=1 --set stream.samples_per_epoch=512 --set train.batch_size=64",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert (demo / "preview.png").stat().st_size > 10_000
    assert (run / "best.pt").exists() and (run / "eval-test" / "eval-test.md").exists()
    assert f"report: {run}/eval-test/eval-test.md" in r.stdout
