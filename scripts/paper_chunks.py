"""Run the paper-scale training (configs/paper.yaml) in resumable chunks of at most ~10 minutes.

    python scripts/paper_chunks.py --data data/sky-n50000-s0 --out runs/paper [--chunk-minutes 9]
        [--max-chunks N] [--launcher "torchrun --nproc_per_node 8 -m fusion.cli"] [--dry-run]
        [key=value ...]

For GPU machines whose jobs are capped in wall time (for example 10 minutes per command).
Each chunk is one ``fusion train`` process: the first starts the run with ``--config``
(and the overrides), later ones continue it with ``--resume`` (the run's own
``config.yaml``; see docs/fusion.md). A chunk is stopped with SIGINT after
``--chunk-minutes`` (SIGKILL 30 s later if it has not exited): checkpoints are written
atomically at the end of every epoch, so only the epoch in progress is lost, and the next
chunk repeats it exactly (per-epoch seeds). Hence one epoch must fit in a chunk: with 40,000
frames at batch 64 that is 625 steps; the script stops with exit code 3 if a chunk
finishes no epoch.

``--max-chunks 1`` runs one chunk and exits (0 when the run is finished, 75 when more
chunks are needed), for schedulers that start each chunk as its own job; without it the
script loops until ``summary.json`` exists. ``--dry-run`` prints the next command only.

Untested on a GPU so far (no GPU was available when it was written); the chunking logic is
tested on the CPU with the smoke preset (tests/test_paper_chunks.py).
"""

from __future__ import annotations

import argparse
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

MORE_CHUNKS = 75  # EX_TEMPFAIL: not finished yet, run again
NO_PROGRESS = 3


def epochs_done(out: Path) -> int:
    """Finished epochs of the run in ``out`` (rows of metrics.csv; 0 when none)."""
    m = out / "metrics.csv"
    if not m.exists():
        return 0
    return max(0, len(m.read_text().strip().splitlines()) - 1)


def next_command(a: argparse.Namespace) -> list[str] | None:
    """The ``fusion train`` command of the next chunk, or None when the run has finished."""
    out = Path(a.out)
    if (out / "summary.json").exists():
        return None
    cmd = shlex.split(a.launcher) + ["train", "--data", a.data, "--out", a.out]
    if (out / "last.pt").exists():
        return cmd + ["--resume"]
    return cmd + ["--config", a.config] + list(a.overrides)


def run_chunk(cmd: list[str], seconds: float) -> int:
    """Run ``cmd``; SIGINT after ``seconds``, SIGKILL 30 s later. Returns its exit code."""
    # SIGINT back to its default in the child: a shell starts background jobs with SIGINT
    # ignored, and Python would then never raise KeyboardInterrupt on our signal
    proc = subprocess.Popen(cmd, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        return proc.wait(timeout=seconds)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGINT)
        try:
            return proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            return proc.wait()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--data", required=True, help="skygen dataset folder (render it first, e.g. skygen render --n 50000)"
    )
    ap.add_argument("--out", required=True, help="run folder")
    ap.add_argument(
        "--config", default="configs/paper.yaml", help="preset for the first chunk (default configs/paper.yaml)"
    )
    ap.add_argument(
        "--chunk-minutes",
        type=float,
        default=9.0,
        help="stop a chunk after this long (default 9: with the 30 s grace it stays under 10 minutes)",
    )
    ap.add_argument("--max-chunks", type=int, help="run at most this many chunks, then exit (75: run again)")
    ap.add_argument(
        "--launcher",
        default=f"{shlex.quote(sys.executable)} -m fusion.cli",
        help='how to start fusion, e.g. "torchrun --nproc_per_node 8 -m fusion.cli" (default: this python)',
    )
    ap.add_argument("--dry-run", action="store_true", help="print the next chunk's command and exit")
    ap.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides for the first chunk")
    a = ap.parse_args(argv)
    if a.chunk_minutes <= 0:
        ap.error("--chunk-minutes must be positive")
    chunks = 0
    while True:
        cmd = next_command(a)
        if cmd is None:
            print(f"{a.out}: finished (summary.json)")
            return 0
        if a.dry_run:
            print(shlex.join(cmd))
            return 0
        if a.max_chunks is not None and chunks >= a.max_chunks:
            print(f"{a.out}: {epochs_done(Path(a.out))} epoch(s) done; run again to continue")
            return MORE_CHUNKS
        before = epochs_done(Path(a.out))
        t0 = time.monotonic()
        print(f"chunk {chunks + 1}: {shlex.join(cmd)}", flush=True)
        code = run_chunk(cmd, 60.0 * a.chunk_minutes)
        chunks += 1
        after = epochs_done(Path(a.out))
        print(f"chunk {chunks}: exit {code}, {time.monotonic() - t0:.0f} s, epochs {before} -> {after}", flush=True)
        if (Path(a.out) / "summary.json").exists():
            continue
        if code not in (0, 130, -signal.SIGINT, -signal.SIGKILL):  # 130: fusion stopped by our SIGINT
            print(f"fusion train failed (exit {code}); fix the error above and run again", file=sys.stderr)
            return code
        if after <= before:
            print(
                f"no epoch finished in {a.chunk_minutes} min: an epoch must fit in one chunk (use more GPUs, "
                "a larger --chunk-minutes where allowed, or fewer frames)",
                file=sys.stderr,
            )
            return NO_PROGRESS


if __name__ == "__main__":
    raise SystemExit(main())
