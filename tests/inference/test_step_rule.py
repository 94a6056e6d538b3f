"""The Newton-Armijo step rule is defined once (inference/step_rule.py) and every Newton loop reads it."""

import pathlib
import re

import pytest

import torchpref
from torchpref.inference.step_rule import STEP_RULE, StepRule

PACKAGE = pathlib.Path(torchpref.__file__).parent
# the modules that run a Newton loop, each of which must read STEP_RULE rather than its own constants
NEWTON_LOOPS = ["inference/newton.py", "inference/_compiled.py", "population/joint.py", "population/shards.py"]
# a literal copy of the rule: the Armijo factor, the shortest step, or halving a step length in place
LITERAL_COPY = re.compile(r"\b1e-4\b|\b1e-12\b|\b(?:t|step)\s*\*=\s*0\.5")


@pytest.mark.parametrize("module", NEWTON_LOOPS)
def test_every_newton_loop_reads_the_one_step_rule(module):
    text = (PACKAGE / module).read_text()
    assert "STEP_RULE" in text, f"{module} does not read torchpref.inference.step_rule.STEP_RULE"
    copies = [m.group(0) for m in LITERAL_COPY.finditer(text)]
    assert not copies, f"{module} writes the step rule's constants again: {copies}"


def test_no_other_module_defines_armijo_constants():
    for path in PACKAGE.rglob("*.py"):
        if path.name == "step_rule.py":
            continue
        text = path.read_text()
        assert not re.search(r"^ARMIJO\s*=\s*[0-9]", text, re.M), f"{path} defines ARMIJO as a literal"


def test_backtrack_matches_brute_force():
    # Psi(t) = -(t - 0.3)^2 along a direction with decrement 1: the first accepted length of
    # 1, 1/2, 1/4, ... is the first with -(t - .3)^2 >= -(0.09) + 1e-4 t
    rule = StepRule()
    psi0, dec = -0.09, 1.0
    expected = next(t for t in rule.lengths() if -((t - 0.3) ** 2) >= psi0 + rule.armijo * t * dec)
    got = rule.backtrack(lambda t: (t, -((t - 0.3) ** 2)), lambda q: q[1], psi0, dec)
    assert got is not None and got[0] == expected == 0.5


def test_backtrack_gives_up_and_refuses_non_finite():
    rule = StepRule()
    assert rule.backtrack(lambda t: float("nan"), lambda q: q, 0.0, 1.0) is None
    assert rule.backtrack(lambda t: -1.0, lambda q: q, 0.0, 1.0) is None
    lengths = list(rule.lengths())
    assert lengths[0] == 1.0 and lengths[-1] > rule.min_step and lengths[-1] * rule.shrink <= rule.min_step
    assert STEP_RULE == StepRule()
