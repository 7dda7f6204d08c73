"""EuRoC MAV datasets (ASL layout, ``mav0/``) read as recordings: only the IMU folders asked for.

A EuRoC ``mav0`` is already close to a recording: ``imu0/data.csv`` carries exactly the recording's IMU columns
and ``imu0/sensor.yaml`` Kalibr's noise keys, ``rate_hz`` and ``T_BS`` (``{cols, rows, data}``).  Its other
folders are not sensors of the recording format (``cam0/data.csv`` is ``#timestamp [ns],filename``, the
ground-truth and Leica/Vicon folders have headers of their own): they are never read, so they can never refuse
the import.

References
----------
M. Burri et al., "The EuRoC micro aerial vehicle datasets", IJRR 35(10), 2016.
"""
from __future__ import annotations

from pathlib import Path

from selfcal.io.recording import Recording, RecordingError, read_sensor

EUROC_FOLDER = "mav0"


def euroc_root(source) -> Path:
    """The ``mav0`` folder: ``source`` itself, or ``source/mav0`` when given its parent."""
    source = Path(source)
    if not source.exists():
        raise RecordingError(f"{source}: no such EuRoC dataset folder")
    if not source.is_dir():
        raise RecordingError(f"{source}: not a folder (expected an EuRoC 'mav0' folder or its parent)")
    if source.name != EUROC_FOLDER and (source / EUROC_FOLDER).is_dir():
        return source / EUROC_FOLDER
    return source


def import_euroc(source, imus=("imu0",)) -> Recording:
    """The IMU folders ``imus`` of an EuRoC dataset, as recording sensors of the same names.

    Parameters
    ----------
    source : str or Path
        The ``mav0`` folder or the folder holding it.
    imus : sequence of str
        IMU folder names inside ``mav0`` (EuRoC has one, ``imu0``).

    Returns
    -------
    Recording
        Each IMU with its columns and its ``sensor.yaml`` as they are (``T_BS`` kept), ``source`` added.

    Raises
    ------
    RecordingError
        One line: no such folder (naming the folders that hold a data.csv), or a bad IMU file.
    """
    root = euroc_root(source)
    sensors = {}
    for name in dict.fromkeys(imus):  # a name given twice is read once
        folder = root / name
        if not (folder / "data.csv").is_file():
            present = ", ".join(sorted(p.name for p in root.iterdir() if (p / "data.csv").is_file())) or "none"
            raise RecordingError(f"{root}: no {name}/data.csv (folders with a data.csv: {present})")
        sensor = read_sensor(folder)
        sensor.meta = {**sensor.meta, "source": f"euroc/{root.parent.name}/{EUROC_FOLDER}/{name}"}
        sensor.folder = None
        sensors[name] = sensor
    for name in sensors:  # the recording's IMU checks (six columns, physics), before anything is written
        Recording(path=root, sensors=sensors).imu(name)
    return Recording(path=None, sensors=sensors)
