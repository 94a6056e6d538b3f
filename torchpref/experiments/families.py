r"""The simulated users of the benchmark suite (:mod:`torchpref.experiments.suite`).

A :class:`Family` is a kind of person: a random utility on the unit cube (a shape, drawn anew
for every trial) and an answering style (how noisy their choices are, how precise their ratings,
whether they tick a 1-5 box). The families span ``d = 1`` to ``6`` and shapes from the paper's
waves to narrow peaks, flat plateaus and BoTorch test functions rescaled into utilities
(:class:`~torchpref.simulation.utility_functions.RescaledUtility`: median item 0, best item about 2).

Each family also says how a trial's items are offered (fresh uniform candidates per query, or a
finite pool as the lake's planned paths), where the metrics are taken (:func:`setup`: a grid in
1-D, the pool, or fixed random points), and the hyperparameters of the *fixed* condition (a
lengthscale of the order of the shape's features, the user's own noise); the *learned*
condition learns the kernel's from the answers (:mod:`~torchpref.experiments.suite`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from botorch.test_functions import Branin, Hartmann, Levy
from torch import Tensor

from torchpref.likelihoods.pairwise_beta import rating_link
from torchpref.simulation.raters import EffortModel, RaterProfile, RealisticUser, precision_for_noise
from torchpref.simulation.users import LikertUser, SimulatedUser, User
from torchpref.simulation.utility_functions import (
    GaussianBumps,
    Plateau,
    RescaledUtility,
    WaveFunction,
    evaluation_grid,
)

RATING_SCALE = 0.8  # sigma_B of every family's raters (eq. 7): utilities 0..2 span ratings 0.5..0.96
EVAL_POINTS = 256  # metric points of a family of d >= 2 without a pool
REFERENCE_POINTS = 1024  # points that set a rescaled utility's median and maximum
NUM_CANDIDATES = 100  # fresh candidates per query


def _uniform(g: torch.Generator, n: int, d: int) -> Tensor:
    return torch.rand(n, d, generator=g, dtype=torch.float64)


def _flips(g: torch.Generator, d: int) -> Tensor:
    return torch.rand(d, generator=g) < 0.5


def _rescaled(fn: Callable[[Tensor], Tensor], bounds: Tensor, d: int, g: torch.Generator) -> RescaledUtility:
    return RescaledUtility(fn, bounds, _uniform(g, REFERENCE_POINTS, d), _flips(g, d))


def _unit(d: int) -> Tensor:
    return torch.tensor([[0.0] * d, [1.0] * d], dtype=torch.float64)


def _botorch(problem, g: torch.Generator) -> RescaledUtility:
    """A BoTorch test function to minimise, negated (a utility to maximise) and rescaled."""
    return _rescaled(lambda X: -problem.evaluate_true(X), problem.bounds.to(torch.float64), problem.dim, g)


def _damped_wave(g: torch.Generator) -> RescaledUtility:
    wave = WaveFunction.random(generator=g, n_components=1)
    return RescaledUtility(lambda X: wave(X, noise=False), _unit(1), evaluation_grid(REFERENCE_POINTS), None)


def _narrow_peak(g: torch.Generator) -> RescaledUtility:
    c = 0.1 + 0.8 * _uniform(g, 3, 2)
    return _rescaled(GaussianBumps(c, [1.0, 0.5, 0.5], [0.05, 0.2, 0.2]), _unit(2), 2, g)


def _plateau(g: torch.Generator) -> RescaledUtility:
    c = 0.3 + 0.4 * _uniform(g, 1, 2)[0]
    v = torch.randn(2, generator=g, dtype=torch.float64)
    return _rescaled(Plateau(c, radius=0.25, edge=0.03, tilt=0.1 * v / v.norm()), _unit(2), 2, g)


def _two_bumps(g: torch.Generator) -> RescaledUtility:
    c = 0.2 + 0.6 * _uniform(g, 2, 4)
    return _rescaled(GaussianBumps(c, [1.0, 0.7], [0.25, 0.25]), _unit(4), 4, g)


@dataclass(frozen=True)
class Family:
    r"""A kind of simulated user.

    Attributes:
        name: the family's name.
        dim: ``d``.
        draw: ``generator -> utility`` (``n x d`` in the unit cube -> ``n``), one per trial.
        comparison_noise: the user's ``sigma_R`` (eq. 3).
        rating_precision: the user's ``nu`` (eqs. 5-6); ratings have ``sigma_B`` :data:`RATING_SCALE`.
        likert: ratings quantised to levels 1-5 (:class:`~torchpref.simulation.users.LikertUser`).
        lengthscale: the fixed condition's kernel lengthscale.
        pool: a finite pool of this many random items (also the metric points), or ``None``:
            :data:`NUM_CANDIDATES` fresh uniform candidates per query.
        model: the fixed condition's model settings, if not the user's own noise (see
            :func:`model_settings`).
        description: what the family is.
        rater: for a realistic family, ``(generator, spread) -> RaterProfile``: the person of a
            trial, drawn for utilities of that spread (standard deviation over the metric
            points); answers come from a :class:`~torchpref.simulation.raters.RealisticUser`.
            ``None``: the paper's user (:class:`~torchpref.simulation.users.SimulatedUser`).
    """

    name: str
    dim: int
    draw: Callable[[torch.Generator], Callable[[Tensor], Tensor]]
    comparison_noise: float
    rating_precision: float
    lengthscale: float
    likert: bool = False
    pool: int | None = None
    model: dict[str, float] | None = field(default=None)
    description: str = ""
    rater: Callable[[torch.Generator, float], RaterProfile] | None = None

    @property
    def realistic(self) -> bool:
        """Whether the family's people are realistic raters (:attr:`rater`)."""
        return self.rater is not None


