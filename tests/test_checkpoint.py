"""Tests for warpdem.io.checkpoint: bit-exact round trips, atomic replacement and readable errors."""

from __future__ import annotations

import os
import pathlib

import h5py
import numpy as np
import pytest

from warpdem.io import checkpoint
from warpdem.io.checkpoint import (
    FORMAT_NAME,
    FORMAT_VERSION,
    CheckpointError,
    checkpoint_name,
    latest_checkpoint,
    read_checkpoint,
    write_checkpoint,
)


def sample_arrays() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(7)
    f32 = rng.normal(size=(5, 3)).astype(np.float32)
    f32[0, 0] = np.nan  # NaN payload and signed zero must survive bit-exactly
    f32[0, 1] = -0.0
    f64 = rng.normal(size=(4, 2, 3))
    f64[1, 1, 1] = np.inf
    return {
        "state/particle_q": f32,
        "state/deep/nested/f64": f64,
        "model/tet_indices": rng.integers(-(2**31), 2**31 - 1, size=(6, 4), dtype=np.int32),
        "model/flags": rng.integers(0, 256, size=7, dtype=np.uint8),
        "state/active": rng.integers(0, 2, size=9).astype(bool),
        "counters/step": np.array(123456789012, dtype=np.int64),  # 0-d
        "time": np.array(0.25, dtype=np.float64),  # 0-d at the root
        "state/empty": np.zeros((0, 3), dtype=np.float32),
        "state/empty_int": np.zeros(0, dtype=np.int64),
        "rng/state": rng.integers(0, 2**63, size=4, dtype=np.uint64),
        "misc/f16": rng.normal(size=3).astype(np.float16),
        "misc/c64": (rng.normal(size=2) + 1j * rng.normal(size=2)).astype(np.complex64),
        "misc/fortran": np.asfortranarray(rng.normal(size=(3, 4))),
    }


SAMPLE_ATTRS = {
    "step": 42,
    "time": 1.25e-3,
    "dt": 1.0e-7,
    "converged": True,
    "captured": False,
    "scene": "scenes/slab.toml",
    "unicode": "Grès — ε",
    "config": {"contact": {"kn": 1.0e9, "laws": ["hertz", "coulomb"]}, "seed": 3, "none": None},
    "sizes": [1, 2, 3],
    "nothing": None,
    "big": 2**70,
}


def assert_bit_identical(actual: np.ndarray, expected: np.ndarray) -> None:
    assert isinstance(actual, np.ndarray)
    assert actual.dtype == expected.dtype
    assert actual.shape == expected.shape
    assert np.ascontiguousarray(actual).tobytes() == np.ascontiguousarray(expected).tobytes()


def test_round_trip_bit_exact(tmp_path: pathlib.Path) -> None:
    arrays = sample_arrays()
    path = write_checkpoint(tmp_path / "a" / "b" / checkpoint_name(42), arrays, SAMPLE_ATTRS)
    assert path == tmp_path / "a" / "b" / "checkpoint_0000000042.h5"
    assert path.is_file()
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]

    got_arrays, got_attrs = read_checkpoint(path)
    assert set(got_arrays) == set(arrays)
    for name, expected in arrays.items():
        assert_bit_identical(got_arrays[name], expected)

    assert got_attrs == SAMPLE_ATTRS
    for name, value in SAMPLE_ATTRS.items():
        assert type(got_attrs[name]) is type(value), name

    with h5py.File(path, "r") as f:
        assert f.attrs["warpdem_format"] == FORMAT_NAME
        assert f.attrs["warpdem_format_version"] == FORMAT_VERSION
        assert isinstance(f["state/deep/nested"], h5py.Group)


def test_numpy_scalar_attrs(tmp_path: pathlib.Path) -> None:
    attrs = {"step": np.int64(5), "time": np.float32(0.5), "flag": np.bool_(True)}
    _, got = read_checkpoint(write_checkpoint(tmp_path / "c.h5", {}, attrs))
    assert got == {"step": 5, "time": 0.5, "flag": True}
    assert type(got["step"]) is int and type(got["time"]) is float and type(got["flag"]) is bool


