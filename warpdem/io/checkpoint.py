"""HDF5 checkpoints of the complete simulation state.

A checkpoint is one HDF5 file holding

- every state array as a dataset, bit-exact (same dtype, same shape, 0-d and empty arrays included); a key
  such as ``"state/particle_q"`` becomes dataset ``particle_q`` in group ``state``;
- scalar metadata (step, time, counters, RNG seed, configuration) as root attributes: ``int``, ``float``,
  ``bool`` and ``str`` natively, anything else JSON-serialisable (dicts, lists, ``None``) as a JSON string under
  the attribute name ``__json__:<name>``, decoded back transparently;
- the root attributes ``warpdem_format`` (= :data:`FORMAT_NAME`) and ``warpdem_format_version``
  (= :data:`FORMAT_VERSION`), checked on read.

Versions: 1, the layout above; 2, the same layout, with a promise: a version-2 file holds every State and Model field
its writer had, including all those added since version 1 (warpdem.io.restart.FIELD_MIGRATIONS lists them). A version-1
file may lack some of them: a restart fills each one it lacks with a fresh model's value where that is exactly what
the run would hold (an energy line of a pass that never ran, the contact books of a run with no contact), and refuses
otherwise, naming the file, the field and why (warpdem.io.restart.restore_checkpoint). A field added later bumps the
version again and adds its rows to that table, with the version it appeared in: 3 added the pressure loads' forces
kept per node (``node_f_load``) and the rigid bodies' drift scratch (``body_q_before``, ``body_omega_ahead``); 4 holds
node_springs node–face springs per node (``node_face_spring``, ``_offset``, ``_shear`` rows, and the model scalar
``node_springs``) where older files hold one (warpdem.io.restart.FIELD_RESHAPES puts it into slot 0); 5 the velocities'
kick carries (``particle_qd_carry``, ``node_qd_carry``: zero in an older run, whose kicks carried nothing); 6 the
coupling springs' rest gaps (``coupling_rest``: zero in an older run, whose springs had none); 7 the sphere–face
contacts' line and the sums of their forces kept for its half ahead (``sphere_face_f``, ``_t``, ``_dissipated``,
``node_f_sphere_face``, ``node_energy_sphere_face``: an older run booked those contacts on the sphere and FEM contact
lines); 8 the bonds' springs' trapezoid line (``energy_bond_trapezoid``: zero in an older run, which booked it on the
damping and friction lines); 9 the cohesive elements' trapezoid line (``node_energy_cohesive_trapezoid``: zero in an
older run, which booked it on the cohesive line); 10 the blended overlap band (the model scalars ``band_width``,
``band_penalty`` and the array ``tet_band_volume``: an older run had no band, so a band model restarts from it only
where no tet had converted); 11 the pressure loads' hand-over to the spheres of converted tets
(``loads/pressure_<kind>_handed_area``, ``state/load_face_force``, ``state/load_face_work``: zero in an older run,
which dropped the faces of converted tets without a hand-over, so its dropped faces stay dropped and the books close
from zero); 12 the impulse each pressure face delivered (``state/load_face_impulse``: a report's counter, counted
from the restart of an older run); 13 the sphere contacts' three force sums as one record per sphere
(``state/contact_sums``, made from an older file's ``contact_f_normal``, ``contact_f_tangential`` and
``contact_t_tangential``, the same values); 14 the cohesive elements' sub-steps (the model scalar
``cohesive_substeps``, ``state/node_f_fast``, ``state/node_substepped`` and ``state/node_energy_substep``: 1 and zero
in an older run, which took one step for every force).

Files are written to ``<name>.tmp-<pid>`` in the target directory and moved over the final name with
``os.replace``, so a crash or an error mid-write never damages the previous checkpoint.
"""

from __future__ import annotations

import json
import os
import pathlib
import re
from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "CheckpointError",
    "checkpoint_name",
    "latest_checkpoint",
    "read_checkpoint",
    "read_checkpoint_attrs",
    "read_checkpoint_version",
    "remove_stale_temporaries",
    "write_checkpoint",
]

