"""The intensity scale of every LiDAR: stored intensities ↔ received signal, how a sensor writes them, and what
the data say about their unit (the cloud → signal conversion of the weather pipeline).

- The physics works on the *received signal* S, in the unit of the profile's ``sensor_constant`` K per m² (K: the
  signal of a ρ = 1 Lambertian target filling the beam at 1 m; None → the intensity full scale): a target of
  reflectance ρ at range R returns ``S = K ρ cos θ / R²``. The detection threshold (``detection_threshold``) is in
  signal units.
- ``intensity_kind`` says how a file stores it: ``signal`` (∝ received power, e.g. Ouster ``signal`` photons): I = S;
  ``reflectivity`` (range-compensated, e.g. Ouster ``reflectivity``, Velodyne 8-bit, KITTI and CARLA [0, 1]):
  ``I = W · S R² / K`` with W the profile's ``reflectivity_white_reading``, the reading of a ρ = 1 diffuse target
  (Ouster 100, Velodyne VLS-128 110; None → the full scale, i.e. the file reads ρ × full scale). Every output
  intensity goes back through the same layer, so a range-compensated file gets range-compensated weather returns.
- Outputs are stored as the sensor stores them (:func:`stored_intensity`): rounded to its step (whole counts for
  8-bit and photon units even in a float file), a return below the lowest reading is 0, the lowest reading, or no
  return (``faint_reading``, per profile).
- The unit is stated by the profile (a built-in, a file, an Ouster metadata JSON whose ``udp_profile_lidar`` names
  the channel, the recipe's ``intensity_unit``; for an Ouster signal profile also ouster-ros' fields, whose
  ``intensity`` is the signal channel next to a ``reflectivity`` field), and values it cannot hold are refused;
  when nothing states it (the default profile), :func:`read_intensity` looks at the data (integer-valued ≤ 255,
  larger counts, [0, 1], fractional floats; range-compensated or ∝ 1/R²) and :func:`resolve_profile` follows them,
  always with a warning, or refuses what no reading can place:

  - fractions — [0, 1] or beyond (Luminar's 0–2 reflectance, View-of-Delft's 0–255 floats, Waymo's 0.005–27) —
    are no photon counts (whole numbers), and a float channel's full scale is not in the data: refused, naming the
    values seen and the recipe line that states them. Read as the default photons (the policy before 2026-11-27,
    warned) they were garbage a batch user scrolls past: fog at 30 m moved every Luminar and Waymo return to < 2.4 m
    and wrote 8–55 into a 0–2 channel, snow wrote up to 7 548 into VoD's 0–255;
  - 8-bit whole counts are read as the sensor's 8-bit calibrated reflectivity (:func:`reflectivity_variant`) unless
    their bright end falls as 1/R² (signal photons, which stay): most 8-bit channels are reflectivity (Velodyne,
    Livox, Hesai, Ouster RFL8), and read as photons a reflectivity channel's returns all look too faint to survive
    any weather, while read as reflectivity a weak photon channel stays within 0–255;
  - a cloud whose returns all read 0 carries no return strength (a map or converter that did not fill the channel:
    hku-mars/mlcc's Livox maps), stated or not: every return would be lost to the faintest fog — refused.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..errors import ModelError
from ..types import IntensityUnit, LidarProfile
from .compiled import jit

SIGNAL, REFLECTIVITY = "signal", "reflectivity"    # LidarProfile.intensity_kind
FAINT_READINGS = ("zero", "lowest", "no_return")    # LidarProfile.faint_reading
#: units stored in whole counts (resolution 1)
COUNT_UNITS = (IntensityUnit.PHOTONS, IntensityUnit.UINT8)
OUSTER_WHITE_REFLECTIVITY = 100.0       # calibrated-reflectivity reading of a diffuse white target (Ouster)


def sensor_constant(profile: LidarProfile) -> float:
    """K: received signal of a ρ = 1 Lambertian target filling the beam at 1 m (signal units · m²); None in the
    profile → the intensity full scale."""
    return float(profile.intensity_full_scale if profile.sensor_constant is None else profile.sensor_constant)


def white_reading(profile: LidarProfile) -> float:
    """W: the stored reading of a ρ = 1 diffuse target in a ``reflectivity`` file (Ouster 100, VLS-128 110); None in
    the profile → the intensity full scale (KITTI, CARLA: the reading is ρ × full scale)."""
    w = profile.reflectivity_white_reading
    return float(profile.intensity_full_scale if w is None else w)


def _unknown_kind(profile: LidarProfile) -> ModelError:
    return ModelError(f"profile {profile.name!r} has intensity_kind {profile.intensity_kind!r}; expected "
                      f"{SIGNAL!r} or {REFLECTIVITY!r}", field="intensity_kind")


def received_signal(intensity, range_m, profile: LidarProfile) -> np.ndarray:
    """Received signal S (signal units) of stored intensities at their ranges: I for ``signal`` profiles,
    ``(I / W) · K / R²`` for range-compensated ``reflectivity`` profiles (W: :func:`white_reading`; 0 where R ≤ 0:
    no return)."""
    i = np.asarray(intensity, dtype=np.float64)
    if profile.intensity_kind == SIGNAL:
        return i
    if profile.intensity_kind == REFLECTIVITY:
        r = np.asarray(range_m, dtype=np.float64)
        scale = sensor_constant(profile) / white_reading(profile)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(r > 0, i * scale / (r * r), 0.0)
    raise _unknown_kind(profile)


def reported_intensity(signal, range_m, profile: LidarProfile) -> np.ndarray:
    """Inverse of :func:`received_signal`: the intensity a profile stores for a return of signal S at apparent range
    R (S for ``signal``, ``W · S R² / K`` for ``reflectivity``); not clipped."""
    s = np.asarray(signal, dtype=np.float64)
    if profile.intensity_kind == SIGNAL:
        return s
    if profile.intensity_kind == REFLECTIVITY:
        r = np.asarray(range_m, dtype=np.float64)
        return s * (r * r) * (white_reading(profile) / sensor_constant(profile))
    raise _unknown_kind(profile)


def intensity_step(profile: LidarProfile) -> float:
    """The resolution a sensor stores its intensity with: the profile's ``intensity_step``, else 1 for count units
    (photons, 8-bit) and 0 (continuous) for [0, 1] floats. Outputs are rounded to it (:func:`stored_intensity`)."""
    if profile.intensity_step is not None:
        return float(profile.intensity_step)
    return 1.0 if profile.intensity_unit in COUNT_UNITS else 0.0


def intensity_resolution(profile: LidarProfile) -> float:
    """The smallest visible change of the stored intensity (effect codes): one step (:func:`intensity_step`), or full scale
    / 255 for continuous values."""
    return intensity_step(profile) or profile.intensity_full_scale / 255.0


def rounded_intensity(reported, profile: LidarProfile) -> np.ndarray:
    """Reported intensities clipped to full scale and rounded to the sensor's step (:func:`intensity_step`)."""
    v = np.minimum(np.asarray(reported, dtype=np.float64), profile.intensity_full_scale)
    step = intensity_step(profile)
    return v if step == 0 else np.round(v / step) * step


