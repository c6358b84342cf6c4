"""Property-based scene fuzzing (tests/scene_fuzz.py): a short, derandomised run in the test suite.

Property (the oracle): for every mutated scene, ``python -m warpdem <scene> --frames 1`` either exits 0 with a finite
energy balance and a USD stage, or exits 2/3 with ``error: ...`` lines and no traceback, within the time bound of
scene_fuzz.TIME_BOUND (a hang fails the example instead of stalling the suite: the run happens in a worker process
that is replaced). The long run with counts is benchmarks/fuzz_scenes.py.
"""

from __future__ import annotations

import math

import pytest
import scene_fuzz
from hypothesis import HealthCheck, given, settings

EXAMPLES = 40
"""Examples of the in-suite run: most are refused at validation (milliseconds), the rest build and run a few steps."""


@pytest.fixture(scope="module")
def runner():
    r = scene_fuzz.Runner()
    yield r
    r.close()


@settings(
    max_examples=EXAMPLES,
    derandomize=True,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(case=scene_fuzz.cases())
def test_mutated_scenes_end_cleanly(runner, case):
    outcome = runner.run(case)
    assert outcome.problem() is None, (
        f"{case.base}: {'; '.join(case.mutations)}: {outcome.problem()}\n{outcome.stderr[-3000:]}"
    )


def test_the_property_rejects_what_it_should():
    # The judge itself: a traceback, exit 1, a NaN energy line, a hang and a bare exit 2 all break the property.
    energy = {"kinetic_translational": 1.0}
    good = scene_fuzz.Outcome(0, "", {"energy_start": energy, "energy_end": energy}, usd_exists=True)
    assert good.problem() is None
    assert scene_fuzz.Outcome(2, "error: s.toml: run.dt: must be > 0\n").problem() is None
    nan = {"kinetic_translational": math.nan}
    assert scene_fuzz.Outcome(0, "", {"energy_start": energy, "energy_end": nan}, True).problem() is not None
    assert scene_fuzz.Outcome(0, "", {"energy_start": energy, "energy_end": energy}, False).problem() is not None
    assert scene_fuzz.Outcome(2, "Traceback (most recent call last):\n").problem() is not None
    assert scene_fuzz.Outcome(2, "something went wrong\n").problem() is not None
    assert scene_fuzz.Outcome(1, "internal error: KeyError\n").problem() is not None
    assert scene_fuzz.Outcome(None, "", hang=True).problem() is not None
