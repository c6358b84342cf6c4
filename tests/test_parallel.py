"""Runs decomposed over MPI ranks (warpdem.parallel, issue 25): spheres, their contacts with history, rolling, walls
and gravity.

Oracles:
- One process is the reference, bit for bit: on the CPU a subdomain keeps its spheres in global-id order and its
  contact grid has the whole run's cells and buckets, so every pair is seen in the same order and every force sums in
  the same order. The time series (every energy line, every count, every frame) and the final checkpoint's spheres,
  lists and bonds are compared for equality, not within a tolerance: a pour at 2, 3 and 4 ranks (3 and 4
  oversubscribed here: ghosts then come from ranks beyond the next slab), the default scene's bonded beam breaking at
  2 ranks.
- A checkpoint is the whole run's, whatever the rank count: a run stopped on 2 ranks and resumed in one process, and
  one stopped in one process and resumed on 2 ranks, end bit for bit where the uninterrupted run ends.
- The slabs and the rows by themselves: every centre has exactly one owner, which holds it; equal shares of the weight
  to one sphere; rows taken from a subdomain and put back give the same spheres, lists and partners.
- The path GPU ranks take: a halo channel is a copy, staged through host buffers or not, on every device the tests
  see; the staging forced on CPU ranks leaves the pour one process's bit for bit; ranks asking for "cuda" take their
  node's GPUs in turn.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from warpdem.parallel.domain import Slabs
from warpdem.parallel.ranked import STAGING_VARIABLE

MPIEXEC = Path(sys.executable).parent / "mpiexec"
ROOT = Path(__file__).resolve().parent.parent


def _channel_pour() -> str:
    """300 beads dropped from up to 4.5 cm into a box 12 cm by 20 cm (benchmarks/parallel_scaling.py's pour, short
    and low): 3 912 steps to 0.12 s, 49 contacts at the end; the beads fall up to 4 cm, ten times the migration
    margin (2 skins, 3.2 mm), so spheres migrate with their histories."""
    spec = importlib.util.spec_from_file_location("parallel_scaling", ROOT / "benchmarks" / "parallel_scaling.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.channel_pour(300, 0.12, height=0.05)


def _mpiexec(ranks: int) -> list[str]:
    """The launcher's words for ``ranks`` ranks. The test extra installs mpi4py and MPICH (its mpiexec beside this
    Python), so a missing launcher is a broken install, a failure, not a skip."""
    assert MPIEXEC.exists(), f'no {MPIEXEC}: pip install -e ".[test]" brings mpi4py and MPICH'
    return [str(MPIEXEC), "-n", str(ranks)]


def _run(
    scene: Path, out: Path, ranks: int, *args: str, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess:
    """Run ``scene`` into ``out`` on ``ranks`` ranks (1: one process), its summary as ``out/summary.json``, with
    ``env`` added to the environment."""
    summary = ["--summary-json", str(out / "summary.json")]
    command = [sys.executable, "-m", "warpdem", str(scene), "--out", str(out), "--quiet", *summary, *args]
    if ranks > 1:
        command = [*_mpiexec(ranks), *command]
    done = subprocess.run(command, capture_output=True, text=True, timeout=600, env={**os.environ, **(env or {})})
    assert done.returncode == 0, f"{ranks} ranks: {done.stdout[-2000:]}{done.stderr[-3000:]}"
    return done


def _final_spheres(out: Path) -> dict[str, np.ndarray]:
    """The last checkpoint's sphere arrays, lists compared over their live slots only (a dead slot holds whatever the
    last build left there)."""
    last = sorted((out / "checkpoints").glob("*.h5"))[-1]
    with h5py.File(last) as f:
        state = f["state"]
        n = int(state["particle_count"][0])
        k = len(state["nbr_index"]) // len(state["nbr_count"])
        count = state["nbr_count"][:n]
        live = np.arange(k)[None, :] < count[:, None]
        found = {
            name: state[name][:n]
            for name in ("particle_q", "particle_qd", "particle_omega", "energy_damping", "energy_friction")
        }
        found["nbr_count"] = count
        for name in ("nbr_index", "nbr_shear"):
            found[name] = state[name][: n * k].reshape(n, k, -1)[live]
        found["nbr_bond"] = state["nbr_bond"][: n * k].reshape(n, k)[live]
        nb = int(state["bond_count"][0])
        for name in ("bond_i", "bond_j", "bond_shear", "bond_broken"):
            found[name] = state[name][:nb]
        found["bonds_broken_total"] = state["bonds_broken_total"][()]
        found["time"] = state["time"][()]
    return found


def _summary(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


def _assert_same_run(a: Path, b: Path, what: str, stem: str = "channel_pour") -> None:
    series_a, series_b = (p / f"{stem}_series.csv" for p in (a, b))
    assert series_a.read_text() == series_b.read_text(), f"{what}: the time series differ"
    fa, fb = _final_spheres(a), _final_spheres(b)
    for name in fa:
        assert np.array_equal(fa[name], fb[name]), f"{what}: {name} differs"


@pytest.fixture(scope="module")
def one_process(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The scene and its one-process run."""
    root = tmp_path_factory.mktemp("parallel")
    scene = root / "channel_pour.toml"
    scene.write_text(_channel_pour())
    _run(scene, root / "one", 1)
    return scene, root / "one"