def stored_intensity(reported, profile: LidarProfile) -> np.ndarray:
    """What the sensor stores for reported intensities (≥ 0): :func:`rounded_intensity`; a positive value that rounds
    to 0 is 0 (``faint_reading: zero``) or one step (``lowest``). A ``no_return`` sensor drops such returns
    (:func:`too_faint`) before they are stored."""
    v = np.asarray(reported, dtype=np.float64)
    out = rounded_intensity(v, profile)
    step = intensity_step(profile)
    if profile.faint_reading == "lowest" and step > 0:
        out = np.where((out == 0) & (v > 0), step, out)
    return out


def stored_signal(signal, range_m, profile: LidarProfile) -> np.ndarray:
    """What the sensor stores for returns of signal S (units of the sensor constant K) at apparent range R:
    :func:`stored_intensity` of :func:`reported_intensity` of ``S·K``, in one compiled pass with the same arithmetic
    (the same values)."""
    if profile.intensity_kind not in (SIGNAL, REFLECTIVITY):
        raise _unknown_kind(profile)
    k = sensor_constant(profile)
    compensated = profile.intensity_kind == REFLECTIVITY
    step = intensity_step(profile)
    return _stored_signal(np.ascontiguousarray(signal, dtype=np.float64),
                          np.ascontiguousarray(range_m, dtype=np.float64), k, compensated,
                          white_reading(profile) / k if compensated else 1.0, float(profile.intensity_full_scale),
                          step, profile.faint_reading == "lowest" and step > 0)


