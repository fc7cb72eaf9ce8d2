"""The solver registry: every attitude solver by name, and one :func:`build_solver` for predict and benchmark.

A solver is anything with ``name`` and ``solve(detections, camera, image=None, **kw)``
(:class:`fusion.solve.base.Solver`). Registered here (:data:`SOLVERS`):

=========================  ======================================================================
``tetra3rs``               tetra3rs lost-in-space, the classical baseline (:mod:`fusion.solve.tetra`)
``whole-sky``              the fine stage over the whole sky, no prior (:mod:`fusion.solve.fine`)
``tetra3rs>whole-sky``     tetra3rs, and the whole-sky fine stage where it refuses
``learned+fine``           the fine stage searching a learned prior's most probable regions
``learned+fine>whole-sky`` learned + fine, and the rest of the sky where the prior's regions refuse
                           (one search: its hypothesis count H, and so its false-match budget, spans
                           both; ``fusion predict --solve`` with a checkpoint); at
                           ``fine.SKY_FIRST_FROM`` (4) detections the whole sky first, the
                           prior's regions (a search of their own) where it refuses; from
                           ``fine.WHOLE_SKY_FROM`` (5) tetra3rs, then the whole sky at once, no prior
``tetra3rs>learned+fine``  tetra3rs, and learned + fine where it refuses
``tetra3rs>learned+fine>whole-sky``  tetra3rs, then learned + fine > whole-sky (``fusion predict --lis-first``)
``oracle-prior``           benchmark only: the fine stage with the true region ranked first
``sim85-prior``            benchmark only: the true region first in 85 % of frames, second otherwise
=========================  ======================================================================

Each entry names the prior it needs (``None``, ``"learned"`` — a checkpoint's model or any
:class:`fusion.solve.priors.RegionPrior` — or ``"oracle"``, the benchmark's truth).
**Adding a solver**: write a class with ``name`` and ``solve`` and register a builder
``@register_solver("my-solver", prior=None, doc="...")`` taking a :class:`SolverContext`;
``fusion predict --solve`` and ``fusion benchmark --solvers my-solver`` then use it
(docs/ARCHITECTURE.md shows a worked example). This module imports no torch, so the command
line can list the names cheaply; builders import what they need.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable

import numpy as np

if TYPE_CHECKING:  # names for the annotations only: importing them here would load torch
    from skygen.instrument.camera import Camera

    from .priors import RegionPrior
    from .tetra import Tetra3Solver


@dataclass
class SolverContext:
    """What a builder may use: the camera, a shared tetra3rs solver, the prior and the search settings."""

    camera: Camera
    tetra: Tetra3Solver  # its database loaded once, shared by every solver built
    prior: RegionPrior | None = None  # at its search level (learned solvers)
    search_centroids: np.ndarray | None = None  # regions the oracle priors rank (benchmark)
    top_k: int = 20  # regions the fine stage searches, most probable first
    chain_top_k: int | None = None  # regions learned+fine>whole-sky searches before the sky (None: top_k)
    focal_tol: float = 0.02  # relative focal-length uncertainty the fine stage fits within
    max_hypotheses: int | None = None  # the fine stage's work budget per solve (None: its default, MAX_HYPOTHESES)
    built: dict = field(default_factory=dict)  # solvers already built for this context, by name


@dataclass(frozen=True)
class SolverSpec:
    name: str
    prior: str | None  # None, "learned" or "oracle"
    doc: str
    build: Callable[[SolverContext], object]


SOLVERS: dict[str, SolverSpec] = {}


def register_solver(name: str, *, prior: str | None = None, doc: str = ""):
    """Decorator registering ``builder(ctx: SolverContext) -> solver`` under ``name``."""
    if prior not in (None, "learned", "oracle"):
        raise ValueError(f"prior={prior!r}: None, 'learned' or 'oracle'")

    def deco(builder):
        SOLVERS[name] = SolverSpec(name, prior, doc, builder)
        return builder

    return deco


def get(ctx: SolverContext, name: str):
    """The solver ``name`` of this context, built once (solvers that chain others share them)."""
    if name not in ctx.built:
        ctx.built[name] = SOLVERS[name].build(ctx)
    return ctx.built[name]


def _fine_stage(ctx: SolverContext, prior, name: str, **kw):
    """A fine stage (:class:`fusion.solve.fine.CoarseToFineSolver`) with the context's search settings."""
    from .fine import CoarseToFineSolver

    kw.setdefault("top_k", ctx.top_k)
    return CoarseToFineSolver(
        ctx.tetra,
        prior,
        name=name,
        focal_tol=ctx.focal_tol,
        max_hypotheses=ctx.max_hypotheses,
        **kw,
    )


