"""LDEC §3's facility beside the paper (``python benchmarks/seed_report.py facility``): both geologies run to 200 ms
by benchmarks/facility_scenes.py's ``report``, and the paper's set-up and nine findings held against its figures, as
OUT/facility.md (the claims' table, then facility_scenes' side-by-side table of the same runs) and OUT/facility.png
(the sections at 10 ms and at the end, facility_scenes' picture).

The verdicts compare the two geologies, as the paper does; each criterion is written in its row. Read a figure's
error where facility_scenes' docstring gives it: wave speeds are fits over 5–6 probes, ±10 %.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple

import facility_scenes as fs  # beside this script, in benchmarks/
import numpy as np
from report_common import LDEC, SCENES_DIR, Claim, claim_table, write_atomically

FACILITY = "facility"
"""The scenario's name on seed_report.py's command line (two scenes, so not one of its scene scenarios)."""
END_TIME = 0.2
"""The runs' end [s] unless --end-time: the report follows the collapse past the scenes' 70 ms (facility_scenes)."""
LDEC_BLOCK = 0.3
"""LDEC's typical block size [m] (§3: "typical block sizes of 30 cm", 8 M blocks in a 60 m cube)."""
SCALE = 3.0
"""The scenes' replica scale, 1:3 (their header): lengths and times × 3 at full scale."""
READ_ERROR = 0.1
"""A wave speed's read error [-]: each is a fit over 5–6 probes, each in its own 2 m block (facility_scenes)."""
TOTAL_COLLAPSE = 0.5
"""Share of the largest room's volume filled with rubble for a total collapse [-]: a loose pile fills ~0.6 of the
volume it lies in."""
MINIMAL = 0.01
"""Share of a tunnel's volume filled with rubble up to which its damage is minimal [-]."""


class Runs(NamedTuple):
    """The facility's two runs (facility_scenes.report's dicts), the persistent scene (the shared set-up) and the
    non-persistent one (its joint sets)."""

    persistent: dict
    nonpersistent: dict
    scene: object
    nonpersistent_scene: object

    @property
    def both(self) -> tuple[dict, dict]:
        return self.persistent, self.nonpersistent


def _share(run: dict, pick) -> float:
    """Rubble over volume of the sections ``pick(section)`` selects at the end [-]."""
    parts = [s for s in run["sections"] if pick(s)]
    return sum(s["rubble"] for s in parts) / sum(s["volume"] for s in parts)


def _room(run: dict) -> dict:
    return next(s for s in run["sections"] if s["kind"] == "room")


def _anisotropy(run: dict) -> float:
    """Largest |v_θ / v_down − 1| over the 45° and 75° rays [-]."""
    w = run["waves"]
    return max(abs(w[ray]["speed"] / w["down"]["speed"] - 1.0) for ray in ("45°", "75°"))


def _domain(r: Runs) -> tuple[str, str]:
    lo, hi = np.asarray(r.scene.mesh.lo), np.asarray(r.scene.mesh.hi)
    size = hi - lo
    depth = float(hi[2] - min(o.lo[2] for o in r.scene.mesh.openings if o.kind == "room"))
    text = (
        f"{size[0]:g} × {size[1]:g} × {size[2]:g} m, the facility's floor {depth:g} m down: "
        f"{SCALE * size[0]:g} × {SCALE * size[1]:g} × {SCALE * size[2]:g} m and {SCALE * depth:g} m at full scale "
        "(1:3 replica scaling); the largest room, a main tunnel, an access tunnel crossing it, a lift shaft"
    )
    return (
        text,
        f"differs (a 1:3 model: {SCALE * size[0]:g} m across at full scale, against 60 m; the facility in kind)",
    )


def _blocks(r: Runs) -> tuple[str, str]:
    p = r.persistent
    text = f"2 m blocks, {p['blocks']} ({p['tets']} tets as rigid bodies); LDEC: 30 cm, 8 M"
    return text, f"differs ({SCALE * 2.0 / LDEC_BLOCK:.0f}× LDEC's relative block size at full scale)"


