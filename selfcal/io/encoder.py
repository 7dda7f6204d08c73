"""Encoder recordings: diode-array frames next to the ASL ``data.csv`` (see ``docs/encoder.md``).

``REC/array<k>/data.csv``   ``#timestamp [ns]`` plus auxiliary columns (``temperature [degC]``, ...), one row per frame
``REC/array<k>/frames.npy`` (N, n) float signal vectors (ADC counts), row J taken at row J's timestamp
``REC/array<k>/sensor.yaml`` ``n_diodes``, ``code_length_l``, ``geometry_nominal: {p, q}``, ``aperture_nominal``
                            ``[t-, t+]``, optional ``adc_max``, ``noise_sigma_counts``, ``array_offset_nominal_rad``,
                            ``illumination_degree``, ``eccentricity_kappa``
``REC/reference/data.csv``  optional ``angle [rad]`` of some positions (mixed calibration); ``reference/sensor.yaml``
                            ``angle_sigma_rad``

Errors a user can cause raise :class:`EncoderRecordingError` (a RecordingError: one line, exit code 1).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

from selfcal.io.atomic import atomic_write_text
from selfcal.io.recording import Recording, RecordingError

ARRAY_RE = re.compile(r"^array(\d+)$")


class EncoderRecordingError(RecordingError):
    """Bad encoder recording (frames of the wrong width, missing sensor.yaml keys, ...)."""


@dataclass
class EncoderArray:
    name: str
    t_ns: np.ndarray
    frames: np.ndarray                  # (N, n)
    meta: dict
    channels: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n_diodes(self) -> int:
        return int(self.frames.shape[1])

    def geometry_nominal(self) -> np.ndarray:
        g = self.meta.get("geometry_nominal", {})
        return np.array([float(g.get(k, 0.0)) for k in ("p", "q", "u", "v", "x", "y")])

    def aperture_nominal(self) -> np.ndarray:
        if "aperture_nominal" in self.meta:
            return np.asarray(self.meta["aperture_nominal"], dtype=float)
        pitch = 2.0 / self.n_diodes
        return np.array([0.6 * pitch, 1.6 * pitch])


def _where(rec: Recording, name: str) -> str:
    return f"{rec.path}/{name}" if rec.path is not None else name


def array_names(rec: Recording) -> list[str]:
    return sorted((s for s in rec.sensors if ARRAY_RE.match(s)), key=lambda s: int(ARRAY_RE.match(s).group(1)))


def read_encoder_arrays(rec: Recording, frames: dict[str, np.ndarray] | None = None) -> list[EncoderArray]:
    """Every ``array<k>`` of a recording, frames loaded from ``frames.npy`` and checked.

    ``frames`` may give the arrays in memory (name -> (N, n)) instead of files.
    """
    names = array_names(rec)
    if not names:
        raise EncoderRecordingError(f"{_where(rec, '')}: no array<k> sensor folder (an encoder recording has "
                                    "array0/data.csv, array0/frames.npy, array0/sensor.yaml)")
    out = []
    for name in names:
        s = rec.sensors[name]
        where = _where(rec, name)
        meta = s.meta
        for key in ("n_diodes", "code_length_l"):
            if key not in meta:
                raise EncoderRecordingError(f"{where}/sensor.yaml: missing key {key!r}")
        if "p" not in (meta.get("geometry_nominal") or {}):
            raise EncoderRecordingError(f"{where}/sensor.yaml: missing geometry_nominal.p (half field of view)")
        if frames is not None and name in frames:
            data = np.asarray(frames[name])
        else:
            if s.folder is None or not (s.folder / "frames.npy").is_file():
                raise EncoderRecordingError(f"{where}/frames.npy: missing (the array's signal vectors)")
            try:
                data = np.load(s.folder / "frames.npy", allow_pickle=False)
            except (ValueError, OSError, EOFError) as err:  # EOFError: an empty file (a run killed at its start)
                raise EncoderRecordingError(f"{where}/frames.npy: not a numpy array file "
                                            f"({' '.join(str(err).split()) or type(err).__name__})") from None
        n = int(meta["n_diodes"])
        if data.ndim != 2:
            raise EncoderRecordingError(f"{where}/frames.npy: expected a 2-D array (frames x diodes), "
                                        f"got shape {data.shape}")
        if data.shape[1] != n:
            raise EncoderRecordingError(f"{where}/frames.npy: frames are {data.shape[1]} diodes wide, "
                                        f"sensor.yaml says n_diodes: {n}")
        if data.shape[0] != s.t_ns.size:
            raise EncoderRecordingError(f"{where}/frames.npy: {data.shape[0]} frames, data.csv has "
                                        f"{s.t_ns.size} rows")
        if not np.issubdtype(data.dtype, np.number):
            raise EncoderRecordingError(f"{where}/frames.npy: dtype {data.dtype} is not numeric")
        _check_counts(data, meta, f"{where}/frames.npy")
        data = data.astype(float)
        if not np.isfinite(data).all():
            J = int(np.argmax(~np.isfinite(data).all(axis=1)))
            raise EncoderRecordingError(f"{where}/frames.npy: frame {J} holds NaN or inf")
        _check_independent_exposures(data, meta, f"{where}/frames.npy")
        out.append(EncoderArray(name, s.t_ns, data, meta, dict(s.values)))
    l = {int(a.meta["code_length_l"]) for a in out}
    if len(l) != 1:
        raise EncoderRecordingError(f"{_where(rec, '')}: arrays disagree on code_length_l ({sorted(l)})")
    if len(out) > 1 and any(a.t_ns.size != out[0].t_ns.size or np.any(a.t_ns != out[0].t_ns) for a in out[1:]):
        raise EncoderRecordingError(f"{_where(rec, '')}: arrays must record the same positions (same timestamps)")
    return out


def _check_counts(data: np.ndarray, meta: dict, where: str) -> None:
    """ADC counts lie in [0, adc_max] up to the noise: a type that cannot hold the ADC's range, or counts beyond it
    (a signed cast wraps 200 to -56), are refused, never calibrated (a cast to int8 gave 24 urad against 6.5)."""
    if "adc_max" not in meta:
        return
    adc_max = float(meta["adc_max"])
    if np.issubdtype(data.dtype, np.integer) and np.iinfo(data.dtype).max < adc_max:
        raise EncoderRecordingError(f"{where}: {data.dtype} holds at most {np.iinfo(data.dtype).max} counts, the "
                                    f"ADC reaches adc_max {adc_max:g}: the frames were cast and wrapped; write the "
                                    "original counts")
    margin = 5.0 * float(meta.get("noise_sigma_counts", 1.0))
    with np.errstate(invalid="ignore"):
        outside = (data < -margin) | (data > adc_max + margin)
    if outside.any():
        J, i = np.argwhere(outside)[0]
        raise EncoderRecordingError(f"{where}: frame {J} diode {i} reads {data[J, i]:g} counts, outside the ADC's "
                                    f"[0, {adc_max:g}] (+-5 noise sigma): wrapped or mis-scaled counts")


def _check_independent_exposures(data: np.ndarray, meta: dict, where: str) -> None:
    """Two exposures of a noisy array never agree on every diode (with sigma >= 1 count, a repeat of all n
    diodes has probability below 0.4^n): identical frames are a repeated buffer, not new measurements, and
    counting them would shrink every sigma (60 copies of one frame gave a 6 urad graduation error)."""
    if float(meta.get("noise_sigma_counts", 1.0)) < 1.0 or len(data) < 2:
        return  # noise below one count: equal frames can be honest repeats
    _, first, counts = np.unique(data, axis=0, return_index=True, return_counts=True)
    if counts.max() > 1:
        J = int(first[np.argmax(counts)])
        raise EncoderRecordingError(f"{where}: {int((counts - 1).sum())} frame(s) repeat another exactly (frame {J} "
                                    f"{counts.max()} times): a repeated buffer, not new exposures; remove the copies")


@dataclass
class ReferenceAngles:
    t_ns: np.ndarray
    angle_rad: np.ndarray
    sigma_rad: float


def read_reference(rec: Recording) -> ReferenceAngles | None:
    """``reference/data.csv`` (``angle [rad]``) with ``angle_sigma_rad`` from its sensor.yaml, or None."""
    s = rec.sensors.get("reference")
    if s is None:
        return None
    where = _where(rec, "reference")
    if "angle" not in s.values:
        raise EncoderRecordingError(f"{where}/data.csv: needs a column 'angle [rad]'")
    if s.units.get("angle") != "rad":
        raise EncoderRecordingError(f"{where}/data.csv: column angle has unit [{s.units.get('angle')}], expected [rad]")
    sigma = float(s.meta.get("angle_sigma_rad", 0.0))
    if not sigma > 0:
        raise EncoderRecordingError(f"{where}/sensor.yaml: angle_sigma_rad must be given and positive")
    return ReferenceAngles(s.t_ns, s.values["angle"], sigma)


def write_angles_csv(path, t_ns, angle_rad, sigma_rad, flags, extra=()) -> None:
    """``#timestamp [ns],angle [rad],angle_sigma [rad],valid [1],flag [text]`` (atomically), then the ``extra``
    columns: ``(header "name [unit]", values)`` pairs (e.g. the tracked drift parameters)."""
    extra = list(extra)
    lines = ["#timestamp [ns],angle [rad],angle_sigma [rad],valid [1],flag [text]"
             + "".join(f",{h}" for h, _ in extra)]
    txt = lambda x: repr(float(x)) if math.isfinite(x) else "nan"  # noqa: E731
    for i, (t, a, s, f) in enumerate(zip(t_ns, angle_rad, sigma_rad, flags)):
        lines.append(f"{int(t)},{txt(a)},{txt(s)},{0 if f else 1},{f or 'ok'}"
                     + "".join(f",{txt(v[i])}" for _, v in extra))
    atomic_write_text(path, "\n".join(lines) + "\n")