#: the paper's model for the waves (docs/wave.md), with the authors' user
_WAVE_MODEL = {
    "lengthscale": 0.02,
    "outputscale": 0.36,
    "comparison_noise": 0.2,
    "rating_scale": 0.8,
    "rating_precision": 60.0,
}

FAMILIES: dict[str, Family] = {
    f.name: f
    for f in [
        Family(
            "waves",
            1,
            lambda g: (lambda w: lambda X: w(X, noise=False))(WaveFunction.random(generator=g)),
            0.05,
            80.0,
            0.02,
            model=_WAVE_MODEL,
            description="the paper's three-wave functions (eq. 13), its user and model",
        ),
        Family(
            "damped-wave",
            1,
            _damped_wave,
            0.3,
            20.0,
            0.03,
            description="one damped wave; noisy choices, imprecise ratings",
        ),
        Family(
            "narrow-peak",
            2,
            _narrow_peak,
            0.1,
            40.0,
            0.05,
            likert=True,
            description="a narrow dominant bump and two broad low ones; Likert ratings",
        ),
        Family(
            "plateau",
            2,
            _plateau,
            0.1,
            10.0,
            0.1,
            description="a broad flat-topped bump, slightly tilted; very imprecise ratings",
        ),
        Family(
            "branin",
            2,
            lambda g: _botorch(Branin(), g),
            0.02,
            100.0,
            0.25,
            description="BoTorch's Branin; near-exact choices and precise ratings",
        ),
        Family(
            "hartmann3",
            3,
            lambda g: _botorch(Hartmann(dim=3), g),
            0.1,
            40.0,
            0.2,
            likert=True,
            pool=300,
            description="BoTorch's Hartmann-3 over a pool of 300 items; Likert ratings",
        ),
        Family("two-bumps", 4, _two_bumps, 0.1, 40.0, 0.25, description="two Gaussian bumps in 4-D"),
        Family(
            "levy5",
            5,
            lambda g: _botorch(Levy(dim=5), g),
            0.2,
            40.0,
            0.15,
            likert=True,
            description="BoTorch's Levy (rugged) in 5-D; noisy choices, Likert ratings",
        ),
        Family(
            "hartmann6", 6, lambda g: _botorch(Hartmann(dim=6), g), 0.05, 60.0, 0.3, description="BoTorch's Hartmann-6"
        ),
    ]
}


def _typical(**kw) -> Callable[[torch.Generator, float], RaterProfile]:
    """People drawn by :meth:`RaterProfile.typical` with ``kw`` (values or ``generator -> value``) replacing draws."""

    def draw(g: torch.Generator, spread: float) -> RaterProfile:
        fixed = {k: (v(g, spread) if callable(v) else v) for k, v in kw.items()}
        return RaterProfile.typical(g, spread, RATING_SCALE, comparison_noise=0.1, **fixed)

    return draw


def _partial_range(g: torch.Generator, spread: float) -> tuple[float, float]:
    width, lo = torch.rand(2, generator=g, dtype=torch.float64).tolist()
    width = 0.4 + 0.27 * width
    return (lo * (1 - width), lo * (1 - width) + width)


def _uniform_between(a: float, b: float) -> Callable[[torch.Generator, float], float]:
    return lambda g, spread: a + (b - a) * float(torch.rand((), generator=g, dtype=torch.float64))


def _scaled_normal(sd: float) -> Callable[[torch.Generator, float], float]:
    return lambda g, spread: sd * spread * float(torch.randn((), generator=g, dtype=torch.float64))