@pytest.mark.parametrize("ranks", [2, 3, 4])
def test_ranks_match_one_process_bit_for_bit(one_process: tuple[Path, Path], tmp_path: Path, ranks: int) -> None:
    scene, reference = one_process
    _run(scene, tmp_path / "out", ranks)
    _assert_same_run(reference, tmp_path / "out", f"{ranks} ranks")
    assert _summary(tmp_path / "out")["migrations"] > 0  # the comparison covers spheres that moved between ranks


def test_halo_staged_through_host_copies_matches_one_process_bit_for_bit(
    one_process: tuple[Path, Path], tmp_path: Path
) -> None:
    # The path GPU ranks take (their messages copied to page-locked host buffers and back, one device wait before
    # the sends), forced on the CPU: copies move bits, so the run is still one process's.
    scene, reference = one_process
    _run(scene, tmp_path / "out", 2, env={STAGING_VARIABLE: "1"})
    _assert_same_run(reference, tmp_path / "out", "2 ranks, staged halo")
    assert _summary(tmp_path / "out")["migrations"] > 0


@pytest.mark.parametrize(("first", "then"), [(2, 1), (1, 2)])
def test_a_checkpoint_resumes_on_another_rank_count(
    one_process: tuple[Path, Path], tmp_path: Path, first: int, then: int
) -> None:
    scene, reference = one_process
    out = tmp_path / "out"
    _run(scene, out, first, "--end-time", "0.06")
    (checkpoint,) = (out / "checkpoints").glob("*.h5")
    _run(scene, out, then, "--restart", str(checkpoint))
    _assert_same_run(reference, out, f"{first} ranks then {then}")


def _started_past_two_frames(command: list[str], series: Path) -> subprocess.Popen:
    """The launcher of ``command``, in a session of its own, once the run has written its second frame."""
    launcher = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    deadline = time.monotonic() + 300
    while launcher.poll() is None and time.monotonic() < deadline:
        if series.is_file() and len(series.read_text().splitlines()) >= 3:
            break
        time.sleep(0.02)
    assert launcher.poll() is None, "the run ended before the test could reach it"
    return launcher