@register_solver("tetra3rs", doc="tetra3rs lost-in-space (the classical baseline)")
def _tetra3rs(ctx: SolverContext):
    return ctx.tetra


@register_solver("whole-sky", doc="the fine stage over the whole sky, no prior")
def _whole_sky(ctx: SolverContext):
    return _fine_stage(ctx, None, "whole-sky")


@register_solver("tetra3rs>whole-sky", doc="tetra3rs, and the whole-sky fine stage where it refuses")
def _tetra3rs_whole_sky(ctx: SolverContext):
    from .base import FallbackSolver

    return FallbackSolver(get(ctx, "tetra3rs"), get(ctx, "whole-sky"))


@register_solver("learned+fine", prior="learned", doc="the fine stage searching the learned prior's regions")
def _learned_fine(ctx: SolverContext):
    return _fine_stage(ctx, ctx.prior, "learned+fine")


@register_solver(
    "learned+fine>whole-sky",
    prior="learned",
    doc="learned + fine, then the rest of the sky where the prior's regions refuse (one budget); at 4 "
    "detections the whole sky first, the prior's regions where it refuses; from 5 tetra3rs, then the whole sky",
)
def _learned_fine_whole_sky(ctx: SolverContext):
    from .fine import FEW_TOP_K_FACTOR, SKY_FIRST_FROM, WHOLE_SKY_FROM

    # fewer regions before the sky (ctx.chain_top_k), but three detections search as many as learned+fine does
    # (top_k x FEW_TOP_K_FACTOR): there the sky search rarely answers, and one set of renders lost a field with fewer
    k = ctx.chain_top_k or ctx.top_k
    return _fine_stage(
        ctx,
        ctx.prior,
        "learned+fine>whole-sky",
        then_whole_sky=True,
        whole_sky_from=WHOLE_SKY_FROM,
        sky_first_from=SKY_FIRST_FROM,
        top_k=k,
        few_top_k_factor=max(1, round(FEW_TOP_K_FACTOR * ctx.top_k / k)),
    )


@register_solver(
    "tetra3rs>learned+fine", prior="learned", doc="tetra3rs lost-in-space, and learned + fine where it refuses"
)
def _tetra3rs_learned_fine(ctx: SolverContext):
    from .base import FallbackSolver

    return FallbackSolver(get(ctx, "tetra3rs"), get(ctx, "learned+fine"))


@register_solver(
    "tetra3rs>learned+fine>whole-sky",
    prior="learned",
    doc="tetra3rs lost-in-space, then learned + fine > whole-sky where it refuses",
)
def _tetra3rs_learned_fine_whole_sky(ctx: SolverContext):
    from .base import FallbackSolver

    return FallbackSolver(get(ctx, "tetra3rs"), get(ctx, "learned+fine>whole-sky"))


def _oracle_centroids(ctx: SolverContext) -> np.ndarray:
    if ctx.search_centroids is None:
        raise ValueError("an oracle prior ranks regions: give SolverContext.search_centroids (the benchmark does)")
    return ctx.search_centroids


@register_solver("oracle-prior", prior="oracle", doc="benchmark only: the true region ranked first")
def _oracle(ctx: SolverContext):
    from .priors import OraclePrior

    return _fine_stage(ctx, OraclePrior(_oracle_centroids(ctx), 1.0), "oracle-prior")


@register_solver("sim85-prior", prior="oracle", doc="benchmark only: the true region first in 85 % of frames")
def _sim85(ctx: SolverContext):
    from .priors import OraclePrior

    return _fine_stage(ctx, OraclePrior(_oracle_centroids(ctx), 0.85, seed=1), "sim85-prior")


def default_search_k(level: str, chain: bool = False) -> int:
    """Regions the fine stage searches by default: 20 fine regions (~2 % of the sky at fine_k = 1000) or 3 of K.

    ``chain``: for ``learned+fine>whole-sky``, which searches the rest of the sky where its regions refuse, 5 fine
    regions from four detections (three keep 80): the same success as 20 in every cell measured at N = 4
    (data/bench500, 13 clean and corrupted cells; data/track300-s23; 0 wrong), p99 1.4-4.4 times shorter
    (results/benchmark/chain-top-k); the prior's regions alone (``learned+fine``) lose 2-4 points at N = 4-6 with 5,
    so they keep 20."""
    if level == "fine":
        return 5 if chain else 20
    return 3