def _load(r: Runs) -> tuple[str, str]:
    (a_p, j_p), (a_n, j_n) = ((x["load"]["area"], x["load"]["impulse"]) for x in r.both)
    gap = abs(j_n / j_p - 1.0)
    text = (
        f"100 MPa on a 3 m disc (0.3 ms rise, 3 ms decay): {a_p:.1f} / {a_n:.1f} m² loaded, impulse "
        f"{j_p:.4g} / {j_n:.4g} N s (persistent / non-persistent)"
    )
    return text, f"differs (a pressure patch, not a calibrated 1 kt source); the same blast within {gap:.1%}"


def _joints(r: Runs) -> tuple[str, str]:
    """The randomized sets of the non-persistent scene, read from it: each plane alternates runs of ``layers`` to
    ``layers_max`` beds with a piece and without one, each run length a uniform draw, so a piece persists through the
    mean run, (layers + layers_max)/2 beds, and half the slabs of a plane hold one (twice the planes' spacing
    between pieces on average)."""
    sets = r.nonpersistent_scene.mesh.joint_sets
    random = [s for s in sets if s.layers_max is not None]
    bed = sets[random[0].reference].spacing
    parts = []
    for s in random:
        mean_run = 0.5 * (s.layers + s.layers_max) * bed
        tilt = "exactly" if s.jitter_angle == 0.0 else f"within {s.jitter_angle:g}° of"
        parts.append(
            f"'{s.name}', {tilt} vertical planes {s.spacing:g} m apart in random runs of {s.layers} to "
            f"{s.layers_max} beds with and without a piece ({mean_run:g} m persistence and {2.0 * s.spacing:g} m "
            "spacing on average)"
        )
    return (
        f"bedding {bed:g} m apart; " + "; ".join(parts),
        "reproduced (randomized persistence through a few layers; LDEC's sets are near-vertical, these vertical)"
        if random
        else "not reproduced (no randomized set)",
    )


def _anisotropic(r: Runs) -> tuple[str, str]:
    a_p, a_n = (_anisotropy(x) for x in r.both)

    def speeds(x: dict) -> str:
        w = x["waves"]
        return " / ".join(f"{w[ray]['speed'] / x['c_p']:.2f}" for ray in fs.RAYS)

    text = (
        f"first-arrival speed down / 45° / 75° (/c_p): {speeds(r.persistent)} persistent, "
        f"{speeds(r.nonpersistent)} non-persistent; largest departure from the speed down {a_p:.0%} / {a_n:.0%}"
    )
    if a_p > a_n + READ_ERROR:
        verdict = "reproduced"
    elif a_p > READ_ERROR:
        verdict = "partly"
    else:
        verdict = "not reproduced"
    return text, (
        f"{verdict} (reproduced: the persistent rock's departure exceeds the other's by more than the "
        f"±{READ_ERROR:.0%} read error; partly: it exceeds the read error alone)"
    )


def _attenuation(r: Runs) -> tuple[str, str]:
    (n_p, s_p), (n_n, s_n) = ((x["attenuation"]["n"], x["attenuation"]["n_se"]) for x in r.both)
    se = math.hypot(s_p, s_n)
    text = f"PPV ∝ r^−n: n = {n_p:.2f} ± {s_p:.2f} persistent, {n_n:.2f} ± {s_n:.2f} non-persistent"
    verdict = "reproduced" if n_n - n_p > se else "partly" if n_n > n_p else "not reproduced"
    return text, (
        f"{verdict} (reproduced: the non-persistent n larger by more than the combined standard error, {se:.2f}; "
        "partly: larger within it)"
    )


def _chimney(r: Runs) -> tuple[str, str]:
    h_p, h_n = (max(s["chimney"] for s in x["sections"]) for x in r.both)
    end = 1e3 * r.persistent["end_time"]
    text = f"highest chimney over any opening at {end:.0f} ms: {h_p:g} m persistent, {h_n:g} m non-persistent"
    if h_p >= h_n + fs.LAYER:
        verdict = "reproduced"
    elif h_p > 0.0:
        verdict = "partly"
    else:
        verdict = "not reproduced"
    return (
        text,
        f"{verdict} (reproduced: the persistent one higher by a bed, {fs.LAYER:g} m, or more; partly: one grew)",
    )