FORMAT_NAME = "warpdem-checkpoint"
"""Value of the root attribute ``warpdem_format`` identifying a warpdem checkpoint."""

FORMAT_VERSION = 14
"""Newest checkpoint format this module writes and reads (module docstring, "Versions"); bump when the layout changes
or fields are added, and list what older files may lack in warpdem.io.restart.FIELD_MIGRATIONS."""

_FORMAT_NAME_ATTR = "warpdem_format"
_FORMAT_VERSION_ATTR = "warpdem_format_version"
_JSON_PREFIX = "__json__:"
_NAME_PATTERN = re.compile(r"(?:(.+)_)?checkpoint_(\d+)\.h5")
_TEMP_PATTERN = re.compile(r".+\.h5\.tmp-(\d+)")

# Numpy kinds that HDF5 stores natively and h5py reads back with the same dtype: bool, signed, unsigned,
# floating, complex.
_NUMERIC_KINDS = "biufc"


class CheckpointError(Exception):
    """A checkpoint file cannot be read: missing, not HDF5, corrupt, or not a supported warpdem checkpoint."""


def checkpoint_name(step: int, scene: str | None = None) -> str:
    """File name of the checkpoint taken at a step.

    Args:
        step: Simulation step number, >= 0.
        scene: Scene name, the file's prefix, so that scenes sharing an output folder never overwrite each other's
            checkpoints; None for no prefix.

    Returns:
        ``<scene>_checkpoint_<step:010d>.h5`` (``checkpoint_<step:010d>.h5`` without a scene); zero padding makes
        names sort in step order.

    Raises:
        ValueError: If ``step`` is negative or not an integer, or ``scene`` is empty or holds a path separator.
    """
    if isinstance(step, bool) or not isinstance(step, int | np.integer) or step < 0:
        raise ValueError(f"checkpoint step must be a non-negative integer, got {step!r}")
    if scene is None:
        return f"checkpoint_{int(step):010d}.h5"
    if not scene or "/" in scene or "\\" in scene:
        raise ValueError(f"checkpoint scene name must be non-empty without path separators, got {scene!r}")
    return f"{scene}_checkpoint_{int(step):010d}.h5"


def latest_checkpoint(directory: str | os.PathLike, scene: str | None = None) -> pathlib.Path | None:
    """Finds the checkpoint with the highest step number in a directory.

    Only files named like :func:`checkpoint_name` count; temporary files of an interrupted write do not.

    Args:
        directory: Directory to search (not recursive).
        scene: Only this scene's checkpoints (``<scene>_checkpoint_<step>.h5``); None: any checkpoint.

    Returns:
        Path of the newest checkpoint, or ``None`` if the directory is missing or holds none.
    """
    root = pathlib.Path(directory)
    if not root.is_dir():
        return None
    best: tuple[int, pathlib.Path] | None = None
    for entry in root.iterdir():
        match = _NAME_PATTERN.fullmatch(entry.name)
        if match is None or not entry.is_file() or (scene is not None and match.group(1) != scene):
            continue
        step = int(match.group(2))
        if best is None or step > best[0]:
            best = (step, entry)
    return None if best is None else best[1]