def test_overwrite_replaces(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "c.h5"
    write_checkpoint(path, {"x": np.arange(3)}, {"step": 1})
    write_checkpoint(path, {"y": np.arange(4.0)}, {"step": 2})
    arrays, attrs = read_checkpoint(path)
    assert list(arrays) == ["y"]
    assert attrs == {"step": 2}


def test_failed_write_keeps_previous(tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "ckpt" / checkpoint_name(10)
    previous = write_checkpoint(path, sample_arrays(), SAMPLE_ATTRS)
    before = previous.read_bytes()

    original = h5py.Group.create_dataset
    calls = 0

    def failing_create_dataset(self: h5py.Group, name: str, *args: object, **kwargs: object) -> h5py.Dataset:
        nonlocal calls
        calls += 1
        if calls > 1:
            raise OSError("disk full (simulated)")
        return original(self, name, *args, **kwargs)

    monkeypatch.setattr(h5py.Group, "create_dataset", failing_create_dataset)
    with pytest.raises(OSError, match="simulated"):
        write_checkpoint(path, {"a": np.ones(3), "b": np.zeros(4)}, {"step": 11})
    assert calls == 2  # the failure happened midway, after the temporary file held data
    monkeypatch.undo()

    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]
    assert path.read_bytes() == before
    arrays, attrs = read_checkpoint(path)
    assert attrs == SAMPLE_ATTRS
    for name, expected in sample_arrays().items():
        assert_bit_identical(arrays[name], expected)


def test_failed_rename_removes_temp(tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "c.h5"
    write_checkpoint(path, {"x": np.arange(3)}, {"step": 1})
    before = path.read_bytes()

    def failing_replace(src: object, dst: object) -> None:
        raise OSError("rename failed (simulated)")

    monkeypatch.setattr(checkpoint.os, "replace", failing_replace)
    with pytest.raises(OSError, match="simulated"):
        write_checkpoint(path, {"x": np.arange(5)}, {"step": 2})
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.h5"]
    assert path.read_bytes() == before


def test_invalid_input_touches_nothing(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "sub" / "c.h5"
    with pytest.raises(TypeError, match="not numeric"):
        write_checkpoint(path, {"names": np.array(["a", "b"])}, {})
    with pytest.raises(TypeError, match="not numeric"):
        write_checkpoint(path, {"objs": np.array([object()])}, {})
    with pytest.raises(TypeError, match="JSON"):
        write_checkpoint(path, {}, {"bad": {"x": object()}})
    with pytest.raises(ValueError, match="reserved"):
        write_checkpoint(path, {}, {"warpdem_format": "x"})
    with pytest.raises(ValueError, match="groups"):
        write_checkpoint(path, {"a": np.ones(1), "a/b": np.ones(1)}, {})
    with pytest.raises(ValueError, match="empty"):
        write_checkpoint(path, {"a//b": np.ones(1)}, {})
    assert not path.parent.exists()


def test_error_missing_file(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "missing.h5"
    with pytest.raises(CheckpointError, match="file not found") as info:
        read_checkpoint(path)
    assert str(path) in str(info.value)
    assert "\n" not in str(info.value)


def test_error_not_hdf5(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "text.h5"
    path.write_text("this is not HDF5\n")
    with pytest.raises(CheckpointError, match="not an HDF5 file") as info:
        read_checkpoint(path)
    assert str(path) in str(info.value)
    assert "\n" not in str(info.value)


def test_error_truncated(tmp_path: pathlib.Path) -> None:
    path = write_checkpoint(tmp_path / "c.h5", sample_arrays(), SAMPLE_ATTRS)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError) as info:
        read_checkpoint(path)
    assert str(path) in str(info.value)
    assert "\n" not in str(info.value)


def test_error_wrong_format(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f.attrs["warpdem_format"] = "someone-elses-format"
        f.attrs["warpdem_format_version"] = 1
    with pytest.raises(CheckpointError, match="not a warpdem checkpoint") as info:
        read_checkpoint(path)
    assert str(path) in str(info.value)

    with h5py.File(path, "w") as f:
        f.create_dataset("x", data=np.ones(2))
    with pytest.raises(CheckpointError, match="not a warpdem checkpoint"):
        read_checkpoint(path)


def test_error_version_too_new(tmp_path: pathlib.Path) -> None:
    path = write_checkpoint(tmp_path / "new.h5", {"x": np.ones(2)}, {})
    with h5py.File(path, "r+") as f:
        f.attrs["warpdem_format_version"] = FORMAT_VERSION + 1
    with pytest.raises(CheckpointError, match=f"version {FORMAT_VERSION + 1} is newer") as info:
        read_checkpoint(path)
    assert str(path) in str(info.value)
    assert "\n" not in str(info.value)


def test_checkpoint_name() -> None:
    assert checkpoint_name(0) == "checkpoint_0000000000.h5"
    assert checkpoint_name(1234) == "checkpoint_0000001234.h5"
    for bad in (-1, True, 1.5):
        with pytest.raises(ValueError):
            checkpoint_name(bad)  # type: ignore[arg-type]
    # A scene prefix keeps two scenes that share an output folder apart.
    assert checkpoint_name(7, "slab") == "slab_checkpoint_0000000007.h5"
    for bad_scene in ("", "a/b", "a\\b"):
        with pytest.raises(ValueError):
            checkpoint_name(7, bad_scene)


def test_latest_checkpoint(tmp_path: pathlib.Path) -> None:
    assert latest_checkpoint(tmp_path / "does-not-exist") is None
    assert latest_checkpoint(tmp_path) is None
    # Step numbers, not modification times or lexical order of unpadded names, decide.
    for step in (900, 10, 12_000_000_000, 5):
        write_checkpoint(tmp_path / checkpoint_name(step), {"x": np.ones(1)}, {"step": step})
    os.utime(tmp_path / checkpoint_name(5), (2e9, 2e9))
    (tmp_path / "checkpoint_0000000000.h5.tmp-123").write_bytes(b"")  # interrupted write
    (tmp_path / "checkpoint_99999999999.h5.bak").write_bytes(b"")
    (tmp_path / "notes.h5").write_bytes(b"")
    (tmp_path / "checkpoint_99999999999999.h5").mkdir()  # a directory is not a checkpoint
    latest = latest_checkpoint(tmp_path)
    assert latest == tmp_path / "checkpoint_12000000000.h5"
    assert read_checkpoint(latest)[1]["step"] == 12_000_000_000


def test_latest_checkpoint_of_a_scene(tmp_path: pathlib.Path) -> None:
    # Two scenes in one folder: each finds its own newest checkpoint, whatever the other's step numbers.
    for scene, steps in (("slab", (10, 30)), ("slab_b", (20, 40)), ("pour", (50,))):
        for step in steps:
            write_checkpoint(tmp_path / checkpoint_name(step, scene), {"x": np.ones(1)}, {"step": step})
    assert latest_checkpoint(tmp_path, "slab") == tmp_path / "slab_checkpoint_0000000030.h5"
    assert latest_checkpoint(tmp_path, "slab_b") == tmp_path / "slab_b_checkpoint_0000000040.h5"
    assert latest_checkpoint(tmp_path, "pour") == tmp_path / "pour_checkpoint_0000000050.h5"
    assert latest_checkpoint(tmp_path, "other") is None
    assert latest_checkpoint(tmp_path) == tmp_path / "pour_checkpoint_0000000050.h5"


def test_a_format_12_checkpoint_with_three_force_sums_resumes_bit_for_bit(tmp_path: pathlib.Path) -> None:
    """Format 13 keeps the sphere contacts' three force sums as one record per sphere (``state/contact_sums``, its
    rows the normal force, tangential force and torque sums); format 12 kept three arrays. The default scene's
    frame-1 checkpoint (its bonds load every sphere, so the sums are not zero: checked) rewritten as format 12 wrote
    it, the three arrays in place of the record, restarts (warpdem.io.restart.FIELD_MIGRATIONS) and ends at frame 2
    equal to the uninterrupted run, array by array, bit for bit (CPU: same kernels, same order of operations)."""
    from warpdem.runner import RunOptions, run_scene
    from warpdem.scene import default_scene_path, load_scene

    scene = load_scene(default_scene_path())
    period = 1.0 / scene.run.output_rate  # a checkpoint every frame: frames 1 and 2
    options = RunOptions(device="cpu", frames=2, out_dir=tmp_path / "run", checkpoint_every=period, quiet=True)
    summary = run_scene(scene, options)
    middle, end = summary.checkpoints
    end_arrays, _ = read_checkpoint(end)
    sums = read_checkpoint(middle)[0]["state/contact_sums"]
    assert sums.shape[1:] == (3, 3) and np.count_nonzero(sums) > 0
    old = tmp_path / "old" / middle.name
    old.parent.mkdir()
    old.write_bytes(middle.read_bytes())
    with h5py.File(old, "r+") as f:
        del f["state/contact_sums"]
        for row, name in enumerate(("contact_f_normal", "contact_f_tangential", "contact_t_tangential")):
            f[f"state/{name}"] = sums[:, row]
        f.attrs["warpdem_format_version"] = 12
    again = run_scene(scene, RunOptions(device="cpu", frames=2, out_dir=tmp_path / "again", quiet=True, restart=old))
    arrays, _ = read_checkpoint(again.checkpoints[-1])
    assert arrays.keys() == end_arrays.keys()
    for name, expected in end_arrays.items():
        np.testing.assert_array_equal(arrays[name], expected, err_msg=name)