def _diffraction(r: Runs) -> tuple[str, str]:
    d_p, d_n = (x["diffraction"] for x in r.both)
    se = math.hypot(d_p["ratio_se"], d_n["ratio_se"])
    text = (
        f"mean PPV·r below the largest room over its mean on a lit ring at the same depth (facility_scenes): "
        f"{d_p['ratio']:.2f} ± {d_p['ratio_se']:.2f} persistent, {d_n['ratio']:.2f} ± {d_n['ratio_se']:.2f} "
        f"non-persistent (first arrivals in the shadow {1e3 * d_p['shadow_arrival']:.2f} / "
        f"{1e3 * d_n['shadow_arrival']:.2f} ms, on the ring {1e3 * d_p['lit_arrival']:.2f} / "
        f"{1e3 * d_n['lit_arrival']:.2f} ms)"
    )
    gap = d_n["ratio"] - d_p["ratio"]
    verdict = "reproduced" if gap > se else "partly" if gap > 0.0 else "not reproduced"
    return text, (
        f"{verdict} (reproduced: the non-persistent measure larger by more than the combined standard error, "
        f"{se:.2f}; partly: larger within it)"
    )


def _room_collapse(r: Runs) -> tuple[str, str]:
    n = r.nonpersistent
    share = _room(n)["rubble"] / _room(n)["volume"]
    mean, most, _ = n["history"]["roof"][-1]
    text = (
        f"non-persistent: {share:.1%} of the room's {_room(n)['volume']:.0f} m³ is rubble at "
        f"{1e3 * n['end_time']:.0f} ms; its roof bed {100 * mean:.0f} cm down on average ({100 * most:.0f} cm at most)"
    )
    verdict = "reproduced" if share >= TOTAL_COLLAPSE else "partly" if mean > fs.CHIMNEY_DROP else "not reproduced"
    return text, (
        f"{verdict} (reproduced: rubble fills {TOTAL_COLLAPSE:.0%} of it, as a loose pile would; partly: its roof bed "
        f"sinks more than {100 * fs.CHIMNEY_DROP:.0f} cm)"
    )


def _persistent_collapse(r: Runs) -> tuple[str, str]:
    s_p, s_n = (_room(x)["rubble"] / _room(x)["volume"] for x in r.both)
    text = f"rubble in the largest room: {s_p:.1%} persistent, {s_n:.1%} non-persistent"
    verdict = "reproduced" if s_p > s_n else "not reproduced"
    return text, f"{verdict} (reproduced: more in the persistent rock, whose joints run through the whole domain)"


def _is_access(s: dict) -> bool:
    return s["name"].startswith("access tunnel")


def _is_stretch(s: dict) -> bool:
    return s["kind"] == "tunnel" and s["name"].startswith("main tunnel")


def _narrow(r: Runs) -> tuple[str, str]:
    shares = [_share(x, _is_access) for x in r.both]
    text = f"the 2 m access tunnel's arms: {shares[0]:.1%} / {shares[1]:.1%} of their volume is rubble"
    verdict = "reproduced" if max(shares) < MINIMAL else "not reproduced"
    return text, f"{verdict} (reproduced: under {MINIMAL:.0%} in both geologies)"


def _midsize(r: Runs) -> tuple[str, str]:
    cells = []
    spread = []
    for x in r.both:
        shares = [s["rubble"] / s["volume"] for s in x["sections"] if _is_stretch(s)]
        cells.append(" / ".join(f"{v:.1%}" for v in shares))
        spread.append(max(shares) > 0.0 and max(shares) >= 2.0 * min(shares))
    text = f"the 4 m main tunnel's straight stretches: {cells[0]} persistent, {cells[1]} non-persistent"
    verdict = "reproduced" if all(spread) else "partly" if any(spread) else "not reproduced"
    return text, f"{verdict} (a range: the most damaged stretch holds twice the least's share or more, per geology)"


def _junctions(r: Runs) -> tuple[str, str]:
    pairs = [(_share(x, lambda s: s["kind"] == "junction"), _share(x, _is_stretch)) for x in r.both]
    text = "rubble share, junctions / straight stretches: " + ", ".join(
        f"{j:.1%} / {s:.1%} {name}" for (j, s), name in zip(pairs, ("persistent", "non-persistent"), strict=True)
    )
    worse = [j > s for j, s in pairs]
    verdict = "reproduced" if all(worse) else "partly" if any(worse) else "not reproduced"
    return text, f"{verdict} (reproduced: the junctions hold the larger share in both geologies)"


