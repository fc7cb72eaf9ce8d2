"""Every GPU check this project owes, in one run that fits a short GPU lease (~9 minutes).

    python scripts/gpu_checks.py --out OUT [--train-seconds 210] [--workers 15] [--work runs/gpu-checks]
        [--device cuda] [--skip tests,timing,render,train] [--quick]
        [--config configs/X.yaml] [--set KEY=VALUE ...] [--epochs N] [--data-like PRESET] [--few-star 3,4,6]

Steps, each with its own time limit, each one's failure recorded and the next one run:

1. ``env``     -- the GPU, driver, torch and timm versions;
2. ``tests``   -- the tests marked ``gpu`` (``pytest -m gpu tests/test_render_torch.py``);
3. ``data``    -- a validation/test dataset rendered here (default camera, 2,400 frames, seed 7,
                  split 5 / 15 / 80 %: 360 validation, 1,920 test frames; the stream never reads
                  the 120 training frames, but ``fusion train`` wants the split non-empty);
4. ``timing``  -- ``fusion timing`` of the paper architecture (random weights), fp32 / bf16 /
                  fp16 at batch 1 and 64, forward and end to end from a raw 1024² frame;
5. ``render``  -- ``benchmarks/gpu_render_bench.py`` on the device (batches 1, 32, 128);
6. ``train``   -- a short from-scratch run of ``--config`` (default ``configs/paper.yaml``, the paper's
                  recipe: focal loss, AdamW, warm-up + cosine, bf16 autocast; ``--model`` picks its
                  model, default ``swinv2_tiny``, the paper's image-only baseline; any other preset
                  trains as it is, ``--set`` overrides added) on the ``frames`` stream (binned renders
                  in ``--workers`` loader processes, every sample new). Its epochs are sized so the run
                  ends in about ``--train-seconds``: for the paper preset from step 4's bf16 batch-64
                  forward time (x3 for the backward pass), for another preset from a two-epoch
                  ``probe`` run of it (or given: ``--epochs``). SIGINT at 1.35 times that as a guard
                  (best.pt is written at every epoch's end);
7. ``eval``    -- ``fusion evaluate`` of its best.pt on the test frames, whole and (``--few-star
                  3,4,6``) cut to their brightest N detections, the image untouched.

``--data-like PRESET`` renders the dataset of an experiment preset (``configs/experiments/``, e.g.
``cpu30``: the same frames, so the same test split, as that experiment's CPU runs; its content id
is in summary.json) in place of step 3's.

Everything lands in ``--out`` as at most eight files (the device tool brings back eight):
``summary.json`` (every step's status, seconds and figures), ``log.txt`` (every command's
output), ``timing.json``, ``render_bench.json``, ``metrics.csv``, ``config.yaml`` (the run's),
``eval-test.json`` and ``eval-test.md``; ``--few-star`` puts its evaluations in
``eval-brightest.json`` (N -> that evaluation) and needs ``--skip render`` to stay at eight.
Where fewer than eight are written, the run's ``best.pt`` comes back too when it is at most 16 MiB
(a small preset's checkpoint, e.g. to hand its prior to ``fusion benchmark --checkpoint`` here).

``--quick`` checks the script itself on a CPU in about two minutes (a 120-frame dataset, the
smoke preset instead of the paper's, one timing, no render benchmark); ``--device cpu`` with it.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

PY = sys.executable
ROOT = Path(__file__).resolve().parents[1]
FILES = (
    "summary.json",
    "log.txt",
    "timing.json",
    "render_bench.json",
    "metrics.csv",
    "config.yaml",
    "eval-test.json",
    "eval-test.md",
    "eval-brightest.json",
    "best.pt",
)
MAX_FILES, MAX_BYTES = 8, 16 * 2**20  # what the device tool brings back
PAPER = "configs/paper.yaml"


class Session:
    def __init__(self, out: Path):
        self.out = out
        self.log = (out / "log.txt").open("a")
        self.summary: dict = {"started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "steps": {}}

    def save(self) -> None:
        tmp = self.out / "summary.json.tmp"
        tmp.write_text(json.dumps(self.summary, indent=2, default=str))
        tmp.replace(self.out / "summary.json")

    def run(self, step: str, cmd: list[str], limit_s: float, interrupt_s: float | None = None) -> int:
        """Run ``cmd`` with its output in log.txt; kill it after ``limit_s`` (SIGINT first after
        ``interrupt_s`` when given). Returns the exit code (124: killed at the limit)."""
        self.log.write(f"\n### [{step}] {' '.join(cmd)}\n")
        self.log.flush()
        t0 = time.perf_counter()
        proc = subprocess.Popen(
            cmd,
            cwd=ROOT,
            stdout=self.log,
            stderr=subprocess.STDOUT,
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        )
        code = None
        try:
            if interrupt_s is not None:
                try:
                    code = proc.wait(timeout=interrupt_s)
                except subprocess.TimeoutExpired:
                    proc.send_signal(signal.SIGINT)
                    self.log.write(f"\n### [{step}] SIGINT after {interrupt_s:.0f} s\n")
            if code is None:
                code = proc.wait(timeout=max(1.0, limit_s - (time.perf_counter() - t0)))
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            code = 124
        dt = time.perf_counter() - t0
        rec = self.summary["steps"].setdefault(step, {"commands": []})
        rec["commands"].append({"cmd": " ".join(cmd), "rc": code, "seconds": round(dt, 1)})
        self.log.write(f"### [{step}] rc={code} in {dt:.1f} s\n")
        self.log.flush()
        self.save()
        return code


def env_info() -> dict:
    info = {"python": platform.python_version(), "machine": platform.machine(), "cpus": os.cpu_count()}
    try:
        import torch

        info["torch"] = torch.__version__
        info["cuda_available"] = torch.cuda.is_available()
        if torch.cuda.is_available():
            p = torch.cuda.get_device_properties(0)
            info.update(
                gpu=p.name,
                gpu_memory_gib=round(p.total_memory / 2**30, 1),
                multiprocessors=p.multi_processor_count,
                bf16=torch.cuda.is_bf16_supported(),
            )
    except Exception as exc:  # the record says what failed; the steps still run
        info["torch_error"] = repr(exc)
    try:
        import timm

        info["timm"] = timm.__version__
    except Exception as exc:
        info["timm_error"] = repr(exc)
    if shutil.which("nvidia-smi"):
        r = subprocess.run(
            ["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"],
            capture_output=True,
            text=True,
        )
        info["nvidia_smi"] = r.stdout.strip()
    return info


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="folder for the (at most eight) result files")
    ap.add_argument("--device", default="cuda", choices=("cuda", "cpu"))
    ap.add_argument("--train-seconds", type=float, default=210.0, help="target length of the training run")
    ap.add_argument(
        "--workers",
        type=int,
        default=max(1, (os.cpu_count() or 2) - 1),
        help="loader / render processes (default: all cores but one)",
    )
    ap.add_argument(
        "--model", default="swinv2_tiny", help="model.name of the paper-preset training run (default swinv2_tiny)"
    )
    ap.add_argument("--config", default=PAPER, help=f"training preset of step 6 (default {PAPER})")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="one more override of the training run (repeatable)",
    )
    ap.add_argument(
        "--epochs", type=int, default=None, help="epochs of the training run (default: sized to --train-seconds)"
    )
    ap.add_argument(
        "--data-like",
        default=None,
        metavar="PRESET",
        help="render an experiment preset's dataset (e.g. cpu30) instead of the default 2,400 frames",
    )
    ap.add_argument(
        "--few-star", default="", help="comma list of N: also evaluate on test frames cut to their brightest N"
    )
    ap.add_argument("--skip", default="", help="comma-separated steps to skip: tests,timing,render,train")
    ap.add_argument(
        "--work",
        default=str(ROOT / "runs" / "gpu-checks"),
        help="folder for the dataset, the run and the timing files (default runs/gpu-checks)",
    )
    ap.add_argument("--quick", action="store_true", help="check the script itself on a CPU (tiny sizes)")
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    skip = {s for s in a.skip.split(",") if s}
    s = Session(out)
    s.summary["env"] = env_info()
    s.summary["args"] = vars(a)
    s.save()
    fusion, skygen = [PY, "-m", "fusion.cli"], [PY, "-m", "skygen.cli"]
    work = Path(a.work)
    data = work / "eval-data"

    if "tests" not in skip:
        s.run(
            "tests",
            [PY, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", "gpu", "tests/test_render_torch.py"],
            120,
        )

    if a.data_like:
        sys.path.insert(0, str(ROOT))
        from fusion.measure.experiment import load_preset

        preset = load_preset(a.data_like)
        render = ["--n", str(preset.dataset_n)] + [x for o in preset.dataset_overrides for x in ("--set", o)]
    else:
        render = ["--n", "120" if a.quick else "2400", "--seed", "7", "--set", "output.split_fractions=[0.05,0.15,0.8]"]
    s.run(
        "data", skygen + ["render", *render, "--workers", str(a.workers), "--out", str(data), "--force", "--quiet"], 240
    )
    if (data / "manifest.json").exists():
        man = json.loads((data / "manifest.json").read_text())
        s.summary["data"] = {k: man.get(k) for k in ("dataset_id", "content_id", "n_frames")}
        s.save()

    timing: dict = {}
    if "timing" not in skip:
        combos = [("fp32", 1)] if a.quick else [(p, b) for p in ("fp32", "bf16", "fp16") for b in (1, 64)]
        for prec, b in combos:
            f = work / f"timing-{prec}-b{b}.json"
            f.parent.mkdir(parents=True, exist_ok=True)
            rc = s.run(
                "timing",
                fusion
                + [
                    "timing",
                    "--config",
                    "configs/paper.yaml",
                    "--device",
                    a.device,
                    "--precision",
                    prec,
                    "--batch",
                    str(b),
                    "--iters",
                    "10" if a.quick else "50",
                    "--warmup",
                    "2" if a.quick else "10",
                    "--mode",
                    "both",
                    "--out",
                    str(f),
                ],
                120,
            )
            if rc == 0 and f.exists():
                timing[f"{prec}-b{b}"] = json.loads(f.read_text())
        (out / "timing.json").write_text(json.dumps(timing, indent=2))

    if "render" not in skip and not a.quick:
        s.run(
            "render",
            [
                PY,
                "benchmarks/gpu_render_bench.py",
                "--frames",
                "512",
                "--batch-sizes",
                "1,32,128",
                "--devices",
                a.device,
                "--out",
                str(out / "render_bench.json"),
            ],
            150,
        )

    if "train" not in skip:
        train_step(s, a, fusion, work, data, timing)
    s.summary["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    s.save()
    extra = sorted(p.name for p in out.iterdir() if p.name not in FILES)
    if extra:
        print(f"gpu_checks: unexpected files in {out}: {extra}", file=sys.stderr)
    print(json.dumps({k: [c["rc"] for c in v["commands"]] for k, v in s.summary["steps"].items()}))
    return 0


def train_step(s: Session, a, fusion: list[str], work: Path, data: Path, timing: dict) -> None:
    """Steps 6 and 7: size the run to ``--train-seconds``, train it on the frames stream, evaluate it."""
    paper = a.config == PAPER and not a.quick
    cfg = "configs/smoke.yaml" if a.quick else a.config
    common = [
        "stream.render_backend=numpy",
        f"train.workers={a.workers}",
        f"train.device={a.device}",
        "train.patience=null",
        "train.progress=false",
    ]
    if paper:
        per_epoch = 16384
        common += [f"model.name={a.model}", f"stream.samples_per_epoch={per_epoch}", "optim.warmup_epochs=1"]
    else:
        sys.path.insert(0, str(ROOT))
        from fusion.config import load_config

        per_epoch = 128 if a.quick else int(load_config(cfg).stream.samples_per_epoch)
        common += [f"stream.samples_per_epoch={per_epoch}"] + (["train.batch_size=32"] if a.quick else [])
    common += list(a.set)
    train = fusion + ["train", "--data", str(data), "--config", cfg, "--stream", "frames", "--force"]
    plan: dict = {"config": cfg, "samples_per_epoch": per_epoch}
    rate = None
    if a.epochs is None and paper:
        # samples/s: the bf16 (else fp32) batch-64 forward time x 3 for forward + backward,
        # no faster than the loader processes can render (~800 binned frames/s each, measured on CPUs)
        for key in ("bf16-b64", "fp32-b64", "fp32-b1"):
            ms = (timing.get(key, {}).get("forward") or {}).get("median_ms")
            if ms:
                plan["forward_ms_used"] = [ms, int(key.rsplit("-b", 1)[1])]
                rate = int(key.rsplit("-b", 1)[1]) / (3 * ms / 1e3)
                break
        rate = min(rate or 200.0, 800.0 * a.workers)
    elif a.epochs is None:
        # a two-epoch probe of the same preset; its second epoch (loaders warm) gives the rate
        probe = work / "probe"
        n = 64 if a.quick else max(per_epoch // 4, 8192)
        s.run(
            "probe", train + ["--out", str(probe), "train.epochs=2"] + common + [f"stream.samples_per_epoch={n}"], 240
        )
        rows = (probe / "metrics.csv").read_text().splitlines() if (probe / "metrics.csv").exists() else []
        if len(rows) >= 3:
            head, last = rows[0].split(","), rows[-1].split(",")
            rate = n / float(last[head.index("epoch_time_s")])
        rate = rate or 200.0
    if (
        a.epochs is None
    ):  # margins: the forward-time guess was 2-3x the H200 run's rate (the guard stops it), a probe is measured
        epochs = max(2, int((0.7 if paper else 0.85) * rate * a.train_seconds / per_epoch))
        plan["estimated_samples_per_s"] = round(rate, 1)
    else:
        epochs = a.epochs
    plan["epochs"] = epochs
    s.summary["train_plan"] = plan
    s.save()
    run_dir = work / "train"
    rc = s.run(
        "train",
        train + ["--out", str(run_dir), f"train.epochs={epochs}"] + common,
        limit_s=1.35 * a.train_seconds + 45,
        interrupt_s=1.35 * a.train_seconds,
    )
    for name in ("metrics.csv", "config.yaml"):
        if (run_dir / name).exists():
            shutil.copy(run_dir / name, s.out / name)
    if (run_dir / "summary.json").exists():
        s.summary["train_summary"] = {
            k: v
            for k, v in json.loads((run_dir / "summary.json").read_text()).items()
            if k not in ("dataset", "config")
        }
    if not (run_dir / "best.pt").exists():
        if rc != 0:
            s.log.write("### [train] no best.pt: the run finished no epoch\n")
        return
    ev = work / "eval"
    evaluate = fusion + [
        "evaluate",
        "--checkpoint",
        str(run_dir / "best.pt"),
        "--data",
        str(data),
        "--split",
        "test",
        "--out",
        str(ev),
        "--workers",
        str(min(8, a.workers)),
    ]
    s.run("eval", evaluate, 180)
    for name in ("eval-test.json", "eval-test.md"):
        if (ev / name).exists():
            shutil.copy(ev / name, s.out / name)
    few: dict = {}
    for n in [int(x) for x in a.few_star.split(",") if x]:
        s.run("eval", evaluate + ["--brightest", str(n)], 180)
        f = ev / f"eval-test-brightest{n}.json"
        if f.exists():
            few[n] = json.loads(f.read_text())
    if few:
        (s.out / "eval-brightest.json").write_text(json.dumps(few, indent=2))
    best = run_dir / "best.pt"
    if len(list(s.out.iterdir())) < MAX_FILES and best.stat().st_size <= MAX_BYTES:
        shutil.copy(best, s.out / "best.pt")
    tops = {"whole": (json.loads((ev / "eval-test.json").read_text()) if (ev / "eval-test.json").exists() else {})}
    tops.update({f"brightest{n}": e for n, e in few.items()})
    s.summary["top1"] = {k: e.get("top1") for k, e in tops.items()}
    s.save()


if __name__ == "__main__":
    sys.exit(main())