def check_search_options(
    focal_tol: float, search_k: int | None, k_flag: str = "--search-k", max_hypotheses: int | None = None
) -> None:
    from ..errors import ConfigError

    if not 0.0 <= focal_tol < 0.2:
        raise ConfigError(f"--focal-tol {focal_tol}: a relative focal-length uncertainty in [0, 0.2), e.g. 0.02")
    if search_k is not None and search_k < 1:
        raise ConfigError(f"{k_flag} {search_k}: search at least 1 region")
    if max_hypotheses is not None and max_hypotheses < 1:
        raise ConfigError(f"--max-hypotheses {max_hypotheses}: a positive number of hypotheses per solve, e.g. 200000")


def make_context(
    camera,
    *,
    prior=None,
    search: str = "fine",
    search_k: int | None = None,
    focal_tol: float = 0.02,
    search_centroids: np.ndarray | None = None,
    tetra=None,
    log=None,
    k_flag: str = "--search-k",
    max_hypotheses: int | None = None,
) -> SolverContext:
    """A :class:`SolverContext` for ``camera``: the prior at its ``search`` level (its fine regions when it has
    them), the regions searched (``search_k``, default :func:`default_search_k`), the fine stage's work budget
    (``max_hypotheses``, default its own) and a tetra3rs solver."""
    check_search_options(focal_tol, search_k, k_flag, max_hypotheses)
    if prior is not None:
        prior = prior.at_level(search)
    level = getattr(prior, "level", "coarse")
    if tetra is None:
        from .tetra import Tetra3Solver

        tetra = Tetra3Solver(camera, log=log)
    if search_centroids is None and prior is not None:
        search_centroids = prior.centroids
    return SolverContext(
        camera,
        tetra,
        prior,
        search_centroids,
        search_k or default_search_k(level),
        search_k or default_search_k(level, chain=True),
        focal_tol,
        max_hypotheses,
    )


def build_solver(
    name: str,
    camera,
    *,
    prior=None,
    search: str = "fine",
    search_k: int | None = None,
    focal_tol: float = 0.02,
    log=None,
    context: SolverContext | None = None,
    max_hypotheses: int | None = None,
):
    """The registered solver ``name`` for ``camera`` (a :class:`skygen.instrument.camera.Camera`).

    ``prior``: a :class:`fusion.solve.priors.RegionPrior` (e.g. ``load_prior(checkpoint)``), needed by
    the learned solvers; ``search``/``search_k``/``focal_tol``: the fine stage's settings, as
    ``fusion predict --solve`` takes them. Pass ``context`` to share one tetra3rs database
    between several solvers.

    Parameters
    ----------
    name : str
        One of :data:`SOLVERS` (``fusion benchmark --help`` lists them with a line each).
    camera : skygen.instrument.camera.Camera
        The camera whose detections the solver will be given (pixels of its full-resolution sensor).
    prior : fusion.solve.priors.RegionPrior, optional
        Required by the solvers registered with ``prior="learned"``.
    search : {"fine", "coarse"}
        Which regions of the prior the fine stage searches; ``search_k`` how many (default per level).
    focal_tol : float
        Relative focal-length uncertainty the fine stage fits within (0.02 = 2 %).
    log : callable, optional
        Receives one line when a database or index is built.
    context : SolverContext, optional
        Shares one tetra3rs database and already-built solvers between calls.
    max_hypotheses : int, optional
        The fine stage's work budget per solve (default: :data:`fusion.solve.fine.MAX_HYPOTHESES` on every
        camera); ignored when ``context`` is given (the context's own).

    Returns
    -------
    Solver
        An object with ``solve(detections, camera, image=None, **kw) -> Solution | Refusal``.

    Raises
    ------
    skygen.errors.ConfigError
        An unknown name, or a learned solver without a prior.
    """
    from ..errors import ConfigError

    if name not in SOLVERS:
        raise ConfigError(f"--solver {name!r}: unknown; choose from {', '.join(SOLVERS)}")
    spec = SOLVERS[name]
    ctx = context or make_context(
        camera,
        prior=prior,
        search=search,
        search_k=search_k,
        focal_tol=focal_tol,
        log=log,
        max_hypotheses=max_hypotheses,
    )
    if spec.prior == "learned" and ctx.prior is None:
        raise ConfigError(f"solver {name} needs a learned prior: pass --checkpoint CK (a trained model)")
    if spec.prior == "oracle" and ctx.search_centroids is None:
        raise ConfigError(
            f"solver {name} is a benchmark reference: it needs the true boresight and the regions "
            "to rank (fusion benchmark)"
        )
    return get(ctx, name)