@jit
def _stored_signal(signal, range_m, k, compensated, per, full_scale, step, lowest):       # pragma: no cover - compiled
    """:func:`stored_signal` per return: reported ``S·K`` (times ``R² · per`` when range-compensated), clipped to
    full scale, rounded half to even to the step, a positive value rounded to 0 raised to one step when ``lowest``."""
    out = np.empty(len(signal))
    for i in range(len(signal)):
        v = signal[i] * k
        if compensated:
            v = v * (range_m[i] * range_m[i]) * per
        o = full_scale if v > full_scale else v
        if step != 0.0:
            o = np.rint(o / step) * step
        if lowest and o == 0.0 and v > 0.0:
            o = step
        out[i] = o
    return out


def too_faint(reported, profile: LidarProfile) -> np.ndarray:
    """Returns a ``faint_reading: no_return`` sensor drops: reported below half a step (all False for the others)."""
    r = np.asarray(reported, dtype=np.float64)
    if profile.faint_reading != "no_return" or intensity_step(profile) == 0:
        return np.zeros(r.shape, dtype=bool)
    return r < 0.5 * intensity_step(profile)



# ---------------------------------------------------------------------------------------------------------------
# What the data say


READING_SAMPLE = 8192              # returns looked at (evenly strided)
RANGE_BINS_M = np.geomspace(2.0, 150.0, 13)
MIN_PER_BIN = 30
REFLECTIVITY_SLOPE = -0.6          # d log(I_90) / d log R above this: range-compensated
SIGNAL_SLOPE = -1.4                # below this: ∝ 1/R² (received signal)


@dataclass(frozen=True)
class IntensityReading:
    """What a cloud's intensities look like: ``values`` ('[0, 1]', '8-bit counts', 'counts', 'floats', 'none'),
    ``kind`` ('signal', 'reflectivity' or None when the data cannot tell) from ``slope``, the slope of the 90th
    percentile of log I over log R (range-compensated data: ≈ 0, received signal: ≈ −2; nan without enough
    ranges)."""

    values: str
    kind: str | None
    slope: float

    def describe(self) -> str:
        slope = "" if np.isnan(self.slope) else f", log I ∝ {self.slope:+.2f} log R"
        return f"{self.values}{slope}"