CLAIMS = (
    Claim(
        "§3, Fig. 5",
        '"The solution domain spanned 60 m in each direction and encapsulated a generic facility that included '
        'several tunnel sections and a lift shaft"; "50 m below the surface"',
        _domain,
    ),
    Claim(
        "§3", '"typical block sizes of 30 cm ... approximately 8 million individual polyhedral rock blocks"', _blocks
    ),
    Claim("§3", '"loading corresponding to one kiloton at the surface 50 m above"', _load),
    Claim("§3, Fig. 6", '"non-persistent (i.e., randomized) joints in the surrounding rock"', _joints),
    Claim("§3, Fig. 7", '"The regular model exhibited strong anisotropy"', _anisotropic),
    Claim("§3, Fig. 7", '"The irregular model exhibited higher attenuation"', _attenuation),
    Claim(
        "§3",
        '"Persistent joints allow shear motion along the entire length of the computational domain, resulting in '
        'large \u201cchimney\u201d effects above collapsed tunnels sections"',
        _chimney,
    ),
    Claim("§3", "the same: more collapse where the joints persist", _persistent_collapse),
    Claim("§3", '"The irregular model resulted in more diffraction of waves around cavities"', _diffraction),
    Claim(
        "§3, Fig. 8", '"the largest room within the facility has totally collapsed" (non-persistent)', _room_collapse
    ),
    Claim("§3, Fig. 8", '"the narrowest access tunnels experienced minimal damage"', _narrow),
    Claim("§3, Fig. 8", '"The midsize tunnels show a range of damage"', _midsize),
    Claim(
        "§3, Fig. 8",
        '"most damage occurring in tunnel sections that contain a junction with another tunnel"',
        _junctions,
    ),
)
"""The report's rows: the set-up (four), then the paper's nine findings."""


def run_facility(device: str, end_time: float | None) -> Runs:
    """Runs both geologies (facility_scenes.run_scenes) to ``end_time`` [s] (END_TIME if None)."""
    from warpdem.scene import load_scene

    persistent, nonpersistent = fs.run_scenes(fs.SCENES, device, end_time or END_TIME)
    scenes = (load_scene(SCENES_DIR / f"{name}.toml") for name in fs.SCENES)
    return Runs(persistent, nonpersistent, *scenes)


def write_facility_report(out: Path, device: str, end_time: float | None, command: str) -> list[Path]:
    """Runs the facility and writes OUT/facility.md, OUT/facility.png and OUT/facility.json (the runs' figures, as
    facility_scenes.py --json writes them). Returns the paths."""
    runs = run_facility(device, end_time)
    side_by_side = fs.format_side_by_side(list(runs.both))
    print("\n".join(side_by_side))
    out.mkdir(parents=True, exist_ok=True)
    p = runs.persistent
    lines = [
        "# An underground facility in jointed rock (LDEC §3, Figs. 5–8) — the paper beside warpdem",
        "",
        f"Scenes `scenes/facility_persistent.toml` and `scenes/facility_nonpersistent.toml`, run to "
        f"{1e3 * p['end_time']:.0f} ms (LDEC's 200 ms is 70 ms at the scenes' 1:3 scale; the report follows the "
        f"collapse further); paper: {LDEC}.",
        f"Written by `{command}`; every figure below is measured on those runs by benchmarks/facility_scenes.py "
        "(its docstring says how: probes, windows, sections).",
        "",
        *claim_table(CLAIMS, runs),
        "",
        f"![{FACILITY}]({FACILITY}.png)",
        "",
        "*The section through the largest room and the main tunnel (y = 12 m): block speed at 10 ms (LDEC's Fig. 7 "
        "at 30 ms, scaled) and displacement at the end, log scales; persistent above, non-persistent below.*",
        "",
        "The same runs, side by side (`python benchmarks/facility_scenes.py --end-time 0.2` prints this table):",
        "",
        "```text",
        *side_by_side,
        "```",
        "",
    ]
    md, png, js = (out / f"{FACILITY}.{ext}" for ext in ("md", "png", "json"))
    write_atomically(md, "\n".join(lines))
    write_atomically(js, fs.figures_json(list(runs.both)))
    fs.draw_sections(list(runs.both), png)
    return [md, png, js]