def write_checkpoint(
    path: str | os.PathLike, arrays: Mapping[str, np.ndarray], attrs: Mapping[str, Any]
) -> pathlib.Path:
    """Writes a checkpoint atomically.

    Args:
        path: Final file name (conventionally ``<dir>/`` + :func:`checkpoint_name`). Parent directories are
            created; an existing file is replaced only once the new one is complete.
        arrays: Dataset name -> numeric array (bool, int, uint, float, complex; any shape, including 0-d and
            empty). ``"/"`` in a name creates HDF5 groups. Stored bit-exactly with the same dtype and shape.
        attrs: Attribute name -> ``int``, ``float``, ``bool``, ``str``, or a JSON-serialisable value (dict, list,
            ``None``), which is stored as JSON and decoded on read (tuples come back as lists). Numpy scalars are
            stored as the matching Python scalar.

    Returns:
        The final path.

    Raises:
        ValueError: If a name is empty, reserved, or a dataset name is also used as a group.
        TypeError: If an array is not numeric or an attribute value cannot be stored.
        OSError: If writing fails; the temporary file is removed and any previous file at ``path`` is untouched.
    """
    import h5py

    final_path = pathlib.Path(path)
    # Validate and encode everything first, so bad input fails before the disk is touched.
    datasets = _prepare_arrays(arrays)
    encoded_attrs = _encode_attrs(attrs)

    final_path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(final_path.parent)
    tmp_path = final_path.with_name(f"{final_path.name}.tmp-{os.getpid()}")
    try:
        with h5py.File(tmp_path, "w") as f:
            f.attrs[_FORMAT_NAME_ATTR] = FORMAT_NAME
            f.attrs[_FORMAT_VERSION_ATTR] = np.int64(FORMAT_VERSION)
            for name, value in encoded_attrs.items():
                f.attrs[name] = value
            for name, array in datasets.items():
                f.create_dataset(name, data=array)
        # The rename must not reach the disk before the data does, or a power loss could leave an empty file
        # under the final name.
        with open(tmp_path, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp_path, final_path)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise
    fsync_path(final_path.parent)
    return final_path


def remove_stale_temporaries(directory: str | os.PathLike) -> list[pathlib.Path]:
    """Deletes the temporary files (``<name>.h5.tmp-<pid>``) that writers killed mid-write left in a directory.

    A temporary file belongs to its writer while that process lives; only files of processes that no longer exist
    are removed (POSIX; elsewhere nothing is removed, as liveness cannot be asked without side effects).

    Args:
        directory: Checkpoint directory (not searched recursively).

    Returns:
        The files removed.
    """
    root = pathlib.Path(directory)
    if os.name != "posix" or not root.is_dir():
        return []
    removed = []
    for entry in root.iterdir():
        match = _TEMP_PATTERN.fullmatch(entry.name)
        if match is None or not entry.is_file():
            continue
        pid = int(match.group(1))
        if pid == os.getpid() or _process_alive(pid):
            continue
        try:
            entry.unlink()
        except OSError:
            continue  # removed meanwhile, or not ours to remove
        removed.append(entry)
    return removed


def _process_alive(pid: int) -> bool:
    """Whether a process of this id exists (POSIX: signal 0 checks without sending anything)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, OSError):
        return True  # someone else's process, or an id the system cannot check: keep the file
    return True


def read_checkpoint(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Reads a checkpoint written by :func:`write_checkpoint`.

    Args:
        path: Checkpoint file.

    Returns:
        ``(arrays, attrs)``: dataset name (``"group/name"``, no leading slash) -> array with the stored dtype
        and shape, and attribute name -> decoded value (format attributes excluded).

    Raises:
        CheckpointError: With a one-line message naming the file, if it is missing, not an HDF5 file, corrupt,
            not a warpdem checkpoint, or written by a newer format version.
    """
    arrays, attrs, _ = read_checkpoint_version(path)
    return arrays, attrs


def read_checkpoint_version(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict[str, Any], int]:
    """:func:`read_checkpoint`, and the file's format version (1 .. :data:`FORMAT_VERSION`: what it may lack).

    Raises:
        CheckpointError: as :func:`read_checkpoint`.
    """
    import h5py

    file_path = _hdf5_file(path)
    try:
        with h5py.File(file_path, "r") as f:
            version = _check_format(file_path, f.attrs)
            attrs = _decode_attrs(file_path, f.attrs)
            arrays: dict[str, np.ndarray] = {}

            def collect(name: str, node: Any) -> None:
                if isinstance(node, h5py.Dataset):
                    # [()] gives a numpy scalar for 0-d datasets; asarray keeps dtype and shape ().
                    arrays[name] = np.asarray(node[()])

            f.visititems(collect)
    except CheckpointError:
        raise
    except (OSError, KeyError, ValueError, TypeError) as exc:
        raise CheckpointError(f"checkpoint {str(file_path)!r}: corrupt HDF5 file ({_one_line(exc)})") from exc
    return arrays, attrs, version


