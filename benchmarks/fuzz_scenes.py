"""Long run of the scene fuzzer (tests/scene_fuzz.py): mutate the shipped scenes, run each mutation through the
command line, and count the outcomes.

    python benchmarks/fuzz_scenes.py --examples 500 [--seed 1] [--json counts.json] [--failures failures.toml]

Each example must end with exit 0 and finite output, or exit 2/3 with ``error: ...`` lines, within the time bound of
tests/scene_fuzz.py. The script prints a table of exit statuses, the number of property failures by kind, and writes
every failing scene (with the mutations that made it) to ``--failures`` so it can be replayed with
``python -m warpdem <scene>``. Unlike the short run in the test suite it draws fresh examples for every seed and does
not shrink failures (a failure is a finding to fix and turn into a test).
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import sys
import time
from pathlib import Path

from hypothesis import HealthCheck, Phase, given, seed, settings

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import scene_fuzz


class TimeUp(Exception):
    """The --minutes budget is spent."""


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--examples", type=int, default=200, help="scenes to generate and run")
    p.add_argument("--seed", type=int, default=0, help="Hypothesis seed")
    p.add_argument("--json", type=Path, help="write the counts as JSON")
    p.add_argument("--failures", type=Path, default=Path("fuzz_failures.txt"), help="failing scenes go here")
    p.add_argument(
        "--profile",
        choices=("all", "runtime"),
        default="all",
        help="all mutations, or only rescaled numbers and duplicated entries (scenes that mostly run)",
    )
    p.add_argument("--minutes", type=float, default=math.inf, help="stop after this long (counts so far are kept)")
    args = p.parse_args(argv)

    runner = scene_fuzz.Runner()
    statuses: collections.Counter[str] = collections.Counter()
    problems: collections.Counter[str] = collections.Counter()
    bases: collections.Counter[str] = collections.Counter()
    failures: list[str] = []
    start = time.perf_counter()

    @seed(args.seed)
    @settings(
        max_examples=args.examples,
        deadline=None,
        database=None,
        phases=[Phase.generate],
        suppress_health_check=list(HealthCheck),
    )
    @given(scene_fuzz.cases(profile=args.profile))
    def one(case: scene_fuzz.Case) -> None:
        if time.perf_counter() - start > 60.0 * args.minutes:
            raise TimeUp
        outcome = runner.run(case)
        status = "hang" if outcome.hang else str(outcome.status)
        statuses[status] += 1
        bases[case.base] += 1
        problem = outcome.problem()
        n = sum(statuses.values())
        print(f"{n:5d} {time.perf_counter() - start:8.1f}s  exit {status:>4}  {case.base}: {'; '.join(case.mutations)}")
        if problem is not None:
            problems[problem] += 1
            text, _ = scene_fuzz.case_payload(case)
            failures.append(f"# {problem}\n# {case.base}: {'; '.join(case.mutations)}\n# stderr:\n")
            failures[-1] += "".join(f"#   {line}\n" for line in outcome.stderr.splitlines()[-30:]) + text + "\n"
            print(f"      FAIL: {problem}: {outcome.stderr.strip().splitlines()[-1:] or ''}", flush=True)

    try:
        one()
    except TimeUp:
        pass
    finally:
        runner.close()
    elapsed = time.perf_counter() - start
    total = sum(statuses.values())
    print(f"\n{total} examples in {elapsed:.0f} s")
    for status, count in sorted(statuses.items()):
        print(f"  exit {status:>4}: {count}")
    print(f"property failures: {sum(problems.values())}")
    for problem, count in problems.most_common():
        print(f"  {count:4d}  {problem}")
    if failures:
        args.failures.write_text("\n".join(failures))
        print(f"failing scenes written to {args.failures}")
    if args.json is not None:
        args.json.write_text(
            json.dumps(
                {
                    "examples": total,
                    "seconds": elapsed,
                    "exit_status": dict(statuses),
                    "failures": dict(problems),
                    "bases": dict(bases),
                },
                indent=1,
            )
        )
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
