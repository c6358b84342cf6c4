"""What the side-by-side reports of the seed papers share (benchmarks/seed_report.py, benchmarks/facility_report.py):
the papers, a report row (:class:`Claim`), the claims' Markdown table and the atomic write of a report's file."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
SCENES_DIR = ROOT / "scenes"
OUT_DIR = ROOT / "docs" / "reports"

CIMNE = "the adaptive DEM/FEM blast paper (CIMNE; `../shared/seeds/adaptive_dem_fem_blast.txt`)"
LDEC = "the LDEC FEM/DEM fracture paper (LLNL; `../shared/seeds/ldec_fem_dem_fracture.txt`)"


@dataclass(frozen=True)
class Claim:
    """One row of a report: what the paper says, and how warpdem's run is held against it.

    Attributes:
        where: the paper's section or figure.
        paper: the paper's words (quoted) or the set-up it states.
        judge: what the run measured (seed_report.Samples; the facility's pair of runs) → (warpdem's measured
            figure, the verdict with its criterion).
    """

    where: str
    paper: str
    judge: Callable[[Any], tuple[str, str]]


def claim_table(claims: tuple[Claim, ...] | list[Claim], measured: Any) -> list[str]:
    """The claims judged on ``measured``, as the lines of a Markdown table: where, the paper, warpdem, the verdict."""
    rows = [(claim.where, claim.paper, *claim.judge(measured)) for claim in claims]
    lines = ["| where | the paper | warpdem | verdict |", "|---|---|---|---|"]
    # A "|" inside a cell (|x|) would end it: Markdown tables take it escaped.
    return lines + ["| " + " | ".join(cell.replace("|", "\\|") for cell in row) + " |" for row in rows]


def write_atomically(path: Path, text: str) -> None:
    """Writes ``text`` to ``path`` through a temporary name beside it, so a stopped run leaves no half a report."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    tmp.replace(path)