def _ranks_of(out: Path) -> list[int]:
    """The pids of the rank processes writing to ``out``."""
    found = []
    for entry in Path("/proc").iterdir():
        try:
            words = (entry / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"warpdem" in words and str(out).encode() in words and not words[0].endswith(b"mpiexec"):
            found.append(int(entry.name))
    return sorted(found)


def test_ctrl_c_under_mpiexec_checkpoints_and_the_run_resumes_bit_for_bit(
    one_process: tuple[Path, Path], tmp_path: Path
) -> None:
    # Ctrl-C in a terminal reaches the launcher, which passes it to every rank (MPICH starts each in a session of its
    # own): the followers leave it to rank 0, which stops within a second, every rank still stepping, writes the
    # checkpoint and exits 130; resumed in one process, the run ends where the uninterrupted run ends, bit for bit.
    # The signal goes after the second frame of six (the series file is rewritten at each).
    scene, reference = one_process
    out = tmp_path / "out"
    command = [*_mpiexec(2), sys.executable, "-m", "warpdem", str(scene), "--out", str(out), "--quiet"]
    launcher = _started_past_two_frames(command, out / "channel_pour_series.csv")
    os.killpg(launcher.pid, signal.SIGINT)
    _, err = launcher.communicate(timeout=300)
    assert launcher.returncode == 130, err[-3000:]
    (checkpoint,) = (out / "checkpoints").glob("*.h5")
    with h5py.File(checkpoint) as f:
        assert 0.0 < f["state"]["time"][0] < 0.12  # mid-run
    _run(scene, out, 1, "--restart", str(checkpoint))
    _assert_same_run(reference, out, "interrupted on 2 ranks, resumed in one process")


def test_a_rank_that_dies_ends_every_rank(one_process: tuple[Path, Path], tmp_path: Path) -> None:
    # A rank killed mid-run (SIGKILL: it can say nothing; rank 0 or the follower, whichever has the larger pid) must
    # not leave the other waiting in the next exchange: the launcher sees it die, ends the other and says which process
    # died; nothing is left running.
    scene, _ = one_process
    out = tmp_path / "out"
    command = [*_mpiexec(2), sys.executable, "-m", "warpdem", str(scene), "--out", str(out), "--quiet"]
    launcher = _started_past_two_frames(command, out / "channel_pour_series.csv")
    ranks = _ranks_of(out)
    assert len(ranks) == 2, ranks
    os.kill(ranks[1], signal.SIGKILL)
    stdout, _ = launcher.communicate(timeout=120)
    assert launcher.returncode != 0
    assert "BAD TERMINATION" in stdout and "Killed (signal 9)" in stdout, stdout[-2000:]
    time.sleep(0.5)
    assert _ranks_of(out) == []


def test_a_bonded_beam_breaking_matches_one_process_bit_for_bit(tmp_path: Path) -> None:
    # The default scene to 12 ms: 1 703 spheres, 8 381 bonds, the boulder lands at 6.7 ms and breaks bonds on both
    # sides of the cut; the big support spheres (r = 5 cm) make the halo a quarter of the beam. Bonds travel with their
    # lower sphere's owner, break alike on every rank that holds them, and are compacted at the same chunk ends.
    for ranks in (1, 2):
        done = subprocess.run(
            [
                *(_mpiexec(ranks) if ranks > 1 else []),
                sys.executable,
                "-m",
                "warpdem",
                "--end-time",
                "0.012",
                "--out",
                str(tmp_path / f"out{ranks}"),
            ],
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert done.returncode == 0, done.stderr[-3000:]
    broken = _final_spheres(tmp_path / "out1")["bonds_broken_total"]
    assert broken[0] > 100  # the comparison covers broken bonds
    _assert_same_run(tmp_path / "out1", tmp_path / "out2", "the bonded beam on 2 ranks", stem="default_beam_impact")


def test_a_scene_of_spheres_and_tets_is_refused_on_ranks_with_what_it_has(tmp_path: Path) -> None:
    # Spheres and tets together are not decomposed yet: every rank stops before stepping with rank 0's message naming
    # the scene and what it has; nothing is written.
    scene = ROOT / "scenes" / "boulder_impact.toml"
    done = subprocess.run(
        [*_mpiexec(2), sys.executable, "-m", "warpdem", str(scene), "--out", str(tmp_path / "out")],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode != 0
    assert "boulder_impact.toml: this scene cannot run on 2 ranks yet" in done.stderr, done.stderr
    assert "spheres and tets together" in done.stderr, done.stderr
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").rglob("*.usd*"))


# ----------------------------------------------------------------------------------------------------------------
# Tets, joints, loads and boundaries (warpdem.parallel.continuum)

SHEARED_JOINT = """
name = "sheared_joint"
[run]
end_time = 0.003
output_rate = 2000.0
[gravity]
vector = [0.0, 0.0, -9.81]
[materials.rock]
density = 2650.0
youngs_modulus = 5.0e9
poisson_ratio = 0.25
[joints]
friction = 0.5
cohesion = 1.0e5
tensile_strength = 5.0e4
[mesh]
kind = "geology"
lo = [0.0, 0.0, 0.0]
hi = [14.0, 1.0, 2.0]
material = "rock"
h = 0.5
[[mesh.joint_sets]]
name = "bed"
dip = 0.0
dip_direction = 0.0
spacing = 10.0
offset = 1.0
[[loads]]
kind = "velocity"
region = { box = { lo = [-1.0, -1.0, 1.9], hi = [15.0, 2.0, 3.0] } }
velocity = [60.0, 0.0, 0.0]
[[boundaries]]
faces = "z-"
kind = "fixed"
"""
"""A 14 m rock beam on a fixed base, cut at mid-height by a bonded joint, its top pushed along at 60 m/s: the upper
half slides on the joint, the elements fail, the node–face springs take over with friction; 402 steps, the top nodes
move 0.18 m, past the margin (0.125 m): the items are decomposed again mid-run."""

JOINTED_BLAST = """
name = "jointed_blast"
[run]
end_time = 0.0005
output_rate = 10000.0
[gravity]
vector = [0.0, 0.0, 0.0]
[materials.granite]
density = 2650.0
youngs_modulus = 5.0e10
poisson_ratio = 0.25
bulk_viscosity_linear = 0.06
bulk_viscosity_quadratic = 1.2
[joints]
friction = 0.6
cohesion = 1.0e6
tensile_strength = 5.0e5
[mesh]
kind = "geology"
lo = [0.0, 0.0, 0.0]
hi = [12.0, 2.0, 3.0]
material = "granite"
h = 0.6
[[mesh.joint_sets]]
name = "east"
dip = 60.0
dip_direction = 90.0
spacing = 3.0
offset = 1.0
[[mesh.joint_sets]]
name = "west"
dip = 45.0
dip_direction = 270.0
spacing = 3.0
offset = 0.75
[[loads]]
kind = "pressure"
faces = "z+"
history = { kind = "blast", peak = 2.0e7, rise_time = 1.0e-4, decay_time = 5.0e-4 }
[[boundaries]]
faces = "x-"
kind = "non_reflecting"
[[boundaries]]
faces = "x+"
kind = "non_reflecting"
[[boundaries]]
faces = "z-"
kind = "non_reflecting"
[[boundaries]]
faces = "y-"
kind = "roller"
[[boundaries]]
faces = "y+"
kind = "roller"
"""
"""A 12 m granite block cut by two joint sets (397 joint elements) under a blast on its top, the ends and the base
non-reflecting: the pulse crosses the joints; 525 steps."""


def _final_continuum(out: Path) -> dict[str, np.ndarray]:
    """The last checkpoint's per-node, per-tet, per-joint and per-loaded-face arrays over their live items (rows of
    slots whole, a candidate list over its live slots), and the joints' failure count."""
    last = sorted((out / "checkpoints").glob("*.h5"))[-1]
    with h5py.File(last) as f:
        state = f["state"]
        per_item = {"node": "node_u", "tet": "tet_active", "joint": "joint_broken"}
        live = {kind: int(state[f"{kind}_count"][0]) for kind in per_item}
        capacity = {kind: len(state[name]) for kind, name in per_item.items()}
        found = {}
        for name, data in state.items():
            kind = name.split("_")[0]
            if name.startswith("load_face_"):
                found[name] = data[()]
            elif kind in live and capacity[kind] and len(data) % capacity[kind] == 0 and name != "node_face_index":
                per = len(data) // capacity[kind]
                found[name] = data[()].reshape(capacity[kind], per, *data.shape[1:])[: live[kind]]
        k = len(state["node_face_index"]) // len(state["node_face_count"])
        count = state["node_face_count"][: live["node"]]
        used = np.arange(k)[None, :] < count[:, None]
        found["node_face_index"] = state["node_face_index"][()].reshape(-1, k)[: live["node"]][used]
        found["joints_broken_total"] = state["joints_broken_total"][()]
        found["time"] = state["time"][()]
    return found


def _assert_same_continuum(a: Path, b: Path, what: str, stem: str) -> None:
    series_a, series_b = (p / f"{stem}_series.csv" for p in (a, b))
    assert series_a.read_text() == series_b.read_text(), f"{what}: the time series differ"
    fa, fb = _final_continuum(a), _final_continuum(b)
    assert fa.keys() == fb.keys()
    for name in fa:
        assert np.array_equal(fa[name], fb[name]), f"{what}: {name} differs"


@pytest.fixture(scope="module", params=["sheared_joint", "jointed_blast"])
def continuum_run(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A jointed scene of tets and its one-process run."""
    root = tmp_path_factory.mktemp(request.param)
    scene = root / f"{request.param}.toml"
    scene.write_text({"sheared_joint": SHEARED_JOINT, "jointed_blast": JOINTED_BLAST}[request.param])
    _run(scene, root / "one", 1)
    return scene, root / "one"


@pytest.mark.parametrize("ranks", [2, 4])
def test_tets_with_joints_and_loads_match_one_process_bit_for_bit(
    continuum_run: tuple[Path, Path], tmp_path: Path, ranks: int
) -> None:
    # The series (every energy line: tets, joints, contacts, loads, dashpots) and every node's, tet's, joint
    # element's and loaded face's state at the end, equal to one process's. The sheared beam's joint elements fail
    # and its items are decomposed again mid-run (its top moves past the margin); the blast's pulse crosses the cuts.
    scene, reference = continuum_run
    done = _run(scene, tmp_path / "out", ranks)
    _assert_same_continuum(reference, tmp_path / "out", f"{scene.stem} on {ranks} ranks", scene.stem)
    # The blast's block (12 m, ghosts within 5.0 m of a slab) leaves one rank 94 % of the nodes: rank 0 says the
    # ranks gain little; the beam's (14 m, 4.5 m) leaves it 81 %, under the 90 % it warns at.
    assert ("too short along its longest side" in done.stderr) == (scene.stem == "jointed_blast"), done.stderr
    # The comparison covers failed joint elements, and on the beam items decomposed again mid-run.
    assert _final_continuum(reference)["joints_broken_total"][0] > 0
    if scene.stem == "sheared_joint":
        assert _summary(tmp_path / "out")["migrations"] > 0


def test_a_continuum_checkpoint_from_2_ranks_resumes_on_4_and_on_1(tmp_path: Path) -> None:
    scene = tmp_path / "sheared_joint.toml"
    scene.write_text(SHEARED_JOINT)
    _run(scene, tmp_path / "whole", 1)
    _run(scene, tmp_path / "half", 2, "--end-time", "0.0015")
    for then in (4, 1):
        out = tmp_path / f"then{then}"
        shutil.copytree(tmp_path / "half", out)  # the half run once, resumed twice
        (checkpoint,) = (out / "checkpoints").glob("*.h5")
        _run(scene, out, then, "--restart", str(checkpoint))
        _assert_same_continuum(tmp_path / "whole", out, f"2 ranks then {then}", "sheared_joint")


def test_slabs_give_every_centre_one_owner_that_holds_it() -> None:
    rng = np.random.default_rng(5)
    q = rng.uniform([0.0, 0.0, 0.0], [3.0, 1.0, 1.0], size=(1000, 3))
    for ranks in (2, 3, 4):
        slabs = Slabs.balanced(q, np.ones(len(q)), ranks, halo=0.05)
        assert slabs.axis == 0  # the longest extent
        owner = slabs.owner(q)
        held = np.stack([slabs.holds(q, r) for r in range(ranks)], axis=1)
        assert held[np.arange(len(q)), owner].all()
        # Equal shares: each slab's count within one sphere of len/ranks (the cut lies between two centres).
        counts = np.bincount(owner, minlength=ranks)
        assert np.all(np.abs(counts - len(q) / ranks) <= 1.0), counts
        # A ghost is within the halo of the slab that holds it, measured along the axis.
        x = q[:, 0]
        edges = (-np.inf, *slabs.cuts, np.inf)
        for r in range(ranks):
            ghosts = held[:, r] & (owner != r)
            gap = np.maximum(edges[r] - x[ghosts], x[ghosts] - edges[r + 1])
            assert np.all(gap < slabs.halo)


def test_rows_round_trip_through_a_subdomain(device: str) -> None:
    from warpdem.build.scene_build import build_scene
    from warpdem.parallel.rows import PARTNER, bonds_of, rows_of, subdomain
    from warpdem.scene import load_scene
    from warpdem.simulation import Simulation

    scene_path = ROOT / "scenes" / "granular_pour.toml"
    model, state = build_scene(load_scene(scene_path), device)
    sim = Simulation(model, state)
    sim.advance(400)  # lists with partners and tangential springs
    m, s = sim.model, sim.state
    n = int(s.particle_count.numpy()[0])
    whole = np.arange(n)
    rows = rows_of(m, s, whole, whole)
    # Half of the spheres, as a subdomain: its slots keep exactly the partners among that half, in their order.
    half = rows.take(rows.fields["particle_q"][:, 0] < np.median(rows.fields["particle_q"][:, 0]))
    no_bonds = bonds_of(s, whole)
    local_model, local_state = subdomain(m, s, half, no_bonds, m.max_neighbors, len(half) + 7, 0)
    back = rows_of(local_model, local_state, half.gid, np.arange(len(half)))
    assert np.array_equal(back.gid, half.gid)
    for name, a in half.fields.items():
        if name in (PARTNER, "nbr_count", "nbr_shear"):
            continue
        assert np.array_equal(back.fields[name], a), name
    for i in range(len(half)):
        mine = half.fields[PARTNER][i][: half.fields["nbr_count"][i]]
        kept = np.isin(mine, half.gid)
        assert np.array_equal(back.fields[PARTNER][i][: back.fields["nbr_count"][i]], mine[kept])
        shear = half.fields["nbr_shear"][i][: half.fields["nbr_count"][i]][kept]
        assert np.array_equal(back.fields["nbr_shear"][i][: back.fields["nbr_count"][i]], shear)
    assert int(local_state.particle_count.numpy()[0]) == len(half)


@pytest.mark.parametrize("precision", [np.float64, np.float32])
@pytest.mark.parametrize("staged", [False, True])
def test_a_channel_carries_each_ghost_its_owners_fields_exactly(device: str, precision: type, staged: bool) -> None:
    # Oracle: the halo is a copy. Rank 0 sends rows of its items 1, 4, 6 (three vec3 fields each) to rank 1, whose
    # ghosts 0, 2, 5 receive them; the MPI message is played by copying the outbox's block into the inbox's. Every
    # ghost then holds its owner's values bit for bit (spheres' float64 fields in float64 rows, nodes' float32 in
    # float32), nothing else changes, and a staged channel's blocks are host copies, not the device buffers (on a GPU
    # the only way).
    from types import SimpleNamespace

    import warp as wp

    from warpdem.parallel.ranked import Channel

    vec = wp.vec3d if precision == np.float64 else wp.vec3f
    rng = np.random.default_rng(7)
    names = ("a", "b", "c")
    owner = SimpleNamespace(**{n: wp.array(rng.normal(size=(8, 3)), dtype=vec, device=device) for n in names})
    ghost = SimpleNamespace(**{n: wp.zeros(8, dtype=vec, device=device) for n in names})
    sent, received = np.array([1, 4, 6]), np.array([0, 2, 5])
    if not staged and device != "cpu":
        # MPI reads host memory, and a GPU buffer's numpy() is a copy: an unstaged channel there is refused.
        with pytest.raises(ValueError, match="must be staged"):
            Channel(names, precision, {1: sent}, {}, tag=1, device=device, staged=staged)
        return
    out = Channel(names, precision, {1: sent}, {}, tag=1, device=device, staged=staged)
    into = Channel(names, precision, {}, {0: received}, tag=1, device=device, staged=staged)
    # Twice, the second time into and from new arrays (a regrowth replaces the state's): the launches recorded for
    # the first arrays must not write the old ones.
    for _ in range(2):
        out.pack(owner)
        wp.synchronize_device(device)  # what the rank does before its sends
        np.copyto(into.inbox[0], out.outbox[1])
        into.unpack(ghost)
        for n in names:
            expected = np.zeros((8, 3), dtype=precision)
            expected[received] = getattr(owner, n).numpy()[sent]
            assert np.array_equal(getattr(ghost, n).numpy(), expected), n
        owner = SimpleNamespace(**{n: wp.array(rng.normal(size=(8, 3)), dtype=vec, device=device) for n in names})
        ghost = SimpleNamespace(**{n: wp.zeros(8, dtype=vec, device=device) for n in names})
    assert out.bytes_sent == 3 * 9 * np.dtype(precision).itemsize
    assert np.shares_memory(out.outbox[1], out._send_rows.numpy()) == (not staged and device == "cpu")


def test_ranks_asking_for_cuda_take_their_nodes_gpus_in_turn() -> None:
    # Invariant: rank r of a node of g GPUs takes GPU r mod g, so each GPU serves ceil or floor of ranks/g ranks; a
    # node without one leaves "cuda", which fails as one process does.
    from warpdem.parallel.comm import local_gpu

    for gpus in (1, 2, 4):
        taken = [local_gpu(r, gpus) for r in range(6)]
        assert taken[:gpus] == [f"cuda:{g}" for g in range(gpus)]
        counts = [taken.count(f"cuda:{g}") for g in range(gpus)]
        assert max(counts) - min(counts) <= 1 and sum(counts) == 6
    assert local_gpu(3, 0) == "cuda"