def read_checkpoint_attrs(path: str | os.PathLike) -> dict[str, Any]:
    """The attributes of a checkpoint alone (step, time, frame, what the run stored), without reading its arrays.

    Raises:
        CheckpointError: as :func:`read_checkpoint`.
    """
    import h5py

    file_path = _hdf5_file(path)
    try:
        with h5py.File(file_path, "r") as f:
            _check_format(file_path, f.attrs)
            return _decode_attrs(file_path, f.attrs)
    except CheckpointError:
        raise
    except (OSError, KeyError, ValueError, TypeError) as exc:
        raise CheckpointError(f"checkpoint {str(file_path)!r}: corrupt HDF5 file ({_one_line(exc)})") from exc


def _hdf5_file(path: str | os.PathLike) -> pathlib.Path:
    """The path of an existing HDF5 file.

    Raises:
        CheckpointError: the file is missing, not a regular file, unreadable or not HDF5.
    """
    import h5py

    file_path = pathlib.Path(path)
    if not file_path.exists():
        raise CheckpointError(f"checkpoint {str(file_path)!r}: file not found")
    if not file_path.is_file():
        raise CheckpointError(f"checkpoint {str(file_path)!r}: not a regular file")
    try:
        is_hdf5 = h5py.is_hdf5(file_path)
    except OSError as exc:
        raise CheckpointError(f"checkpoint {str(file_path)!r}: cannot read file ({_one_line(exc)})") from exc
    if not is_hdf5:
        raise CheckpointError(f"checkpoint {str(file_path)!r}: not an HDF5 file (corrupt or wrong file type)")
    return file_path