#: the realistic families (docs/suite.md): people drawn from the published ranges, with one trait
#: pushed further in each; utilities from the idealised families' shapes
REALISTIC_FAMILIES: dict[str, Family] = {
    f.name: f
    for f in [
        Family(
            "typical-peak",
            2,
            _narrow_peak,
            0.1,
            40.0,
            0.05,
            likert=True,
            rater=_typical(levels=7),
            description="the narrow-peak utility; typical people (all traits at the published ranges), 1-7 Likert",
        ),
        Family(
            "offset-drift",
            4,
            _two_bumps,
            0.1,
            40.0,
            0.25,
            rater=_typical(rating_offset=_scaled_normal(0.48), drift_sd=lambda g, s: 0.1 * s),
            description="two bumps in 4-D; twice the typical offset and drift, a slider",
        ),
        Family(
            "compressed",
            2,
            _plateau,
            0.1,
            40.0,
            0.1,
            likert=True,
            rater=_typical(scale_range=_partial_range, levels=5),
            description="the plateau; people using 40-67 % of a 1-5 scale",
        ),
        Family(
            "lapsing",
            1,
            _damped_wave,
            0.1,
            40.0,
            0.03,
            rater=_typical(
                lapse_rate=_uniform_between(0.25, 0.4),
                rating_precision=lambda g, s: precision_for_noise(0.15 * s, RATING_SCALE),
                rating_offset=0.0,
                drift_sd=0.0,
                scale_range=(0.0, 1.0),
            ),
            description="one damped wave; choices lapse 25-40 % of the time, precise unbiased ratings",
        ),
        Family(
            "typical-pool",
            3,
            lambda g: _botorch(Hartmann(dim=3), g),
            0.1,
            40.0,
            0.2,
            likert=True,
            pool=300,
            rater=_typical(levels=7),
            description="Hartmann-3 over a pool of 300; typical people, 1-7 Likert",
        ),
    ]
}

#: the idealised families (the paper's users) and the realistic ones
ALL_FAMILIES: dict[str, Family] = {**FAMILIES, **REALISTIC_FAMILIES}


def model_settings(family: Family) -> dict[str, float]:
    """The fixed condition's model: ``family.model``, or the family's lengthscale, outputscale 1 and
    the user's own noise (``nu`` 20 for Likert raters: a level is a bin 0.2 wide)."""
    if family.model is not None:
        return dict(family.model)
    return {
        "lengthscale": family.lengthscale,
        "outputscale": 1.0,
        "comparison_noise": family.comparison_noise,
        "rating_scale": RATING_SCALE,
        "rating_precision": 20.0 if family.likert else family.rating_precision,
    }  # a realistic family's model is the nominal person's: no offset, gain 1, no lapses


@dataclass
class TrialSetup:
    """One trial of a family: the user, the metric points and their truth, the first pair."""

    user: User
    eval_X: Tensor  # E x d metric points
    f_true: Tensor  # E true utilities
    u_true: Tensor  # E true ratings (the raters' mean rating, eq. 7)
    x0: Tensor  # 2 x d the first comparison's items
    pool: Tensor | None  # P x d, or None (fresh candidates)
    selector_seed: int


def setup(family: Family, trial_seed: int, effort: EffortModel | None = None) -> TrialSetup:
    """A trial of ``family`` drawn from ``trial_seed`` (``effort``: a realistic person's seconds)."""
    g = torch.Generator().manual_seed(int(trial_seed))
    utility = family.draw(g)
    user_seed, selector_seed = torch.randint(0, 2**62, (2,), generator=g).tolist()
    rating_scale = family.model["rating_scale"] if family.model is not None else RATING_SCALE
    paper_user = SimulatedUser(
        utility,
        family.comparison_noise,
        rating_scale,
        family.rating_precision,
        torch.Generator().manual_seed(user_seed),
    )
    user: User = LikertUser(paper_user) if family.likert and not family.realistic else paper_user
    pool = None
    if family.pool is not None:
        pool = _uniform(g, family.pool, family.dim)
        eval_X = pool
        x0 = pool[torch.randperm(family.pool, generator=g)[:2]]
    else:
        eval_X = evaluation_grid(101) if family.dim == 1 else _uniform(g, EVAL_POINTS, family.dim)
        x0 = _uniform(g, 2, family.dim)
    with torch.no_grad():
        f_true = utility(eval_X)
    if family.rater is not None:  # realistic: the person, drawn for this utility's spread from the user's own stream
        person_g = torch.Generator().manual_seed(user_seed)
        profile = family.rater(person_g, float(f_true.std()))
        if effort is not None:
            profile = profile.with_effort(effort)
        user = RealisticUser(utility, profile, person_g)
    return TrialSetup(user, eval_X, f_true, rating_link(f_true, rating_scale), x0, pool, selector_seed)