def read_intensity(intensity: np.ndarray, positions_m: np.ndarray) -> IntensityReading:
    """Look at the returns' intensities (points not at the origin; about 8 000, evenly strided): their values, and
    whether their strong end (90th percentile per range bin, 2–150 m) falls as 1/R² (signal) or stays
    (reflectivity)."""
    stride = max(1, len(intensity) // READING_SAMPLE)
    r = np.linalg.norm(np.asarray(positions_m)[::stride], axis=1)
    ok = r > 0
    i, r = np.asarray(intensity)[::stride][ok].astype(np.float64), r[ok]
    if len(i) == 0:
        return IntensityReading("none", None, float("nan"))
    top = float(i.max())
    integral = bool(np.all(i == np.rint(i)))
    values = ("8-bit counts" if integral and top <= 255 else "counts" if integral
              else "[0, 1]" if top <= 1.0 else "floats")
    bins = np.digitize(r, RANGE_BINS_M)
    xs, ys = [], []
    for b in range(1, len(RANGE_BINS_M)):
        sel = (bins == b) & (i > 0)
        if np.count_nonzero(sel) >= MIN_PER_BIN:
            xs.append(np.log(np.sqrt(RANGE_BINS_M[b - 1] * RANGE_BINS_M[b])))
            ys.append(np.log(np.percentile(i[sel], 90)))
    if len(xs) < 4 or xs[-1] - xs[0] < np.log(4.0):
        return IntensityReading(values, None, float("nan"))
    slope = float(np.polyfit(xs, ys, 1)[0])
    kind = REFLECTIVITY if slope > REFLECTIVITY_SLOPE else SIGNAL if slope < SIGNAL_SLOPE else None
    return IntensityReading(values, kind, slope)


def check_intensity_scale(intensity: np.ndarray, profile: LidarProfile, model_id: str) -> None:
    """Refuse intensities that contradict the profile (the classic "0–1 cloud read as photons" mistake)."""
    if len(intensity) == 0:
        return
    top = float(np.max(intensity))
    fs = profile.intensity_full_scale
    if top > fs * (1 + 1e-6):
        raise ModelError(f"intensities reach {top:g} but profile {profile.name!r} says full scale {fs:g} "
                         f"({profile.intensity_unit}); give the profile matching the data", model=model_id,
                         field="intensity")
    if (profile.intensity_unit != IntensityUnit.UNIT and np.issubdtype(intensity.dtype, np.floating)
            and len(intensity) >= 100 and 0 < top <= 1.0):
        raise _unit_scale_error(profile, model_id)


def _unit_scale_error(profile: LidarProfile, model_id: str) -> ModelError:
    return ModelError(f"all intensities are within [0, 1] but profile {profile.name!r} expects "
                      f"{profile.intensity_unit} up to {profile.intensity_full_scale:g}; use a profile with "
                      f"intensity_unit 'unit' (e.g. kitti-hdl64, carla-64), or state the unit: 'intensity_unit: "
                      f"unit' in the recipe's inputs (a bag recipe: the topic's entry), in a lidar.yaml next to the "
                      f"files or given as --lidar-profile FILE.yaml", model=model_id, field="intensity")


def reflectivity_variant(profile: LidarProfile) -> LidarProfile:
    """The same (Ouster) sensor storing its 8-bit calibrated reflectivity, as in the RNG15_RFL8_NIR8 and RFL8
    channels: a diffuse white target reads 100 (:data:`OUSTER_WHITE_REFLECTIVITY`), readings below 1 are stored as 1
    (``faint_reading: lowest``)."""
    return dataclasses.replace(profile, intensity_unit=IntensityUnit.UINT8, intensity_full_scale=255.0,
                               intensity_kind=REFLECTIVITY, reflectivity_white_reading=OUSTER_WHITE_REFLECTIVITY,
                               intensity_step=None, faint_reading="lowest")


@dataclass(frozen=True)
class IntensityScale:
    """The profile a weather model converts intensities with, how it was decided (``note``, for the manifest) and
    the warning to print when the data and the stated unit disagree or nothing stated it (None: none)."""

    profile: LidarProfile
    note: str
    warning: str | None = None


class IntensityWarning(UserWarning):
    """The data and the stated intensity unit disagree, or nothing stated it (printed once per process and
    message; the manifest records it per file)."""


def chain_intensity_scale(cloud, model_id: str) -> IntensityScale:
    """:func:`resolve_profile` of the sensor's own data: the chain's input (``cloud.recorded``) when an earlier step
    ran, else ``cloud`` — a unit is a property of the sensor, and an earlier step (laser power variance's gains)
    changes what the intensities look like. The intensities as they are now are then checked against the scale
    decided (:func:`check_intensity_scale`)."""
    source = cloud.recorded if cloud.recorded is not None and "intensity" in cloud.recorded.fields else cloud
    scale = resolve_profile(cloud.profile, np.asarray(source.fields["intensity"]), source.positions_m, model_id,
                            source.fields.get("ring"), ouster=not OUSTER_FIELDS.isdisjoint(source.fields),
                            ouster_signal=ouster_signal_layout(source.fields))
    if source is not cloud:
        check_intensity_scale(np.asarray(cloud.fields["intensity"]), scale.profile, model_id)
    return scale


def resolve_profile(profile: LidarProfile, intensity: np.ndarray, positions_m: np.ndarray,
                    model_id: str, ring: np.ndarray | None = None, ouster: bool = False,
                    ouster_signal: bool = False) -> IntensityScale:
    """The intensity scale of a cloud: the profile's when it states it (``intensity_source``; values it cannot hold
    are refused); when nothing states it (the default profile, an Ouster JSON whose packet profile carries both
    channels), the data decide (:func:`read_intensity`) — 8-bit whole counts are read as the sensor's calibrated
    reflectivity (:func:`reflectivity_variant`) unless they fall as 1/R² (signal), fractions ([0, 1] against a
    count unit, or beyond: :func:`fraction_error`) are refused however few points there are — and the warning says
    what was assumed, what the data showed and how to state it. Never silent. Returns that all read 0 are refused,
    stated or not (:func:`no_strength_error`). A stated unit is not second-guessed: an earlier step of a chain (laser
    power variance) may have changed what the intensities look like. ``ring``: the cloud's ring field, if any; when
    it counts at most half the profile's beams, the warning says so (a nuScenes HDL-32E scan read with the default
    OS1-128, :func:`beam_count_hint`; ``ouster``: the cloud has the fields only an Ouster driver writes); without one, when its returns lie above or below the profile's beams
    (:func:`elevation_span_hint`). ``ouster_signal``: the cloud's fields are ouster-ros' (:func:`ouster_signal_layout`),
    whose intensity is the signal channel: an Ouster signal profile (the default, a metadata JSON whose packet
    profile carries signal) is then stated by them."""
    check_intensity_scale(intensity, profile, model_id)
    if profile.intensity_kind not in (SIGNAL, REFLECTIVITY):
        raise _unknown_kind(profile)
    if no_strength(intensity, positions_m):
        raise no_strength_error(model_id)
    said = f"{profile.intensity_kind} in {profile.intensity_unit} (full scale {profile.intensity_full_scale:g})"
    if profile.intensity_source:
        return IntensityScale(profile, f"{said}, stated by {profile.intensity_source}")
    if ouster_signal and profile.intensity_kind == SIGNAL and profile.intensity_unit == IntensityUnit.PHOTONS:
        return IntensityScale(profile, f"{said}, stated by the cloud's fields (ouster-ros: the intensity is the "
                                       f"signal channel, reflectivity a field of its own)")
    reading = read_intensity(intensity, positions_m)
    if reading.values == "[0, 1]" and profile.intensity_unit != IntensityUnit.UNIT:
        raise _unit_scale_error(profile, model_id)          # however few points: nothing says they are photons
    if reading.values == "floats":
        raise fraction_error(intensity, model_id)
    how = ("give lidar_profile (e.g. os1-128 for Ouster signal photons, os1-128-reflectivity for its 8-bit "
           "reflectivity, hdl-32e for nuScenes) or intensity_unit in the recipe")
    how += beam_count_hint(profile, ring, ouster) if ring is not None else elevation_span_hint(profile, positions_m)
    if reading.values == "8-bit counts" and reading.kind != SIGNAL and profile.intensity_kind == SIGNAL:
        adopted = dataclasses.replace(reflectivity_variant(profile), intensity_source="the data")
        seen, read_as = (("look like 8-bit range-compensated reflectivity", "such") if reading.kind == REFLECTIVITY
                         else ("are 8-bit whole counts whose range slope cannot tell signal from reflectivity",
                               "8-bit reflectivity, as most 8-bit channels are,"))
        return IntensityScale(adopted, f"8-bit reflectivity read from the data ({reading.describe()}); nothing "
                                       f"stated the unit",
                              f"{model_id}: no profile states the intensity unit and the data {seen} "
                              f"({reading.describe()}): read as {read_as} with profile {profile.name!r}'s sensor; "
                              f"{how}")
    if reading.kind == profile.intensity_kind:
        return IntensityScale(profile, f"{said}: nothing stated it, the data agree ({reading.describe()})")
    seen = "do not tell" if reading.kind is None else f"look like {reading.kind} but not like an 8-bit channel"
    return IntensityScale(profile, f"{said}: nothing stated it, assumed ({reading.describe()})",
                          f"{model_id}: no profile states the intensity unit and the data {seen} "
                          f"({reading.describe()}): read as {said}; {how}")


def fraction_error(intensity: np.ndarray, model_id: str) -> ModelError:
    """Fractional intensities beyond [0, 1] whose unit nothing states: no photon counts (whole numbers), and the full
    scale of a float channel is not in the data (Luminar 0–2, View-of-Delft 0–255, Waymo 0.005–27). The error names
    the values seen and the lines that state them; the runner and preview prefix the file."""
    v = np.asarray(intensity)
    return ModelError(f"intensities {float(v.min()):g} … {float(v.max()):g} have fractions and nothing states their "
                      f"unit: they are no photon counts (whole numbers), and a float channel's full scale is not in "
                      f"the data. State it: 'intensity_unit: unit' and 'intensity_full_scale: F' (F: the "
                      f"channel's full scale, at least {float(v.max()):g}) in the recipe's inputs (a bag recipe: "
                      f"the topic's entry), in a lidar.yaml next to the files or given as --lidar-profile FILE.yaml, "
                      f"or 'lidar_profile: NAME' of a profile whose unit holds them", model=model_id,
                      field="intensity")


def no_strength(intensity: np.ndarray, positions_m: np.ndarray) -> bool:
    """Whether a cloud has returns and all of them read 0 (an evenly strided sample first: a real scan's first
    non-zero value ends it there, in microseconds)."""
    v = np.asarray(intensity)
    return not np.any(v[::max(1, len(v) // READING_SAMPLE)]) and not np.any(v) and bool(np.any(positions_m))


def no_strength_error(model_id: str) -> ModelError:
    """Every return reads 0: the cloud carries no return strength (hku-mars/mlcc's Livox maps), and a weather model
    would lose every return to the faintest particle."""
    return ModelError("every return's intensity is 0: the cloud carries no return strength (a map, or a converter "
                      "that did not fill the channel), and the LiDAR weather and power models need it; give the "
                      "sensor's own scans", model=model_id, field="intensity")


#: built-in profiles to suggest for a ring field counting this many beams
PROFILE_FOR_BEAMS = {32: "hdl-32e for a Velodyne HDL-32E (nuScenes)", 64: "kitti-hdl64 for KITTI, carla-64 for CARLA"}
#: fields only Ouster's drivers write (ouster-ros: ambient; ouster-sdk and newer ouster-ros: near_ir; ouster_ros 1.x
#: of ouster_example: noise, its point ``x y z intensity t reflectivity ring noise range``); Livox writes
#: ``reflectivity`` too, so that one says nothing
OUSTER_FIELDS = frozenset({"ambient", "near_ir", "noise"})


def ouster_signal_layout(fields) -> bool:
    """Whether a cloud's fields (canonical names) are ouster-ros' with the signal channel as its intensity: an Ouster
    field (:data:`OUSTER_FIELDS`) and a ``reflectivity`` field besides the intensity (ouster-ros' default point:
    ``intensity`` is the signal photons; its native point: ``signal``). A cloud whose only strength field is
    ``reflectivity`` reads that one as its intensity and has no such second field."""
    return "intensity" in fields and "reflectivity" in fields and not OUSTER_FIELDS.isdisjoint(fields)


def reflectivity_following(fields, rows: np.ndarray, before, after) -> dict:
    """``{"reflectivity": values}`` of an ouster-ros cloud (:func:`ouster_signal_layout`) whose returns ``rows`` kept
    their range while their stored signal went from ``before`` to ``after`` (weather, soiling, laser power); ``{}``
    for any other cloud. The sensor computes its calibrated reflectivity from the signal photons it measured, scaled
    by range and its sensitivity (Ouster FW user manual, "Calibrated Reflectivity"), so at an unchanged range the
    reading follows the signal (models.md §3.1: I_hard = I·exp(−2αR)): ``rint(ρ · after / before)``, the unit's
    own calibration kept (not the profile's W·S·R²/K, which weather returns get: :mod:`io.derived_fields`); at
    least 1 for a return that read ≥ 1 (the channel's faintest reading, :func:`reflectivity_variant`), at most 255
    (or its recorded value above); a return recorded with signal 0 keeps its reading."""
    if not ouster_signal_layout(fields) or not len(rows):
        return {}
    values = np.asarray(fields["reflectivity"])
    read = values[rows].astype(np.float64)
    before = np.asarray(before, dtype=np.float64)
    ratio = np.where(before > 0, np.asarray(after, dtype=np.float64) / np.where(before > 0, before, 1.0), 1.0)
    out = values.copy()
    out[rows] = np.minimum(np.maximum(np.rint(read * ratio), np.minimum(read, 1.0)),
                           np.maximum(read, 255.0)).astype(values.dtype)
    return {"reflectivity": out}


OUSTER_FIT = "FILE.json, the unit's Ouster metadata (its beam angles and packet profile)"


def beam_count_hint(profile: LidarProfile, ring: np.ndarray | None, ouster: bool = False) -> str:
    """'' or a note for the warning when a cloud's ring field counts at most half the profile's beams: its rings
    then index the profile's first beams, which are other beams of another sensor. ``ouster``: the cloud has
    Ouster's fields (:data:`OUSTER_FIELDS`: an OS-0/1/2-32 or -64 from ouster-ros), so the fitting profile is its
    metadata JSON, not a Velodyne's of as many beams."""
    if ring is None or len(ring) == 0 or not np.issubdtype(np.asarray(ring).dtype, np.number):
        return ""
    beams = int(np.max(ring)) + 1
    if beams > profile.channels // 2:
        return ""
    fit = OUSTER_FIT if ouster else PROFILE_FOR_BEAMS.get(beams)
    return (f"; the cloud's ring field counts {beams} beams (0…{beams - 1}) but profile {profile.name!r} has "
            f"{profile.channels}, so its rings index other beams" + (f": give lidar_profile {fit}" if fit else ""))


SPAN_MARGIN_DEG = 1.0          # returns this far beyond a profile's outermost beams are not its beams'
SPAN_MIN_RANGE_M = 2.0         # nearer returns' elevations carry the beam-origin offset (15 mm: 0.4° at 2 m)


def elevation_span_hint(profile: LidarProfile, positions_m: np.ndarray) -> str:
    """'' or a note for the warning when a cloud's returns (beyond 2 m; 0.1 … 99.9 percentile) reach elevations
    more than 1° above or below the profile's outermost beams — another sensor's scan (a Velodyne HDL-32E's
    −30.7° … +10.7° read with the default OS1-128's ±22.5°: its weather fills 128 beams the sensor does not have) —
    naming the built-in profiles whose beams span them. An odd stride samples every beam of a beam-interleaved
    list (an even one would see only every other ring of a 32-beam scan stored column by column)."""
    p = np.asarray(positions_m)[::max(1, len(positions_m) // READING_SAMPLE) | 1]
    r = np.linalg.norm(p, axis=1)
    far = r > SPAN_MIN_RANGE_M
    if np.count_nonzero(far) < MIN_PER_BIN or not profile.beam_elevation_deg:
        return ""
    low, high = np.percentile(np.degrees(np.arcsin(p[far, 2] / r[far])), [0.1, 99.9])

    def spans(beams) -> bool:
        return min(beams) - SPAN_MARGIN_DEG <= low and high <= max(beams) + SPAN_MARGIN_DEG

    if spans(profile.beam_elevation_deg):
        return ""
    from ..profiles.lidar import BUILTIN

    fit = [name for name, make in BUILTIN.items() if spans(make().beam_elevation_deg)]
    return (f"; the cloud's returns span elevations {low:+.1f}° … {high:+.1f}° but profile {profile.name!r}'s beams "
            f"{min(profile.beam_elevation_deg):+.1f}° … {max(profile.beam_elevation_deg):+.1f}°, so they are "
            f"another sensor's (or a tilted mount's)" + (f": give lidar_profile {' or '.join(fit)}" if fit else ""))