def _prepare_arrays(arrays: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Checks dataset names and dtypes.

    Args:
        arrays: Dataset name -> array-like.

    Returns:
        Normalised name (no leading or trailing slash) -> numpy array (not copied when already an array).

    Raises:
        ValueError: On an empty name or a name that is both a dataset and a group.
        TypeError: On a non-string name or a non-numeric array.
    """
    out: dict[str, np.ndarray] = {}
    for key, value in arrays.items():
        if not isinstance(key, str):
            raise TypeError(f"checkpoint array name must be a str, got {key!r}")
        name = key.strip("/")
        parts = name.split("/")
        if not name or any(part in ("", ".", "..") for part in parts):
            raise ValueError(f"checkpoint array name {key!r} is empty or has an empty or relative path component")
        if name in out:
            raise ValueError(f"checkpoint array name {key!r} given twice")
        array = np.asarray(value)
        if array.dtype.kind not in _NUMERIC_KINDS or array.dtype.fields is not None:
            raise TypeError(f"checkpoint array {key!r}: dtype {array.dtype} is not numeric")
        out[name] = array
    groups = {"/".join(name.split("/")[:i]) for name in out for i in range(1, name.count("/") + 1)}
    clashes = sorted(groups.intersection(out))
    if clashes:
        raise ValueError(f"checkpoint array names {clashes} are also used as groups of other arrays")
    return out


def _encode_attrs(attrs: Mapping[str, Any]) -> dict[str, Any]:
    """Converts attribute values to what HDF5 stores natively, JSON-encoding the rest.

    Args:
        attrs: Attribute name -> value.

    Returns:
        Stored attribute name -> HDF5-storable scalar.

    Raises:
        ValueError: On an empty or reserved name.
        TypeError: On a value that is neither a supported scalar nor JSON-serialisable.
    """
    out: dict[str, Any] = {}
    for name, value in attrs.items():
        if not isinstance(name, str) or not name:
            raise ValueError(f"checkpoint attribute name must be a non-empty str, got {name!r}")
        if name in (_FORMAT_NAME_ATTR, _FORMAT_VERSION_ATTR) or name.startswith(_JSON_PREFIX):
            raise ValueError(f"checkpoint attribute name {name!r} is reserved")
        if isinstance(value, np.generic) and value.dtype.kind in "biuf":
            value = value.item()
        if isinstance(value, bool):
            out[name] = np.bool_(value)
        elif isinstance(value, int) and -(2**63) <= value < 2**63:
            out[name] = np.int64(value)
        elif isinstance(value, float):
            out[name] = np.float64(value)
        elif isinstance(value, str):
            out[name] = value
        else:
            try:
                out[_JSON_PREFIX + name] = json.dumps(value)
            except (TypeError, ValueError) as exc:
                raise TypeError(
                    f"checkpoint attribute {name!r}: {type(value).__name__} is not int, float, bool, str "
                    f"or JSON-serialisable ({exc})"
                ) from exc
    return out


def _decode_attrs(file_path: pathlib.Path, stored: Any) -> dict[str, Any]:
    """Reverses :func:`_encode_attrs`.

    Args:
        file_path: Checkpoint file, for error messages.
        stored: The root ``h5py.AttributeManager``.

    Returns:
        Attribute name -> Python value.

    Raises:
        CheckpointError: If a JSON attribute does not decode.
    """
    out: dict[str, Any] = {}
    for name, value in stored.items():
        if name in (_FORMAT_NAME_ATTR, _FORMAT_VERSION_ATTR):
            continue
        if isinstance(value, bytes):
            value = value.decode("utf-8")
        if name.startswith(_JSON_PREFIX):
            try:
                out[name[len(_JSON_PREFIX) :]] = json.loads(value)
            except (TypeError, ValueError) as exc:
                raise CheckpointError(
                    f"checkpoint {str(file_path)!r}: attribute {name!r} is not valid JSON ({_one_line(exc)})"
                ) from exc
        elif isinstance(value, np.generic):
            out[name] = value.item()
        else:
            out[name] = value
    return out


def _check_format(file_path: pathlib.Path, stored: Any) -> int:
    """Checks the format name and version attributes.

    Args:
        file_path: Checkpoint file, for error messages.
        stored: The root ``h5py.AttributeManager``.

    Returns:
        The format version.

    Raises:
        CheckpointError: If the file is not a warpdem checkpoint or its version is unsupported.
    """
    name = stored.get(_FORMAT_NAME_ATTR)
    if isinstance(name, bytes):
        name = name.decode("utf-8", errors="replace")
    if name is None:
        raise CheckpointError(
            f"checkpoint {str(file_path)!r}: not a warpdem checkpoint (no {_FORMAT_NAME_ATTR!r} attribute)"
        )
    if name != FORMAT_NAME:
        raise CheckpointError(
            f"checkpoint {str(file_path)!r}: format {str(name)!r} is not {FORMAT_NAME!r}, not a warpdem checkpoint"
        )
    version = stored.get(_FORMAT_VERSION_ATTR)
    if not isinstance(version, int | np.integer) or isinstance(version, bool | np.bool_):
        raise CheckpointError(f"checkpoint {str(file_path)!r}: missing or invalid format version {version!r}")
    version = int(version)
    if version > FORMAT_VERSION:
        raise CheckpointError(
            f"checkpoint {str(file_path)!r}: format version {version} is newer than the supported version "
            f"{FORMAT_VERSION}; upgrade warpdem to read it"
        )
    if version < 1:
        raise CheckpointError(f"checkpoint {str(file_path)!r}: unsupported format version {version}")
    return version


def fsync_path(path: pathlib.Path) -> None:
    """Forces a file, or a directory's entries (a completed rename), to the disk so it survives a power loss; best
    effort: a platform or file system that cannot (Windows, some network ones) is let be.

    Args:
        path: The file or directory.
    """
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _one_line(exc: BaseException) -> str:
    """Collapses an exception message (h5py's can span lines) to one line."""
    return " ".join(str(exc).split()) or type(exc).__name__
