"""fusion: Star-Fusion training, measurement and attitude solving on skygen shards.

The package in four parts (docs/ARCHITECTURE.md)::

    fusion.model    the contract: inputs, networks, regions, metrics, checkpoints
    fusion.train    fusion train              (imports model)
    fusion.measure  evaluate, robustness, timing, export, experiment   (imports model)
    fusion.solve    predict, benchmark, solvers and priors             (imports model)

The public API, for notebooks and scripts (names load on first use, so ``import fusion``
does not import torch)::

    import fusion
    ckpt = fusion.load_checkpoint("runs/demo")                 # a typed Checkpoint, loaded once
    model = ckpt.build_model()                                 # the network with its weights, eval mode
    pred = fusion.Predictor("runs/demo/best.pt", solve=True)   # detector + learned prior + fine stage
    solver = fusion.build_solver("tetra3rs", camera)           # any registered solver by name
    cfg = fusion.load_config("configs/cpu.yaml", ["train.epochs=2", "data.path=data/demo"])
    fusion.train.train(cfg, "runs/x")                          # the subpackage fusion.train
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from skygen.lazy import lazy_attributes

__version__ = "0.1.0"

_LAZY = {
    "load_config": ".config",
    "build_config": ".config",
    "FusionConfig": ".config",
    "Checkpoint": ".model.checkpoint",
    "load_checkpoint": ".model.checkpoint",
    "create_model": ".model.networks",
    "Preprocessor": ".model.inputs",
    "Regions": ".model.regions",
    "evaluate_checkpoint": ".measure.evaluate",
    "Predictor": ".solve.predict",
    "build_solver": ".solve.registry",
    "SOLVERS": ".solve.registry",
    "load_prior": ".solve.priors",
    "run_benchmark": ".solve.benchmark",
}

if TYPE_CHECKING:
    from .config import FusionConfig, build_config, load_config
    from .measure.evaluate import evaluate_checkpoint
    from .model.checkpoint import Checkpoint, load_checkpoint
    from .model.inputs import Preprocessor
    from .model.networks import create_model
    from .model.regions import Regions
    from .solve.benchmark import run_benchmark
    from .solve.predict import Predictor
    from .solve.priors import load_prior
    from .solve.registry import SOLVERS, build_solver


__getattr__ = lazy_attributes(__name__, _LAZY)


__all__ = ["__version__", *_LAZY]
